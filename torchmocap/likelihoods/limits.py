"""A joint-limit energy: how far a pose lies outside the skeleton's joint limits.

``V = Σ_d (e_d / scale_d)²`` with ``e_d = max(0, θ_d − upper_d, lower_d − θ_d)`` — zero inside
the limits, quadratic outside. Added to a likelihood it penalises particles instead of clamping
them (a clamp would take a sensor-manifold particle off its manifold). It reads no observation.
Shapes: ``P`` particles, ``D`` DoF.
"""

from __future__ import annotations

import math

import torch

from torchmocap.likelihoods.base import Likelihood

__all__ = ["JointLimitLikelihood", "limit_excess"]


def limit_excess(theta: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """``(P, D)`` distance of each coordinate outside ``[lower, upper]`` (0 inside)."""
    lo, hi = lower.to(theta), upper.to(theta)
    return torch.relu(theta - hi) + torch.relu(lo - theta)


class JointLimitLikelihood(Likelihood):
    """Energy of the excess over the joint limits.

    Args:
        skeleton: the model (its ``lower``/``upper`` limits).
        scale_deg: excess (degrees; centimetres for translations) that costs 1.
    """

    requires = ()

    def __init__(self, skeleton, scale_deg: float = 5.0) -> None:
        super().__init__()
        if not (isinstance(scale_deg, (int, float)) and math.isfinite(scale_deg)
                and scale_deg > 0):
            raise ValueError(f"scale_deg: expected a number > 0, got {scale_deg!r}")
        self.scale_deg = float(scale_deg)
        scale = torch.full((skeleton.num_dofs,), math.radians(scale_deg))
        scale[list(skeleton.translation_dofs)] = scale_deg / 100.0
        self.register_buffer("inv_scale", 1.0 / scale)
        self.register_buffer("lower", skeleton.lower.detach().clone())
        self.register_buffer("upper", skeleton.upper.detach().clone())

    def prepare(self, frame):
        return None

    def energy(self, poses, observation) -> torch.Tensor:
        e = limit_excess(poses.theta, self.lower, self.upper) * self.inv_scale.to(poses.theta)
        return e.square().sum(-1)

    def extra_repr(self) -> str:
        return f"scale_deg={self.scale_deg}"
