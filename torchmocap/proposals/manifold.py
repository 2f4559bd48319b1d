"""Manifold sampling (Pons-Moll et al. 2010, §4.2–4.3): propose poses on the sensor manifold.

Per particle: diffuse the *active* coordinates ``x_a = g(theta_prev) + N(0, diag(std^2))``,
draw a noisy copy of this frame's sensor orientations, and map back with
``theta = g^{-1}(x_a, sensors~)``. The sensor-noise model is an object of
:mod:`torchmocap.proposals.noise` (the ``noise`` config group): none, Gaussian on the passive
parameters (the paper's GN), von Mises–Fisher on S³ (eq. 16) or a tangent Gaussian.

The proposal's coordinates (:meth:`ManifoldProposal.coordinates`) are the active coordinates: an
annealer measures the particle spread there and sets the per-layer diffusion std in them. The
proposal density of ``theta`` has no closed form (it lives on a manifold pushed through
``g^{-1}``), so ``log_q`` is not reported.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import torch

from torchmocap.ik.sensor_manifold import SensorManifold, sensor_rotations
from torchmocap.proposals.base import (
    Proposal,
    ProposalContext,
    Proposed,
    as_std,
    context_std,
    select_ancestors,
)
from torchmocap.proposals.noise import SensorNoise, VonMisesFisherNoise

__all__ = ["ManifoldProposal"]


class ManifoldProposal(Proposal):
    """Sample poses on the sensor manifold (the paper's manifold sampling, MS).

    Args:
        manifold: the :class:`~torchmocap.ik.SensorManifold` (skeleton + sensor placement).
        noise: a :class:`~torchmocap.proposals.noise.SensorNoise` (default vMF, κ = 1000).
        rotation_std_deg, translation_std: diffusion std of the active rotation (degrees) and
            translation (metres) coordinates, when ``active_std`` is not given.
        active_std: scalar or ``(d,)`` diffusion std of the active coordinates (overrides the
            two above).
        clamp_active: clamp diffused active coordinates into the joint limits.
        compute_residual: report the worst sensor residual in ``stats`` (~40% extra time).
            Default (None): only when some passive joint's axes are not mutually orthogonal
            (otherwise every rotation is reachable and the residual is round-off).
        compile: compile the manifold's ``g^{-1}`` core with ``torch.compile`` (see
            :meth:`~torchmocap.ik.SensorManifold.compile_inverse`).

    ``sample(context, num, generator)`` needs ``context.sensors`` (``(S, 3, 3)``/``(S, 4)``, or
    per particle). ``stats``: ``residual_max_deg``, ``within_limits`` (fraction of passive
    joints inside limits), ``gimbal`` (count), ``seconds``.
    """

    requires = ("imu",)

    def __init__(
        self,
        manifold: SensorManifold,
        noise: SensorNoise | None = None,
        rotation_std_deg: float = 3.0,
        translation_std: float = 0.02,
        active_std: float | Sequence[float] | torch.Tensor | None = None,
        clamp_active: bool = True,
        compute_residual: bool | None = None,
        compile: bool = False,
    ) -> None:
        super().__init__()
        if noise is None:
            noise = VonMisesFisherNoise()
        if not isinstance(noise, SensorNoise):
            raise TypeError(f"noise: expected a SensorNoise (torchmocap.proposals.noise), got "
                            f"{type(noise).__name__}")
        self.manifold = manifold
        if compile:
            manifold.compile_inverse()
        self.noise = noise
        self.clamp_active = bool(clamp_active)
        self.compute_residual = (not manifold._orthogonal if compute_residual is None
                                 else bool(compute_residual))
        d = manifold.num_active
        sk = manifold.skeleton
        if active_std is None:
            std = torch.full((d,), math.radians(rotation_std_deg))
            trans = set(sk.translation_dofs)
            for i, dof in enumerate(manifold.active_dofs):
                if dof in trans:
                    std[i] = float(translation_std)
            active_std = std
        self.register_buffer("active_std", as_std(active_std, d, "active_std"))
        self.register_buffer("active_lower", sk.lower[manifold.active_index].clone())
        self.register_buffer("active_upper", sk.upper[manifold.active_index].clone())

    def coordinates(self, theta: torch.Tensor) -> torch.Tensor:
        return theta.index_select(-1, self.manifold.active_index.to(theta.device))

    @property
    def coordinate_std(self) -> torch.Tensor:
        return self.active_std

    def decode(
        self,
        x_a: torch.Tensor,
        sensors: torch.Tensor,
        generator: torch.Generator | None = None,
        reference: torch.Tensor | None = None,
        noisy: bool = True,
    ):
        """``g^{-1}(x_a, noisy sensors)`` for ``x_a (P, d)``; returns the ManifoldSolution.

        ``noisy=False`` maps with the measured sensors (no noise draw)."""
        m = self.manifold
        num, S = x_a.shape[0], m.num_sensors
        R = sensor_rotations(sensors, S).to(x_a.dtype)
        q = (self.noise.sensor_noise(num, S, dtype=x_a.dtype, device=x_a.device,
                                     generator=generator) if noisy else None)
        sol = m.inverse(x_a, R, reference=reference, noise=q,
                        compute_residual=self.compute_residual, validate=False)
        if noisy:
            sol.theta = self.noise.perturb_passive(sol.theta, m.passive_index, generator)
        return sol

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        t0 = time.perf_counter()
        m = self.manifold
        if context.sensors is None:
            raise ValueError("context.sensors: ManifoldProposal needs this frame's sensor "
                             "orientations")
        base = select_ancestors(context, num, m.num_dofs, generator)
        xa = self.coordinates(base)
        std = context_std(context, self.active_std, xa)
        xa = xa + torch.randn(xa.shape, generator=generator, dtype=xa.dtype,
                              device=xa.device) * std
        if self.clamp_active:
            xa = torch.clamp(xa, self.active_lower.to(xa.dtype), self.active_upper.to(xa.dtype))
        sol = self.decode(xa, context.sensors, generator, reference=base)
        stats = {
            "within_limits": sol.within_limits.to(torch.float32).mean().item(),
            "gimbal": int(sol.gimbal.sum()),
        }
        if sol.residual is not None:
            stats["residual_max_deg"] = float(sol.residual.max()) * 57.29577951308232
        stats["seconds"] = time.perf_counter() - t0
        return Proposed(particles=sol.theta, stats=stats)

    def extra_repr(self) -> str:
        return f"active={self.manifold.num_active}, clamp_active={self.clamp_active}"
