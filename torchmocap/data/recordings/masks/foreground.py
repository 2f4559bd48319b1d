"""Foreground by colour difference from the background, robust to shadows, then cleaned up.

A shadow darkens the background but keeps its chromaticity; so each frame colour ``I`` is split
against the background colour ``B`` (Horprasert et al.'s decomposition) into a brightness ratio
``α = I·B / B·B`` and a chromatic distortion ``‖I − αB‖`` (grey levels). A pixel is foreground
when the chromatic distortion exceeds ``threshold`` noise standard deviations, or when its
brightness changes by more than that and ``α`` leaves the shadow/highlight range
``[shadow_min, highlight_max]``.
"""

from __future__ import annotations

from torch import Tensor

from torchmocap.data.recordings.masks.background import BackgroundModel
from torchmocap.data.recordings.masks.morphology import (
    closing,
    drop_small_components,
    fill_holes,
    opening,
)
from torchmocap.data.recordings.masks.settings import MaskSettings

__all__ = ["clean_masks", "colour_distortion", "foreground_masks"]


def colour_distortion(images: Tensor, background: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Brightness ratio and chromatic distortion of ``images`` against ``background``.

    Args:
        images: ``(*, 3, H, W)`` RGB (any range; uint8 is converted to float32).
        background: ``(*, 3, H, W)`` RGB broadcastable to ``images``.

    Returns:
        ``alpha (*, H, W)``: ``I·B / B·B`` (1 = unchanged, < 1 darker along the background's
        colour); ``chroma (*, H, W)``: ``‖I − αB‖``; ``brightness (*, H, W)``:
        ``(α − 1)‖B‖``, the signed brightness change in the units of the input.

    Example:
        >>> import torch
        >>> bg = torch.full((3, 2, 2), 100.0)
        >>> a, cd, db = colour_distortion(bg * 0.6, bg)  # a shadow: darker, same chroma
        >>> round(float(a[0, 0]), 4), round(float(cd[0, 0]), 4), round(float(db[0, 0]), 2)
        (0.6, 0.0, -69.28)
    """
    I = images.float() if not images.is_floating_point() else images
    B = background.to(I.dtype)
    i0, i1, i2 = I.unbind(-3)
    b0, b1, b2 = B.unbind(-3)
    bb = (b0 * b0 + b1 * b1 + b2 * b2).clamp_min(1e-6)
    alpha = (i0 * b0 + i1 * b1 + i2 * b2) / bb
    chroma = ((i0 - alpha * b0).square() + (i1 - alpha * b1).square()
              + (i2 - alpha * b2).square()).sqrt()
    brightness = (alpha - 1) * bb.sqrt()
    return alpha, chroma, brightness


def foreground_masks(frames: Tensor, background: BackgroundModel, settings: MaskSettings
                     ) -> Tensor:
    """Raw foreground ``(T, C, H, W)`` bool of ``frames (T, C, 3, H, W)`` (uint8 or float)
    against ``background`` (threshold, shadow_min, highlight_max of ``settings``)."""
    alpha, chroma, brightness = colour_distortion(frames, background.colour)
    tau = settings.threshold * background.noise  # (C, H, W), broadcast over T
    changed = brightness.abs() > tau
    outside = (alpha < settings.shadow_min) | (alpha > settings.highlight_max)
    return (chroma > tau) | (changed & outside)


def _radius(fraction: float, height: int) -> int:
    return max(1, round(fraction * height)) if fraction > 0 else 0


def clean_masks(masks: Tensor, valid: Tensor, settings: MaskSettings) -> Tensor:
    """Opening, closing, hole filling and small-component removal of ``(T, C, H, W)`` masks,
    restricted to each camera's ``valid (C, H, W)`` region (sizes from ``settings``)."""
    T, C, H, W = masks.shape
    m = (masks & valid).reshape(T * C, H, W)
    m = opening(m, _radius(settings.open_size, H))
    m = closing(m, _radius(settings.close_size, H))
    if settings.fill_holes:
        m = fill_holes(m)
    m = drop_small_components(m, round(settings.min_area * H * W))
    return m.reshape(T, C, H, W) & valid
