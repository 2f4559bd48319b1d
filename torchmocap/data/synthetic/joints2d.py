"""2D joint detections: projected joint centres per camera with pixel noise, outliers and misses.

Output ``(T, C, J, 3)`` holds ``(u, v, confidence)``: correct detections get a confidence drawn
from ``[lo, hi]``, outliers (a uniform random image position) from ``[0.1, lo]``; missed joints,
joints outside the image or behind the camera, and every joint of a dropped view get
``(0, 0, 0)``.

Joints hidden by the body (``occluded``, from
:func:`torchmocap.data.synthetic.occlusion.joint_occlusion`)
behave as a detector behaves on them: missed more often (``occluded_miss_prob``), placed less
precisely (``occluded_pixel_noise``) and reported with a lower confidence
(``occluded_confidence``) — the depth-order cue a single view still carries.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["synthesize_joints2d"]


def synthesize_joints2d(positions: Tensor, rig, generator: torch.Generator,
                        pixel_noise: float = 0.0, outlier_prob: float = 0.0,
                        miss_prob: float = 0.0, confidence: tuple[float, float] = (1.0, 1.0),
                        dropped: Tensor | None = None, occluded: Tensor | None = None,
                        occluded_miss_prob: float = 0.5, occluded_pixel_noise: float = 3.0,
                        occluded_confidence: tuple[float, float] = (0.1, 0.5)) -> Tensor:
    """Simulated 2D joint detections.

    Args:
        positions: ``(T, J, 3)`` world joint centres (m).
        rig: :class:`~torchmocap.cameras.CameraRig` with ``C`` cameras.
        generator: randomness.
        pixel_noise: std (px) of Gaussian noise on correct detections.
        outlier_prob: probability of a detection at a uniform random image position.
        miss_prob: probability of a missed detection.
        confidence: ``(lo, hi)`` confidence range of correct detections.
        dropped: optional ``(T, C)`` bool, views lost in a frame.
        occluded: optional ``(T, C, J)`` bool, joints hidden by the body in a view; their
            detections use the three ``occluded_*`` settings instead (outliers stay outliers).
        occluded_miss_prob: probability of missing a hidden joint.
        occluded_pixel_noise: std (px) of the noise on a hidden joint's detection.
        occluded_confidence: ``(lo, hi)`` confidence range of hidden joints' detections.

    Returns:
        ``(T, C, J, 3)`` (u, v, confidence), dtype of ``positions``.
    """
    if positions.dim() != 3 or positions.shape[-1] != 3:
        raise ValueError(f"positions: expected shape (T, J, 3), got {tuple(positions.shape)}")
    pix, _, vis = rig.project(positions)  # (T, C, J, 2), (T, C, J)
    shape = vis.shape
    f64 = torch.float64
    noise = torch.randn(*shape, 2, generator=generator, dtype=f64).to(pix)
    g = torch.rand(*shape, 4, generator=generator, dtype=f64).to(pix)
    size = rig.image_size.to(pix)  # (C, 2)
    u_out = (g[..., :2] * size[None, :, None, :]) - 0.5
    outlier = g[..., 2] < outlier_prob
    miss = g[..., 3] < miss_prob
    lo, hi = float(confidence[0]), float(confidence[1])
    cg = torch.rand(*shape, generator=generator, dtype=f64).to(pix)
    conf = torch.where(outlier, 0.1 + (lo - 0.1) * cg, lo + (hi - lo) * cg)
    sigma = torch.full_like(conf, float(pixel_noise))
    if occluded is not None:
        if occluded.shape != shape:
            raise ValueError(f"occluded: expected shape {tuple(shape)}, got "
                             f"{tuple(occluded.shape)}")
        occ = occluded.to(conf.device)
        olo, ohi = float(occluded_confidence[0]), float(occluded_confidence[1])
        conf = torch.where(occ & ~outlier, olo + (ohi - olo) * cg, conf)
        sigma = torch.where(occ, float(occluded_pixel_noise), sigma)
        miss = torch.where(occ, g[..., 3] < occluded_miss_prob, miss)
    uv = torch.where(outlier[..., None], u_out, pix + sigma[..., None] * noise)
    ok = vis & ~miss
    if dropped is not None:
        ok &= ~dropped.to(ok.device)[..., None]
    uv = torch.where(ok[..., None], uv, torch.zeros_like(uv))
    conf = torch.where(ok, conf, torch.zeros_like(conf))
    return torch.cat([uv, conf[..., None]], -1)
