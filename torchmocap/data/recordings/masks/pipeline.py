"""``compute_masks``: foreground masks of a multi-view recording from its frames alone (plus
background plates and the subject's 2D detections when there are some)."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from torchmocap.cameras.rig import CameraRig
from torchmocap.data.recordings.masks.background import estimate_background
from torchmocap.data.recordings.masks.consistency import hull_filter, hull_regions, keypoint_gate
from torchmocap.data.recordings.masks.foreground import clean_masks, foreground_masks
from torchmocap.data.recordings.masks.inputs import (
    check_images,
    check_keypoints,
    check_plates,
    resize_views,
)
from torchmocap.data.recordings.masks.preview import write_mask_preview
from torchmocap.data.recordings.masks.settings import MaskError, MaskSettings

__all__ = ["compute_masks", "working_images", "working_sizes"]

#: frames whose foreground is computed at once (bounds the float temporaries)
_CHUNK = 8


def working_sizes(sizes: Tensor, scale: float) -> Tensor:
    """``(C, 2)`` image sizes at ``scale`` (rounded like :meth:`CameraRig.scaled_images`)."""
    return torch.round(sizes.double() * scale).long().clamp_min(1)


def working_images(images: Tensor, rig: CameraRig, scale: float) -> Tensor:
    """The frames as the masks see them: ``(T, C, h, w, 3)`` uint8 at ``scale`` (antialiased
    bilinear; each view resampled to ``rig.scaled_images(scale)``'s size, zero padding), for a
    sequence whose images must line up with :func:`compute_masks`' masks."""
    images, sizes = check_images(images, rig)
    return resize_views(images, sizes, working_sizes(sizes, scale)).permute(0, 1, 3, 4, 2)


def _scale_keypoints(kp: Tensor, scale: float) -> Tensor:
    """Pixels at ``scale`` with the pixel-centre convention ``u' + 0.5 = s (u + 0.5)``."""
    out = kp.clone()
    out[..., :2] = (kp[..., :2] + 0.5) * scale - 0.5
    return out


def _working_plates(plates: list[Tensor | None] | None, sizes: Tensor, out_sizes: Tensor,
                    device: torch.device) -> list[Tensor | None] | None:
    """Plates ``(3, h', w')`` float resampled with their camera's factor per axis (so that a
    codec crop stays a crop of the working frame)."""
    if plates is None:
        return None
    out: list[Tensor | None] = []
    for c, p in enumerate(plates):
        if p is None:
            out.append(None)
            continue
        ph, pw = p.shape[:2]
        fx, fy = float(out_sizes[c, 0] / sizes[c, 0]), float(out_sizes[c, 1] / sizes[c, 1])
        size = torch.tensor([[max(1, round(pw * fx)), max(1, round(ph * fy))]])
        out.append(resize_views(p[None, None].to(device), torch.tensor([[pw, ph]]), size
                                )[0, 0].float())
    return out


def _fractions(masks: Tensor, valid: Tensor) -> list[float]:
    """Per camera, the mean fraction of its image that ``masks (T, C, H, W)`` cover."""
    area = valid.sum((-1, -2)).clamp_min(1).double()
    return [round(float(v), 5) for v in (masks.sum((-1, -2)).double().mean(0) / area).cpu()]


def compute_masks(images: Tensor, rig: CameraRig, backgrounds=None, keypoints: Tensor | None = None,
                  settings: MaskSettings | Mapping[str, Any] | None = None,
                  preview: str | os.PathLike | None = None, preview_frame: int | None = None
                  ) -> tuple[Tensor, dict]:
    """Foreground masks of every frame and view at the working resolution.

    Background: the per-pixel median of ``median_frames`` frames, replaced by the registered,
    gain-corrected plate where the two disagree (a subject who stands still stays foreground;
    with keypoints only near the subject, so that the plate's own people and moved objects
    are not foreground).
    Foreground: chromatic distortion or a brightness change outside the shadow range beyond
    ``threshold`` × each camera's noise (MAD), then opening, closing, hole filling and removal
    of small components. Multi-view: each mask ∩ the reprojection of the largest component of
    the visual hull supported by C − 1 views (with keypoints: carved only near the subject's
    triangulated keypoints); optionally only components overlapping the subject's keypoint box.
    Frames are processed in chunks of 8 (the float temporaries of one chunk at scale 0.5 and
    four 1920x1088 views are about 0.5 GB).

    Args:
        images: ``(T, C, H, W, 3)`` uint8 RGB frames at the rig's resolution. Views smaller
            than ``(H, W)`` (``rig.image_size[c]``) fill the top-left corner.
        rig: the ``C`` calibrated cameras, image sizes as decoded.
        backgrounds: background plates: None, a ``(C, H', W', 3)`` uint8 tensor, or ``C``
            tensors ``(H'_c, W'_c, 3)`` (None for a camera without one). A plate may be larger
            than its camera's frames by a codec crop (< 16 px, right/bottom edge).
        keypoints: ``(T, C, K, 3)`` the subject's detections (u, v, confidence) in the images'
            pixels, or None; they place the hull's box and gate the components.
        settings: :class:`MaskSettings` or its dict form (``data.masks.*``).
        preview: write a preview PNG of frame ``preview_frame`` (default: the middle one) there.
        preview_frame: frame shown in the preview.

    Returns:
        ``masks (T, C, h, w)`` bool on the images' device, at ``rig.scaled_images(scale)``'s
        sizes (padding False), and a JSON-safe report: settings, working sizes, per-camera
        background info, foreground fractions before/after the multi-view check, the hull's
        volumes and empty frames, the gate's removals, and seconds per stage.

    Raises:
        MaskError: names the argument or setting and what was expected.

    Example:
        >>> from torchmocap.cameras import make_ring_rig
        >>> rig = make_ring_rig(4, image_size=(64, 48))
        >>> frames = torch.randint(0, 255, (3, 4, 48, 64, 3), dtype=torch.uint8)
        >>> masks, report = compute_masks(frames, rig, settings={"scale": 0.5,
        ...                                                        "multiview": False})
        >>> masks.shape
        torch.Size([3, 4, 24, 32])
    """
    settings = MaskSettings.from_dict(settings)
    timing: dict[str, float] = {}
    tic = time.perf_counter()
    images, sizes = check_images(images, rig)
    T, C = images.shape[:2]
    plates = check_plates(backgrounds, sizes)
    kp = check_keypoints(keypoints, (T, C))
    if preview_frame is not None and (isinstance(preview_frame, bool) or not isinstance(
            preview_frame, int) or not 0 <= preview_frame < T):
        raise MaskError(f"preview_frame: expected a frame index in [0, {T}), got "
                        f"{preview_frame!r}")
    dev = images.device
    out_sizes = working_sizes(sizes, settings.scale)
    wrig = rig.scaled_images(settings.scale).to(dev)
    frames = resize_views(images, sizes, out_sizes)  # (T, C, 3, h, w)
    h, w = frames.shape[-2:]
    valid = (torch.arange(w, device=dev)[None, None, :] < out_sizes[:, 0, None, None].to(dev)) \
        & (torch.arange(h, device=dev)[None, :, None] < out_sizes[:, 1, None, None].to(dev))
    plates = _working_plates(plates, sizes, out_sizes, dev)
    if kp is not None:
        kp = _scale_keypoints(kp.to(dev), settings.scale)
    timing["resize"] = time.perf_counter() - tic

    tic = time.perf_counter()
    background = estimate_background(frames, valid, plates, settings, kp)
    timing["background"] = time.perf_counter() - tic

    tic = time.perf_counter()
    fg = torch.cat([clean_masks(foreground_masks(frames[i:i + _CHUNK], background, settings),
                                valid, settings) for i in range(0, T, _CHUNK)])
    timing["foreground"] = time.perf_counter() - tic

    report: dict[str, Any] = {"frames": T, "settings": settings.to_dict(),
                              "working_sizes": out_sizes.tolist(), "background": background.info}
    masks = fg
    if settings.multiview and C >= 2:
        tic = time.perf_counter()
        bounds, skeletons, how = hull_regions(wrig, kp, settings)
        masks, report["multiview"] = hull_filter(fg, wrig, bounds.expand(T, 3, 2), settings,
                                                 skeletons)
        report["multiview"]["bounds_from"] = sorted(set(how))
        timing["multiview"] = time.perf_counter() - tic
    if settings.keypoint_gate and kp is not None:
        tic = time.perf_counter()
        masks, report["keypoint_gate"] = keypoint_gate(masks, kp, settings)
        timing["keypoint_gate"] = time.perf_counter() - tic
    report["foreground_fraction"] = _fractions(fg, valid)
    report["mask_fraction"] = _fractions(masks, valid)
    if preview is not None:
        tic = time.perf_counter()
        t = T // 2 if preview_frame is None else preview_frame
        write_mask_preview(preview, frames[t].permute(0, 2, 3, 1), masks[t], fg[t] & ~masks[t],
                           out_sizes, None if kp is None else kp[t])
        timing["preview"] = time.perf_counter() - tic
    report["timing_s"] = {k: round(v, 4) for k, v in timing.items()}
    return masks, report
