"""Synthetic scenes for the camera-refinement tests: a known 4-camera rig, smooth 3D
trajectories of a body-sized point set walking a circle, their noisy, partly missed detections
(optionally with per-camera time offsets), and a perturbed copy of the rig to refine."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchmocap.cameras import CameraRig, apply_rig_parameters, make_ring_rig, refinement_pixels
from torchmocap.geometry import geodesic_angle

FPS = 30.0


@dataclass
class Scene:
    rig: CameraRig  # the truth
    perturbed: CameraRig  # what the refinement starts from
    detections: torch.Tensor  # (T, C, K, 3)
    offsets: torch.Tensor  # (C,) true time offsets (frames)
    trajectory: object  # times (...) -> (..., K, 3)
    perturbation: torch.Tensor  # (C, 13) values that made ``perturbed``


def trajectories(K: int, g: torch.Generator, walk_m: float = 1.0):
    """``at(times) -> (*times.shape, K, 3)``: a 1.7 m cloud of K points swaying (sums of
    sinusoids, 0.3–1.5 Hz, 15 cm) while walking a circle of ``walk_m`` (4 s a turn)."""
    f64 = torch.float64
    base = (torch.rand(K, 3, generator=g, dtype=f64) - 0.5) * torch.tensor(
        [0.5, 0.3, 1.7], dtype=f64) + torch.tensor([0.0, 0.0, 0.95], dtype=f64)
    amp = torch.rand(K, 3, 3, generator=g, dtype=f64) * 0.15
    freq = 0.3 + torch.rand(K, 3, 3, generator=g, dtype=f64) * 1.2
    phase = torch.rand(K, 3, 3, generator=g, dtype=f64) * 2 * math.pi

    def at(times: torch.Tensor) -> torch.Tensor:
        s = times.to(f64)[..., None, None, None] / FPS
        walk = times.to(f64)[..., None] / FPS * 2 * math.pi * 0.25
        centre = torch.stack([walk.cos(), walk.sin(), torch.zeros_like(walk)], -1) * walk_m
        return base + centre + (amp * torch.sin(2 * math.pi * freq * s + phase)).sum(-1)

    return at


def perturbation(C: int, g: torch.Generator, rotation_deg=(1.0, 3.0), centre_m=(0.02, 0.05),
                 focal=(0.02, 0.05)) -> torch.Tensor:
    """``(C, 13)`` values: a random rotation, centre move and focal change per camera, each of
    a magnitude drawn uniformly from its range (focal: either sign)."""
    f64 = torch.float64
    v = torch.zeros(C, 13, dtype=f64)

    def uniform(lo_hi):
        return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * float(torch.rand(1, generator=g))

    for c in range(C):
        a = torch.randn(3, generator=g, dtype=f64)
        v[c, 0:3] = a / a.norm() * math.radians(uniform(rotation_deg))
        d = torch.randn(3, generator=g, dtype=f64)
        v[c, 3:6] = d / d.norm() * uniform(centre_m)
        sign = 1.0 if float(torch.rand(1, generator=g)) < 0.5 else -1.0
        v[c, 6:8] = math.log1p(sign * uniform(focal))
    return v


def make_scene(seed: int = 0, T: int = 60, K: int = 25, noise_px: float = 2.0,
               offsets=(0.0, 0.0, 0.0, 0.0), missing: float = 0.1,
               image_size=(1280, 960)) -> Scene:
    g = torch.Generator().manual_seed(seed)
    rig = make_ring_rig(len(offsets), radius=3.5, image_size=image_size).double()
    at = trajectories(K, g)
    off = torch.tensor(offsets, dtype=torch.float64)
    times = torch.arange(T, dtype=torch.float64)[None] + off[:, None]  # (C, T)
    uv = refinement_pixels(at(times), rig.K, rig.R, rig.t, rig.dist, per_camera=True)
    uv = uv + noise_px * torch.randn(uv.shape, generator=g, dtype=torch.float64)
    conf = 0.5 + 0.5 * torch.rand(uv.shape[:-1], generator=g, dtype=torch.float64)
    lost = torch.rand(conf.shape, generator=g, dtype=torch.float64) < missing
    w, h = image_size
    outside = (uv[..., 0] < -0.5) | (uv[..., 0] > w - 0.5) | (uv[..., 1] < -0.5) | \
        (uv[..., 1] > h - 0.5)
    lost = lost | outside
    conf = torch.where(lost, torch.zeros_like(conf), conf)
    det = torch.cat([uv * (conf > 0)[..., None], conf[..., None]], -1)
    v = perturbation(rig.num_cameras, g)
    K_, R_, t_, d_ = apply_rig_parameters(v, rig.K, rig.R, rig.t, rig.dist)
    bad = CameraRig(K_, R_, t_, rig.image_size, d_, rig.names)
    return Scene(rig, bad, det, off, at, v)


def rig_errors(est: CameraRig, truth: CameraRig) -> dict[str, torch.Tensor]:
    """Errors of ``est`` after the similarity that best maps it onto ``truth`` (the refinement
    cannot see the world's similarity): rotation from the cameras' mean rotation difference,
    scale and shift from the centres. ``rotation_deg (C,)``, ``centre_m (C,)``, ``focal (C,)``
    (relative), ``scale``."""
    est, truth = est.double(), truth.double()
    U, _, Vh = torch.linalg.svd((truth.R.transpose(-1, -2) @ est.R).mean(0))
    Q = U @ Vh
    ce, ct = est.camera_centers() @ Q.T, truth.camera_centers()
    a, b = ce - ce.mean(0), ct - ct.mean(0)
    s = (a * b).sum() / (a * a).sum()
    return {"rotation_deg": torch.rad2deg(geodesic_angle(est.R @ Q.T, truth.R)),
            "centre_m": (s * a + ct.mean(0) - ct).norm(dim=-1),
            "focal": est.K[:, 0, 0] / truth.K[:, 0, 0] - 1, "scale": s}
