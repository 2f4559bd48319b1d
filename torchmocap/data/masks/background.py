"""Per-camera background model: the video's temporal median, corrected by a background plate.

The median of a subsample of frames is the background wherever the scene is still; where the
subject stands still it is the subject. A plate (the empty scene, taken at another time) is
registered to the median (affine warp, then per-channel gain/offset, both robust), and replaces
the median where the two disagree. A plate's own clutter (a person, a moved object) therefore
shows up as foreground only where the median also differs from it, and the multi-view check
removes what a single view sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchmocap.data.masks.morphology import dilate, erode
from torchmocap.data.masks.regions import person_region
from torchmocap.data.masks.registration import register_images, warp_images
from torchmocap.data.masks.settings import MaskSettings

__all__ = ["BackgroundModel", "estimate_background", "robust_sigma"]

#: pixels (about) used to fit a plate's colour gain/offset
_FIT_PIXELS = 60_000


@dataclass
class BackgroundModel:
    """Background of each camera at the working resolution.

    Attributes:
        colour: ``(C, 3, H, W)`` float32 RGB in [0, 255].
        noise: ``(C, H, W)`` float32 standard deviation (grey levels, per channel) of a frame's
            difference from ``colour`` where nothing moves.
        from_plate: ``(C, H, W)`` bool, True where the (registered) plate is used.
        info: one JSON-safe dict per camera saying what was done.
    """

    colour: Tensor
    noise: Tensor
    from_plate: Tensor
    info: list[dict] = field(default_factory=list)


def robust_sigma(x: Tensor, max_samples: int = 200_000) -> Tensor:
    """``(C,)`` robust standard deviation 1.4826 · median |x − median x| of ``x (C, ...)``,
    from an evenly strided subsample of at most ``max_samples`` values per row."""
    flat = x.reshape(x.shape[0], -1)
    step = max(1, math.ceil(flat.shape[1] / max_samples))
    s = flat[:, ::step].float()
    return 1.4826 * (s - s.median(1, keepdim=True).values).abs().median(1).values


def _median_frames(frames: Tensor, count: int) -> Tensor:
    """``(C, 3, H, W)`` per-pixel median of ``count`` evenly spaced frames of ``(T, C, 3, H, W)``
    uint8 (the lower median for an even count, a value of one of the frames)."""
    T = frames.shape[0]
    idx = torch.linspace(0, T - 1, min(count, T)).round().long().unique()
    return frames[idx.to(frames.device)].median(0).values.float(), idx


def _fit_gain_offset(src: Tensor, dst: Tensor, ok: Tensor, iterations: int = 5
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """Per camera and channel ``dst ≈ gain · src + offset`` over pixels ``ok (C, H, W)``,
    Tukey-reweighted on the colour residual. Returns ``gain (C, 3)``, ``offset (C, 3)`` and
    the robust per-channel residual scale ``(C,)``."""
    C = src.shape[0]
    x, y = src.reshape(C, 3, -1).double(), dst.reshape(C, 3, -1).double()
    w = ok.reshape(C, 1, -1).double().expand(C, 3, -1)
    gain = torch.ones(C, 3, dtype=torch.float64, device=src.device)
    offset = torch.zeros_like(gain)
    sigma = torch.ones(C, dtype=torch.float64, device=src.device)
    for _ in range(iterations):
        sw = w.sum(-1).clamp_min(1)
        mx, my = (w * x).sum(-1) / sw, (w * y).sum(-1) / sw
        vx = (w * (x - mx[..., None]) ** 2).sum(-1)
        cxy = (w * (x - mx[..., None]) * (y - my[..., None])).sum(-1)
        gain = torch.where(vx > 1e-9, cxy / vx.clamp_min(1e-9), torch.ones_like(vx))
        offset = my - gain * mx
        r = y - gain[..., None] * x - offset[..., None]  # (C, 3, N)
        okc = ok.reshape(C, -1)
        sigma = torch.stack([1.4826 * rc[:, m].abs().median() if bool(m.any()) else
                             torch.ones((), dtype=r.dtype, device=r.device)
                             for rc, m in zip(r, okc)]).clamp_min(0.5)
        u = r.norm(dim=1) / (4.685 * math.sqrt(3) * sigma[:, None])
        w = (okc & (u < 1)).double()[:, None, :] * ((1 - u * u) ** 2)[:, None, :]
        w = w.expand(C, 3, -1)
    return gain, offset, sigma


def estimate_background(frames: Tensor, valid: Tensor, plates: list[Tensor | None] | None,
                        settings: MaskSettings, keypoints: Tensor | None = None
                        ) -> BackgroundModel:
    """Background colour and noise of every camera from the frames (and plates).

    Args:
        frames: ``(T, C, 3, H, W)`` uint8 frames at the working resolution (a camera whose
            images are smaller occupies the top-left ``valid`` region).
        valid: ``(C, H, W)`` bool, each camera's image region.
        plates: per camera a ``(3, H', W')`` float plate at the working resolution whose pixel
            ``(0, 0)`` shows the frames' pixel ``(0, 0)`` (codec crops are on the right and
            bottom), or None; None for no plates at all.
        settings: :class:`MaskSettings` (``median_frames``, ``register_plates``,
            ``max_plate_motion``, ``plate_agreement``, ``plate_dilation``,
            ``plate_near_subject``, ``subject_radius``, ``min_confidence``, ``min_noise``).
        keypoints: ``(T, C, K, 3)`` the subject's detections at the working resolution, or
            None.

    Returns:
        :class:`BackgroundModel`.
    """
    T, C, _, H, W = frames.shape
    dev = frames.device
    median, idx = _median_frames(frames, settings.median_frames)
    # noise of a frame around the median where the median is used (strided pixel subsample)
    k = max(1, math.ceil(math.sqrt(H * W / _FIT_PIXELS)))
    diff = frames[idx.to(dev), :, :, ::k, ::k].float() - median[None, :, :, ::k, ::k]
    sub = valid[:, ::k, ::k]
    sigma_median = torch.stack([robust_sigma(diff[:, c][:, :, sub[c]].reshape(1, -1))[0]
                                for c in range(C)])
    colour = median.clone()
    noise = sigma_median[:, None, None].expand(C, H, W).clone()
    from_plate = torch.zeros(C, H, W, dtype=torch.bool, device=dev)
    info: list[dict] = []
    diag = math.hypot(H, W)
    near = None
    if keypoints is not None and settings.plate_near_subject:
        region = person_region(keypoints[idx.to(keypoints.device)], (H, W),
                               settings.subject_radius, settings.min_confidence)
        near = region.any(0).to(dev)  # (C, H, W)
    grow = max(1, round(settings.plate_dilation * H)) if settings.plate_dilation > 0 else 0
    for c in range(C):
        item: dict = {"median_frames": int(idx.numel()),
                      "noise_median": round(float(sigma_median[c]), 3)}
        plate = None if plates is None else plates[c]
        if plate is None:
            item["plate"] = False
            info.append(item)
            continue
        plate = plate.to(dev, torch.float32)
        affine = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64,
                              device=dev)[None]
        item["plate"] = True
        if settings.register_plates:
            reg = register_images(median[c:c + 1].mean(1), plate[None].mean(1), valid[c:c + 1])
            corners = torch.tensor([[0.0, 0.0, 1.0], [W - 1, 0.0, 1.0], [0.0, H - 1, 1.0],
                                    [W - 1, H - 1, 1.0]], dtype=torch.float64, device=dev)
            moved = ((corners @ reg["affine"][0].T) - corners[:, :2]).norm(dim=-1).max()
            item["registration_shift_px"] = round(float(moved), 3)
            if float(moved) <= settings.max_plate_motion * diag:
                affine = reg["affine"]
                item["registration"] = [[round(float(v), 5) for v in row]
                                        for row in affine[0].tolist()]
            else:
                item["registration"] = "rejected"
        warped, inside = warp_images(plate[None], affine, (H, W))
        warped, inside = warped[0], inside[0] & valid[c]
        inside = erode(inside[None], 1)[0]  # bilinear samples near the plate's edge
        k = max(1, math.ceil(math.sqrt(H * W / _FIT_PIXELS)))  # a strided subsample suffices
        gain, offset, sigma_pm = _fit_gain_offset(warped[None, :, ::k, ::k],
                                                  median[c:c + 1, :, ::k, ::k],
                                                  inside[None, ::k, ::k])
        corrected = (warped * gain[0, :, None, None].float() + offset[0, :, None, None].float()
                     ).clamp(0, 255)
        dist = (corrected - median[c]).norm(dim=0)
        sig = float(sigma_pm[0])
        disagree = inside & (dist > settings.plate_agreement * math.sqrt(3) * sig)
        # isolated disagreeing pixels are noise; the rest is grown over the blurred outline
        disagree = dilate(erode(disagree[None], 1), 1)[0] & disagree
        if grow:
            disagree = dilate(disagree[None], grow)[0] & inside
        if near is not None and bool(near[c].any()):
            item["plate_outside_subject"] = round(
                float((disagree & ~near[c]).sum()) / max(1, int(valid[c].sum())), 4)
            disagree = disagree & near[c]
        colour[c] = torch.where(disagree[None], corrected, median[c])
        noise[c] = torch.where(disagree, torch.full_like(noise[c], sig), noise[c])
        from_plate[c] = disagree
        item.update(gain=[round(float(v), 4) for v in gain[0]],
                    offset=[round(float(v), 3) for v in offset[0]],
                    noise_plate=round(sig, 3),
                    plate_fraction=round(float(disagree.sum()) / max(1, int(valid[c].sum())),
                                         4))
        info.append(item)
    noise = noise.clamp_min(settings.min_noise)
    return BackgroundModel(colour, noise, from_plate, info)

