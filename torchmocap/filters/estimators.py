"""Point estimates of a weighted particle set (Pons-Moll eq. 18), as config-selectable modules.

An estimator is called as ``estimator(particles (P, D), weights (P,), context) -> (D,)`` with
normalised ``weights`` and the frame's :class:`~torchmocap.proposals.ProposalContext` (its
``previous`` is the prediction, its ``sensors`` the measured tracking-sensor orientations).

* :class:`WeightedMeanEstimator` — ``Σ_i w_i θ_i``; with ``rotation_groups`` the root rotation
  (or any 3-coordinate rotation) is averaged on SO(3) (chordal mean), not as angles;
* :class:`ManifoldMeanEstimator` — ``g^{-1}(Σ_i w_i x_a^i, measured sensors)``: the weighted mean
  of the active coordinates mapped back with the measured (noise-free) sensors, so the estimate
  lies on the sensor manifold;
* :class:`BestParticleEstimator` — the highest-weight particle.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = [
    "BestParticleEstimator",
    "Estimator",
    "ManifoldMeanEstimator",
    "WeightedMeanEstimator",
]


def _check(particles: torch.Tensor, weights: torch.Tensor) -> None:
    if particles.dim() != 2:
        raise ValueError(f"particles: expected shape (P, D), got {tuple(particles.shape)}")
    if weights.shape != particles.shape[:1]:
        raise ValueError(f"weights: expected shape ({particles.shape[0]},), got "
                         f"{tuple(weights.shape)}")


class Estimator(nn.Module):
    """Base class: ``forward(particles, weights, context) -> (D,)``."""

    def forward(self, particles: torch.Tensor, weights: torch.Tensor, context=None
                ) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} must implement forward()")


class WeightedMeanEstimator(Estimator):
    """Weighted mean of the particles (eq. 18).

    Args:
        skeleton: when given with ``rotation_groups=True``, the root rotation's three angles are
            averaged on SO(3) (:func:`~torchmocap.filters.annealed.rotation_mean_fn`).
        rotation_groups: see ``skeleton``.
    """

    def __init__(self, skeleton=None, rotation_groups: bool = False) -> None:
        super().__init__()
        self._mean = None
        if rotation_groups:
            if skeleton is None:
                raise ValueError("skeleton: required for rotation_groups=True")
            from torchmocap.filters.annealed import rotation_mean_fn
            from torchmocap.filters.prediction import skeleton_rotation_groups

            self._mean = rotation_mean_fn(skeleton_rotation_groups(skeleton))

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        if self._mean is not None:
            return self._mean(particles, weights)
        return (weights.to(particles.dtype)[:, None] * particles).sum(0)


class ManifoldMeanEstimator(Estimator):
    """``g^{-1}(Σ_i w_i x_a^i, measured sensors)`` (active-coordinate mean, mapped back).

    Args:
        manifold: the :class:`~torchmocap.ik.SensorManifold` of the tracking sensors.
    """

    def __init__(self, manifold) -> None:
        super().__init__()
        self.manifold = manifold

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        if context is None or context.sensors is None:
            raise ValueError("context.sensors: the manifold estimator needs this frame's "
                             "sensor orientations")
        m = self.manifold
        xa = (weights.to(particles.dtype)[:, None] * m(particles)).sum(0)
        ref = context.previous if context.previous.dim() == 1 else None
        return m.inverse(xa[None], context.sensors, reference=ref,
                         compute_residual=False).theta[0]


class BestParticleEstimator(Estimator):
    """The particle of largest weight."""

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        return particles[int(torch.argmax(weights))]


def as_estimator(e) -> Estimator:
    """``e`` itself when it is an :class:`Estimator`; typed error otherwise."""
    if not isinstance(e, Estimator):
        raise TypeError(f"estimator: expected a torchmocap Estimator, got {type(e).__name__}")
    return e

