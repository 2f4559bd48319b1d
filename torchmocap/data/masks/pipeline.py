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
from torchmocap.data.masks.background import estimate_background
from torchmocap.data.masks.consistency import hull_filter, hull_regions, keypoint_gate
from torchmocap.data.masks.foreground import clean_masks, foreground_masks
from torchmocap.data.masks.inputs import check_images, check_keypoints, check_plates, resize_views
from torchmocap.data.masks.preview import write_mask_preview
from torchmocap.data.masks.settings import MaskSettings

__all__ = ["compute_masks", "working_sizes"]

#: frames whose foreground is computed at once (bounds the float temporaries)
_CHUNK = 8


def working_sizes(sizes: Tensor, scale: float) -> Tensor:
    """``(C, 2)`` image sizes at ``scale`` (rounded like :meth:`CameraRig.scaled_images`)."""
    return torch.round(sizes.double() * scale).long().clamp_min(1)


def _scale_keypoints(kp: Tensor, scale: float) -> Tensor:
    """Pixels at ``scale`` with the pixel-centre convention ``u' + 0.5 = s (u + 0.5)``."""
    out = kp.clone()
    out[..., :2] = (kp[..., :2] + 0.5) * scale - 0.5
    return out


def compute_masks(images: Tensor, rig: CameraRig, backgrounds=None, keypoints: Tensor | None = None,
                  settings: MaskSettings | Mapping[str, Any] | None = None,
                  preview: str | os.PathLike | None = None, preview_frame: int | None = None
                  ) -> tuple[Tensor, dict]:
    """Foreground masks of every frame and view at the working resolution.

    Background: the per-pixel median of ``median_frames`` frames, replaced by the registered,
    gain-corrected plate where the two disagree (a subject who stands still stays foreground).
    Foreground: chromatic distortion or a brightness change outside the shadow range beyond
    ``threshold`` × each camera's noise (MAD), then opening, closing, hole filling and removal
    of small components. Multi-view: each mask ∩ the reprojection of the largest component of
    the visual hull supported by C − 1 views; optionally only components overlapping the
    subject's keypoint box.

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
        >>> masks, report = compute_masks(frames, rig, settings={"scale": 0.5})
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
    if preview_frame is not None and not (isinstance(preview_frame, int) and
                                          0 <= preview_frame < T):
        from torchmocap.data.masks.settings import MaskError

        raise MaskError(f"preview_frame: expected a frame index in [0, {T}), got "
                        f"{preview_frame!r}")
    dev = images.device
    s = settings.scale
    out_sizes = working_sizes(sizes, s)
    wrig = rig.scaled_images(s).to(dev)
    frames = resize_views(images, sizes, out_sizes)  # (T, C, 3, h, w)
    h, w = frames.shape[-2:]
    ys, xs = torch.arange(h, device=dev), torch.arange(w, device=dev)
    valid = (xs[None, None, :] < out_sizes[:, 0, None, None].to(dev)) & \
            (ys[None, :, None] < out_sizes[:, 1, None, None].to(dev))
    plates_w = None
    if plates is not None:
        plates_w = []
        for c, p in enumerate(plates):
            if p is None:
                plates_w.append(None)
                continue
            ph, pw = p.shape[:2]
            # the frames' factor per axis, so that a codec crop stays a crop
            fx, fy = float(out_sizes[c, 0] / sizes[c, 0]), float(out_sizes[c, 1] / sizes[c, 1])
            size = torch.tensor([[max(1, round(pw * fx)), max(1, round(ph * fy))]])
            plates_w.append(resize_views(p[None, None].to(dev), torch.tensor([[pw, ph]]),
                                         size)[0, 0].float())
    if kp is not None:
        kp = _scale_keypoints(kp.to(dev), s)
    timing["resize"] = time.perf_counter() - tic

    tic = time.perf_counter()
    background = estimate_background(frames, valid, plates_w, settings, kp)
    timing["background"] = time.perf_counter() - tic

    tic = time.perf_counter()
    fg = torch.cat([clean_masks(foreground_masks(frames[i:i + _CHUNK], background, settings),
                                valid, settings) for i in range(0, T, _CHUNK)])
    timing["foreground"] = time.perf_counter() - tic

    masks, report_mv, report_gate = fg, None, None
    if settings.multiview and C >= 2:
        tic = time.perf_counter()
        bounds, skeletons, how = hull_regions(wrig, kp, settings)
        masks, report_mv = hull_filter(fg, wrig, bounds.expand(T, 3, 2), settings, skeletons)
        report_mv["bounds_from"] = sorted(set(how))
        timing["multiview"] = time.perf_counter() - tic
    if settings.keypoint_gate and kp is not None:
        tic = time.perf_counter()
        masks, report_gate = keypoint_gate(masks, kp, settings)
        timing["keypoint_gate"] = time.perf_counter() - tic

    area = valid.sum((-1, -2)).clamp_min(1).double()
    report: dict[str, Any] = {
        "frames": T,
        "settings": settings.to_dict(),
        "working_sizes": out_sizes.tolist(),
        "background": background.info,
        "foreground_fraction": [round(float(v), 5) for v in
                                fg.sum((-1, -2)).double().mean(0).cpu() / area.cpu()],
        "mask_fraction": [round(float(v), 5) for v in
                          masks.sum((-1, -2)).double().mean(0).cpu() / area.cpu()],
    }
    if report_mv is not None:
        report["multiview"] = report_mv
    if report_gate is not None:
        report["keypoint_gate"] = report_gate
    if preview is not None:
        tic = time.perf_counter()
        t = T // 2 if preview_frame is None else preview_frame
        write_mask_preview(preview, frames[t].permute(0, 2, 3, 1), masks[t], fg[t] & ~masks[t],
                           out_sizes, None if kp is None else kp[t])
        timing["preview"] = time.perf_counter() - tic
    report["timing_s"] = {k: round(v, 4) for k, v in timing.items()}
    return masks, report
