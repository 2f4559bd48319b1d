"""Point estimates of a weighted particle set (Pons-Moll eq. 18), as config-selectable modules.

An estimator is called as ``estimator(particles (P, D), weights (P,), context) -> (D,)`` with
normalised ``weights`` and the frame's :class:`~torchmocap.proposals.ProposalContext` (its
``previous`` is the prediction, its ``sensors`` the measured tracking-sensor orientations).

* :class:`WeightedMeanEstimator` — ``Σ_i w_i θ_i``; with ``rotation_groups`` the root rotation
  (``"root"``) or every 3-DoF joint (``"all"``) is averaged on SO(3) (chordal mean), not as
  angles;
* :class:`ManifoldMeanEstimator` — ``g^{-1}(Σ_i w_i x_a^i, z)``: the weighted mean of the active
  coordinates mapped back through the sensor manifold, with ``z`` either the measured sensors
  (``sensors="measured"``) or the weighted SO(3) mean of the sensor-bone orientations the
  particles themselves carry (``sensors="particles"``: Pons-Moll eq. 18, whose particles are
  ``g^{-1}(x_a^i, z~^i)`` with their own noisy sensors ``z~^i`` — the estimate's passive joints
  may then deviate from a misaligned measurement, Fig. 4b);
* :class:`BestParticleEstimator` — the highest-weight particle;
* :class:`TemporalMapEstimator` — the particle (mode) of largest ``weight x N(θ; prediction,
  diag σ²)``: the MAP of the filtering posterior under a Gaussian temporal prior about the
  prediction. With a multi-modal set whose mirror-image modes have the same likelihood (monocular
  depth ambiguity) the weights alone cannot choose; the prior keeps the estimate on the
  interpretation it followed, while the other modes stay in the set.
"""

from __future__ import annotations

import torch
from torch import nn

from torchmocap.filters.optim.temporal_prior import TemporalPrior, check_prior_stds

__all__ = [
    "BestParticleEstimator",
    "Estimator",
    "ManifoldMeanEstimator",
    "TemporalMapEstimator",
    "WeightedMeanEstimator",
]


def _check(particles: torch.Tensor, weights: torch.Tensor) -> None:
    if particles.dim() != 2:
        raise ValueError(f"particles: expected shape (P, D), got {tuple(particles.shape)}")
    if weights.shape != particles.shape[:1]:
        raise ValueError(f"weights: expected shape ({particles.shape[0]},), got "
                         f"{tuple(weights.shape)}")


class Estimator(nn.Module):
    """Base class: ``forward(particles, weights, context) -> (D,)``; ``requires`` names the
    observation modalities it reads (e.g. the sensors of eq. 18's manifold mean)."""

    requires: tuple[str, ...] = ()

    def forward(self, particles: torch.Tensor, weights: torch.Tensor, context=None
                ) -> torch.Tensor:
        raise NotImplementedError(f"{type(self).__name__} must implement forward()")


class WeightedMeanEstimator(Estimator):
    """Weighted mean of the particles (eq. 18).

    Args:
        skeleton: the model (needed for ``rotation_groups``).
        rotation_groups: ``False``/``"none"``: every coordinate averaged as a number;
            ``True``/``"root"``: the root rotation's three angles averaged on SO(3);
            ``"all"``: every joint with three rotation axes (root, spine, shoulders, hips) —
            the angles of each are mapped to a rotation, averaged
            (:func:`~torchmocap.filters.optim.anneal.rotation_mean_fn`) and decomposed back next to
            the highest-weight particle.
    """

    MODES = ("none", "root", "all")

    def __init__(self, skeleton=None, rotation_groups: bool | str = False) -> None:
        super().__init__()
        mode = {False: "none", True: "root"}.get(rotation_groups, rotation_groups) \
            if isinstance(rotation_groups, bool) else rotation_groups
        if mode not in self.MODES:
            raise ValueError(f"rotation_groups: expected a bool or one of {self.MODES}, got "
                             f"{rotation_groups!r}")
        self.rotation_groups = mode
        self._mean = None
        if mode != "none":
            if skeleton is None:
                raise ValueError(f"skeleton: required for rotation_groups={rotation_groups!r}")
            from torchmocap.filters.optim.anneal import rotation_mean_fn
            from torchmocap.filters.optim.rotations import skeleton_rotation_groups

            joints = None if mode == "root" else [
                n for j, n in enumerate(skeleton.joint_names)
                if len(skeleton.joint_axes[j]) == 3]
            self._mean = rotation_mean_fn(skeleton_rotation_groups(skeleton, joints))

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        if self._mean is not None:
            return self._mean(particles, weights)
        return (weights.to(particles.dtype)[:, None] * particles).sum(0)


