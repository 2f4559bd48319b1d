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

from torchmocap.data.recordings.masks.morphology import dilate, erode
from torchmocap.data.recordings.masks.regions import person_region
from torchmocap.data.recordings.masks.registration import register_images, warp_images
from torchmocap.data.recordings.masks.settings import MaskSettings

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


def _register(median: Tensor, plate: Tensor, valid: Tensor, settings: MaskSettings,
              item: dict) -> Tensor:
    """``(1, 2, 3)`` affine map from frame pixels to ``plate`` pixels: the registration's, or
    the identity when registration is off or would move a corner too far (noted in ``item``)."""
    H, W = median.shape[-2:]
    eye = torch.eye(2, 3, dtype=torch.float64, device=median.device)[None]
    if not settings.register_plates:
        return eye
    reg = register_images(median.mean(0)[None], plate.mean(0)[None], valid[None])
    corners = torch.tensor([[0.0, 0.0, 1.0], [W - 1, 0.0, 1.0], [0.0, H - 1, 1.0],
                            [W - 1, H - 1, 1.0]], dtype=torch.float64, device=median.device)
    moved = float(((corners @ reg["affine"][0].T) - corners[:, :2]).norm(dim=-1).max())
    item["registration_shift_px"] = round(moved, 3)
    if moved > settings.max_plate_motion * math.hypot(H, W):
        item["registration"] = "rejected"
        return eye
    item["registration"] = [[round(float(v), 5) for v in row] for row in reg["affine"][0]]
    return reg["affine"]


def _plate_region(median: Tensor, plate: Tensor, valid: Tensor, near: Tensor | None,
                  settings: MaskSettings, item: dict) -> tuple[Tensor, Tensor, float]:
    """The registered, gain-corrected plate ``(3, H, W)`` of one camera, where it replaces the
    median ``(H, W)`` bool, and its noise (per-channel standard deviation of the residual)."""
    H, W = median.shape[-2:]
    affine = _register(median, plate, valid, settings, item)
    warped, inside = warp_images(plate[None], affine, (H, W))
    warped = warped[0]
    inside = erode((inside[0] & valid)[None], 1)[0]  # bilinear samples near the plate's edge
    k = max(1, math.ceil(math.sqrt(H * W / _FIT_PIXELS)))  # a strided subsample suffices
    gain, offset, sigma = _fit_gain_offset(warped[None, :, ::k, ::k], median[None, :, ::k, ::k],
                                           inside[None, ::k, ::k])
    corrected = (warped * gain[0, :, None, None].float() + offset[0, :, None, None].float()
                 ).clamp(0, 255)
    sig = float(sigma[0])
    # colour distance against the norm of 3-channel noise, sqrt(3) sigma
    disagree = inside & ((corrected - median).norm(dim=0) >
                         settings.plate_agreement * math.sqrt(3) * sig)
    # isolated disagreeing pixels are noise; the rest is grown over the blurred outline
    disagree = dilate(erode(disagree[None], 1), 1)[0] & disagree
    if settings.plate_dilation > 0:
        disagree = dilate(disagree[None], max(1, round(settings.plate_dilation * H)))[0] & inside
    area = max(1, int(valid.sum()))
    if near is not None and bool(near.any()):
        item["plate_outside_subject"] = round(float((disagree & ~near).sum()) / area, 4)
        disagree = disagree & near
    item.update(gain=[round(float(v), 4) for v in gain[0]],
                offset=[round(float(v), 3) for v in offset[0]], noise_plate=round(sig, 3),
                plate_fraction=round(float(disagree.sum()) / area, 4))
    return corrected, disagree, sig


def estimate_background(frames: Tensor, valid: Tensor, plates: list[Tensor | None] | None,
                        settings: MaskSettings, keypoints: Tensor | None = None
                        ) -> BackgroundModel:
    """Background colour and noise of every camera from the frames (and plates).

    Args:
        frames: ``(T, C, 3, H, W)`` uint8 frames at the working resolution (a camera whose
            images are smaller occupies the top-left ``valid`` region).
        valid: ``(C, H, W)`` bool, each camera's image region.
        plates: per camera a ``(3, H', W')`` float plate at the working resolution whose pixel
            ``(0, 0)`` shows about the frames' pixel ``(0, 0)`` (codec crops are on the right
            and bottom; registration finds the rest), or None; None for no plates at all.
        settings: :class:`MaskSettings` (``median_frames``, ``register_plates``,
            ``max_plate_motion``, ``plate_agreement`` — the plate and the median disagree
            where their colour distance exceeds ``plate_agreement`` × √3 × the residual's
            per-channel standard deviation —, ``plate_dilation``, ``plate_near_subject``,
            ``subject_radius``, ``min_confidence``, ``min_noise``).
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
    near = None
    if keypoints is not None and settings.plate_near_subject:
        near = person_region(keypoints[idx.to(keypoints.device)], (H, W),
                             settings.subject_radius, settings.min_confidence).any(0).to(dev)
    info: list[dict] = []
    for c in range(C):
        item: dict = {"median_frames": int(idx.numel()),
                      "noise_median": round(float(sigma_median[c]), 3),
                      "plate": plates is not None and plates[c] is not None}
        info.append(item)
        if not item["plate"]:
            continue
        corrected, use, sig = _plate_region(median[c], plates[c].to(dev, torch.float32),
                                            valid[c], None if near is None else near[c],
                                            settings, item)
        colour[c] = torch.where(use[None], corrected, median[c])
        noise[c] = torch.where(use, torch.full_like(noise[c], sig), noise[c])
        from_plate[c] = use
    return BackgroundModel(colour, noise.clamp_min(settings.min_noise), from_plate, info)
