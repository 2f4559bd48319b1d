"""Gaussian temporal prior about a pose: the one implementation every component uses (the
annealer's weights, the mixture tracker's optimised energy and mode weights, the temporal MAP
estimator, the Viterbi smoother's transitions).

``R(θ; m) = ½ Σ_d ((θ_d − m_d) / σ_d)²`` with ``σ_d`` one angle for every rotation DoF and one
length for the root translation; rotation differences are wrapped to ``[−π, π)``
(:func:`~torchmocap.geometry.wrap_angle`). In annealing it multiplies every layer's weights by
``exp(−R)`` — untempered, so layer ``k`` targets ``exp(−β_k V(θ)) p(θ | m)``: the search
leaves the prediction's basin only where the evidence pays for it, the locality a descent from
the prediction has by construction. ``D`` pose coordinates, ``P`` poses.

Example:
    >>> from torchmocap.skeleton import human31
    >>> prior = TemporalPrior.for_skeleton(human31(), std_deg=20.0, translation_std=0.1)
    >>> x = torch.zeros(5, 31)
    >>> prior.energy(x, torch.zeros(31)).shape
    torch.Size([5])
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from torchmocap.geometry import wrap_angle

__all__ = ["TemporalPrior", "check_prior_stds", "temporal_prior_precision"]


def check_prior_stds(std_deg, translation_std, names=("std_deg", "translation_std")
                     ) -> tuple[float, float]:
    """The prior's two stds as floats; a typed error naming the setting (``names``) unless
    both are finite numbers > 0."""
    for name, v in zip(names, (std_deg, translation_std)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v <= 0:
            raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    return float(std_deg), float(translation_std)


def temporal_prior_precision(num_dofs: int, translation_dofs: Sequence[int], std_deg: float,
                             translation_std: float, dtype: torch.dtype = torch.float32,
                             device: torch.device | str | None = None) -> torch.Tensor:
    """``1 / σ² (D,)``: ``σ = radians(std_deg)`` per rotation DoF, ``translation_std`` (metres)
    on ``translation_dofs``."""
    check_prior_stds(std_deg, translation_std)
    s = torch.full((num_dofs,), math.radians(std_deg), dtype=dtype, device=device)
    if len(translation_dofs):
        s[list(translation_dofs)] = float(translation_std)
    return 1.0 / (s * s)


class TemporalPrior(nn.Module):
    """A Gaussian about a mean pose: ``energy(x, mean) = ½ Σ_d prec_d · wrap(x_d − mean_d)²``.

    Args:
        precision: ``(D,)`` ``1 / σ²`` (:func:`temporal_prior_precision`).
        rotation: ``(D,)`` bool, the coordinates whose differences are wrapped to ``[−π, π)``
            (the angles; none when the poses compared are known to be close).

    Buffers follow ``.to(device)``; the energy is computed in the dtype of ``x``.
    """

    def __init__(self, precision: torch.Tensor, rotation: torch.Tensor) -> None:
        super().__init__()
        if precision.dim() != 1 or rotation.shape != precision.shape:
            raise ValueError(f"precision, rotation: expected two (D,) tensors, got "
                             f"{tuple(precision.shape)}, {tuple(rotation.shape)}")
        if rotation.dtype != torch.bool:
            raise ValueError(f"rotation: expected a bool mask, got {rotation.dtype}")
        self.register_buffer("precision", precision)
        self.register_buffer("rotation", rotation)

    @classmethod
    def for_skeleton(cls, skeleton, std_deg: float, translation_std: float,
                     dtype: torch.dtype = torch.float64) -> TemporalPrior:
        """``std_deg`` on every rotation DoF of ``skeleton``, ``translation_std`` metres on its
        root translation."""
        return cls.from_stds(skeleton.num_dofs, skeleton.translation_dofs, std_deg,
                             translation_std, dtype)

    @classmethod
    def from_stds(cls, num_dofs: int, translation_dofs: Sequence[int], std_deg: float,
                  translation_std: float, dtype: torch.dtype = torch.float64,
                  device: torch.device | str | None = None, wrap: bool = True
                  ) -> TemporalPrior:
        """The prior of ``num_dofs`` coordinates, ``translation_dofs`` in metres (std
        ``translation_std``), the others angles (std ``std_deg`` degrees). ``wrap=False``
        compares angles as plain numbers (for poses known to be within ``π`` of the mean, where
        wrapping only costs the last bits: the mixture tracker's local optima about the prior
        mode they descend from)."""
        prec = temporal_prior_precision(num_dofs, translation_dofs, std_deg, translation_std,
                                        dtype=dtype, device=device)
        rot = torch.full((num_dofs,), bool(wrap), dtype=torch.bool, device=device)
        rot[list(translation_dofs)] = False
        return cls(prec, rot)

    @property
    def num_dofs(self) -> int:
        return int(self.precision.shape[0])

    def difference(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        """``x − mean`` ``(..., D)`` with rotation differences wrapped to ``[−π, π)``."""
        d = x - mean.to(x)
        return torch.where(self.rotation.to(x.device), wrap_angle(d), d)

    def energy(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        """``(...)`` ``½ Σ_d prec_d d_d²`` of poses ``x (..., D)`` about ``mean``
        (broadcastable); differentiable in ``x``."""
        d = self.difference(x, mean)
        return 0.5 * (d * d * self.precision.to(x)).sum(-1)

    def gradient(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        """``∂ energy / ∂ x`` ``(..., D)`` (its Hessian is ``diag(precision)``)."""
        return self.difference(x, mean) * self.precision.to(x)

    def log_prob(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        """``−energy`` in float64: the log density up to a constant."""
        return -self.energy(x.to(torch.float64), mean.to(torch.float64))

    def forward(self, x: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
        return self.energy(x, mean)

    def extra_repr(self) -> str:
        return f"num_dofs={self.num_dofs}, translations={int((~self.rotation).sum())}"
