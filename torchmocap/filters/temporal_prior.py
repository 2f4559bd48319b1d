"""Gaussian temporal prior about the predicted pose.

``R(θ) = ½ Σ_d ((θ_d − θ̂_d) / σ_d)²`` with ``θ̂`` the prediction, ``σ_d`` one angle for every
rotation DoF and one length for the root translation; rotation differences are wrapped to
``(−π, π]``. In annealing it multiplies every layer's weights by ``exp(−R)`` — untempered, so
layer ``k`` targets ``exp(−β_k V(θ)) p(θ | θ̂)``: the search leaves the prediction's basin only
where the evidence pays for it, the locality a descent from the prediction has by construction.
``D`` pose coordinates, ``P`` poses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

__all__ = ["TemporalPrior", "temporal_prior_precision"]


def temporal_prior_precision(num_dofs: int, translation_dofs: Sequence[int], std_deg: float,
                             translation_std: float, dtype: torch.dtype = torch.float32,
                             device: torch.device | str | None = None) -> torch.Tensor:
    """``1 / σ² (D,)``: ``σ = radians(std_deg)`` per rotation DoF, ``translation_std`` (metres)
    on ``translation_dofs``."""
    for name, v in (("std_deg", std_deg), ("translation_std", translation_std)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v <= 0:
            raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    s = torch.full((num_dofs,), math.radians(std_deg), dtype=dtype, device=device)
    if len(translation_dofs):
        s[list(translation_dofs)] = float(translation_std)
    return 1.0 / (s * s)


class TemporalPrior:
    """``x (P, D) -> ½ Σ_d prec_d · wrap(x_d − mean_d)² (P,)``: the negative log density (up
    to a constant) of a Gaussian about ``mean``; differentiable.

    Args:
        mean: ``(D,)`` the predicted pose.
        precision: ``(D,)`` ``1 / σ²`` (:func:`temporal_prior_precision`).
        rotation: ``(D,)`` bool, the coordinates whose differences are wrapped to ``(−π, π]``.
    """

    def __init__(self, mean: torch.Tensor, precision: torch.Tensor,
                 rotation: torch.Tensor) -> None:
        if mean.dim() != 1 or precision.shape != mean.shape or rotation.shape != mean.shape:
            raise ValueError(f"mean, precision, rotation: expected three (D,) tensors, got "
                             f"{tuple(mean.shape)}, {tuple(precision.shape)}, "
                             f"{tuple(rotation.shape)}")
        self.mean, self.precision, self.rotation = mean.detach(), precision, rotation

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        d = x - self.mean.to(x)
        wrapped = torch.remainder(d + math.pi, 2 * math.pi) - math.pi
        d = torch.where(self.rotation.to(x.device), wrapped, d)
        return 0.5 * (d * d * self.precision.to(x)).sum(-1)
