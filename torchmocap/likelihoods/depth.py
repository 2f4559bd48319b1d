"""Point-cloud likelihood of Hauberg & Pedersen (2011, eq. 15).

``p(Z | θ) ∝ ∏_k exp(−min(D²(θ, z_k), τ) / 2σ²)`` — each observed 3D point ``z_k`` (from a stereo
or depth camera) is at a Gaussian distance from the skin, truncated at ``τ`` against outliers.
The skin is the union of the capsules, each with the half facing the camera only (the other half
cannot have produced a point): :func:`~torchmocap.body.capsules.capsule_distance` with the camera
centre. The energy is ``V = Σ_k min(D², τ) / 2σ²`` over the frame's points (deterministically
thinned to at most ``max_points``, evenly through the cloud).

Shapes: ``P`` particles, ``K`` points, ``B`` capsules.
"""

from __future__ import annotations

import math

import torch

from torchmocap.body.capsules import capsule_distance
from torchmocap.likelihoods.base import Likelihood

__all__ = ["PointCloudLikelihood", "point_cloud_energy"]


def point_cloud_energy(endpoints: torch.Tensor, radii: torch.Tensor, points: torch.Tensor,
                       camera_center: torch.Tensor | None, sigma: float, tau: float,
                       chunk: int = 64) -> torch.Tensor:
    """``V (P,)`` of capsule axes ``endpoints (P, B, 2, 3)`` against ``points (K, 3)``.

    ``camera_center (3,)``: distances to the camera-facing half-capsules (None: whole capsules).
    Particles are processed in chunks (the ``(P, K, B)`` distances are the memory peak).
    """
    P = endpoints.shape[0]
    if points.shape[0] == 0:
        return torch.zeros(P, dtype=endpoints.dtype, device=endpoints.device)
    pts = points.to(endpoints)
    out = []
    for a in range(0, P, chunk):
        e = endpoints[a:a + chunk]
        n = e.shape[0]
        c = None if camera_center is None else camera_center.to(e).expand(n, 3)
        d = capsule_distance(pts.expand(n, -1, -1), e, radii, c).abs()  # (n, K)
        out.append(torch.clamp(d * d, max=tau).sum(-1) / (2 * sigma * sigma))
    return torch.cat(out)


class PointCloudLikelihood(Likelihood):
    """Eq. 15 against the frame's depth points.

    Args:
        body: the runtime :class:`~torchmocap.body.CapsuleBody`.
        depth_camera: the runtime depth camera (a one-camera rig; its centre selects the
            visible half of each capsule). Without one the whole capsules are used.
        sigma: std (metres) of a point's distance to the skin.
        tau: truncation of the squared distance (m²; robustness against outliers).
        max_points: points used per frame (evenly thinned; 0 = all).

    ``requires = ("depth",)``; a frame without points has no evidence (energy 0 for every
    particle, reported as such).
    """

    requires = ("depth",)

    def __init__(self, body, depth_camera=None, sigma: float = 0.03, tau: float = 0.01,
                 max_points: int = 400) -> None:
        super().__init__()
        for name, v in (("sigma", sigma), ("tau", tau)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or v <= 0:
                raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
        if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 0:
            raise ValueError(f"max_points: expected an int >= 0, got {max_points!r}")
        self.body = body
        self.sigma, self.tau, self.max_points = float(sigma), float(tau), max_points
        centre = None if depth_camera is None else depth_camera.camera_centers()[0]
        self.register_buffer("camera_center", None if centre is None else
                             centre.detach().to(body.radii.dtype).clone())

    def prepare(self, frame) -> torch.Tensor:
        pts = frame.depth
        if pts is None:
            raise ValueError("frame.depth: the point-cloud likelihood needs depth points")
        if pts.dim() != 2 or pts.shape[-1] != 3:
            raise ValueError(f"frame.depth: expected points (K, 3), got {tuple(pts.shape)}")
        pts = pts[torch.isfinite(pts).all(-1)]
        if self.max_points and pts.shape[0] > self.max_points:
            idx = torch.linspace(0, pts.shape[0] - 1, self.max_points,
                                 device=pts.device).round().long()
            pts = pts[idx]
        return pts.to(self.body.radii.dtype)

    def evidence(self, observation: torch.Tensor) -> bool:
        return observation.shape[0] > 0

    def energy(self, poses, observation: torch.Tensor) -> torch.Tensor:
        return point_cloud_energy(poses.endpoints(self.body), self.body.radii, observation,
                                  self.camera_center, self.sigma, self.tau)

    def extra_repr(self) -> str:
        return f"sigma={self.sigma}, tau={self.tau}, max_points={self.max_points}"