class ManifoldMeanEstimator(Estimator):
    """``g^{-1}(Σ_i w_i x_a^i, z)``: the active-coordinate mean, mapped back on the manifold.

    Args:
        manifold: the :class:`~torchmocap.ik.SensorManifold` of the tracking sensors.
        sensors: ``"measured"`` — ``z`` = this frame's measured sensor orientations
            (``context.sensors``); ``"particles"`` — ``z`` = the weighted SO(3) mean of the
            particles' own sensor-bone orientations (eq. 18: each particle carries its noisy
            sensor draw, so the estimate stays on the manifold of the noisy sensors it came
            from instead of snapping back to a possibly misaligned measurement).
    """

    SENSORS = ("measured", "particles")

    def __init__(self, manifold, sensors: str = "measured") -> None:
        super().__init__()
        if sensors not in self.SENSORS:
            raise ValueError(f"sensors: expected one of {self.SENSORS}, got {sensors!r}")
        self.manifold = manifold
        self.sensors = sensors

    def forward(self, particles, weights, context=None):
        from torchmocap.geometry import rotation_mean

        _check(particles, weights)
        m = self.manifold
        xa = (weights.to(particles.dtype)[:, None] * m(particles)).sum(0)
        ref = context.previous if context is not None and context.previous.dim() == 1 else None
        valid = None if context is None else context.sensor_valid
        if self.sensors == "particles" or (valid is not None and not bool(valid.all())):
            bones = rotation_mean(m.bone_orientations(particles), weights)  # (S, 3, 3) R_TB
            if self.sensors == "measured":  # only the dropped samples come from the particles
                from torchmocap.ik.sensor_manifold import sensor_rotations

                meas = sensor_rotations(context.sensors, m.num_sensors).to(bones) \
                    @ m.sensor_to_bone.to(bones)
                keep = valid.bool().to(bones.device)[:, None, None]
                bones = torch.where(keep, meas, bones)
            return m.inverse(xa[None], bones, reference=ref, compute_residual=False,
                             sensor_frame=False).theta[0]
        if context is None or context.sensors is None:
            raise ValueError("context.sensors: the manifold estimator needs this frame's "
                             "sensor orientations")
        return m.inverse(xa[None], context.sensors, reference=ref,
                         compute_residual=False).theta[0]

    def extra_repr(self) -> str:
        return f"sensors={self.sensors!r}"


class BestParticleEstimator(Estimator):
    """The particle of largest weight."""

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        return particles[int(torch.argmax(weights))]


class TemporalMapEstimator(Estimator):
    """The particle maximising ``log w_i − ½ Σ_d ((θ_i,d − m_d) / σ_d)²`` with ``m`` the
    prediction (``context.previous (D,)``): the weight times a Gaussian temporal prior.

    Args:
        skeleton: the model (its translation DoFs get ``translation_std``, rotation differences
            are wrapped to ``(−π, π]``).
        rotation_std_deg: ``σ`` of every rotation DoF (degrees).
        translation_std: ``σ`` of the translation DoFs (metres).

    Without a ``(D,)`` prediction in the context (none, or a ``(P0, D)`` particle set) it is
    :class:`BestParticleEstimator`.
    """

    def __init__(self, skeleton=None, rotation_std_deg: float = 20.0,
                 translation_std: float = 0.1) -> None:
        super().__init__()
        self.rotation_std_deg, self.translation_std = check_prior_stds(
            rotation_std_deg, translation_std, ("rotation_std_deg", "translation_std"))
        self.translation_dofs = [] if skeleton is None else list(skeleton.translation_dofs)

    def log_scores(self, particles: torch.Tensor, weights: torch.Tensor,
                   prediction: torch.Tensor) -> torch.Tensor:
        """``(P,)`` log weight plus log temporal prior (up to a constant) of each particle."""
        prior = TemporalPrior.from_stds(particles.shape[-1], self.translation_dofs,
                                        self.rotation_std_deg, self.translation_std,
                                        device=particles.device)
        log_prior = prior.log_prob(particles, prediction)
        return torch.log(weights.to(torch.float64).clamp_min(1e-300)) + log_prior

    def forward(self, particles, weights, context=None):
        _check(particles, weights)
        prev = None if context is None else context.previous
        if prev is None or prev.dim() != 1:  # no single prediction (e.g. a particle set)
            return particles[int(torch.argmax(weights))]
        if prev.shape[0] != particles.shape[1]:
            raise ValueError(f"context.previous: expected a ({particles.shape[1]},) prediction "
                             f"for particles of shape {tuple(particles.shape)}, got "
                             f"{tuple(prev.shape)}")
        return particles[int(torch.argmax(self.log_scores(particles, weights, prev)))]

    def extra_repr(self) -> str:
        return (f"rotation_std_deg={self.rotation_std_deg:g}, "
                f"translation_std={self.translation_std:g}")


def as_estimator(e) -> Estimator:
    """``e`` itself when it is an :class:`Estimator`; typed error otherwise."""
    if not isinstance(e, Estimator):
        raise TypeError(f"estimator: expected a torchmocap Estimator, got {type(e).__name__}")
    return e

