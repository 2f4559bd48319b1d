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
        limits: what to do with particles whose passive joints ``g^{-1}`` puts outside their
            limits (about 9% of draws on real motion): ``"keep"`` them, or ``"resample"`` their
            active diffusion and sensor noise up to ``limit_tries`` times (the particle stays on
            the manifold; clamping its passive angles would take it off).
        limit_tries: redraws of ``"resample"``.
        dropped_spread_deg: a sensor sample flagged invalid (``context.sensor_valid``: dropped,
            the last value held) carries no information: its sensor follows each particle's own
            ancestor bone, spread by this many degrees (tangent Gaussian), instead of the stale
            held value.

    ``sample(context, num, generator)`` needs ``context.sensors`` (``(S, 3, 3)``/``(S, 4)``, or
    per particle). ``stats``: ``residual_max_deg``, ``within_limits`` (fraction of passive
    joints inside limits), ``gimbal`` (count), ``resampled`` (redrawn particles),
    ``dropped_sensors`` (invalid samples this frame), ``seconds``.
    """

    requires = ("imu",)
    LIMITS = ("keep", "resample")

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
        limits: str = "keep",
        limit_tries: int = 4,
        dropped_spread_deg: float = 10.0,
    ) -> None:
        super().__init__()
        if limits not in self.LIMITS:
            raise ValueError(f"limits: expected one of {self.LIMITS}, got {limits!r}")
        if isinstance(limit_tries, bool) or not isinstance(limit_tries, int) or limit_tries < 0:
            raise ValueError(f"limit_tries: expected an int >= 0, got {limit_tries!r}")
        self.limits, self.limit_tries = limits, limit_tries
        if not (isinstance(dropped_spread_deg, (int, float)) and dropped_spread_deg >= 0):
            raise ValueError(f"dropped_spread_deg: expected a number >= 0, got "
                             f"{dropped_spread_deg!r}")
        self.dropped_spread = math.radians(dropped_spread_deg)
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
            for name, v in (("rotation_std_deg", rotation_std_deg),
                            ("translation_std", translation_std)):
                if isinstance(v, bool) or not isinstance(v, (int, float)) \
                        or not math.isfinite(v) or v < 0:
                    raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
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

    def _sensors(self, context: ProposalContext, base: torch.Tensor,
                 generator: torch.Generator | None) -> torch.Tensor:
        """This frame's sensors ``(S, 3, 3)``, or per particle ``(P, S, 3, 3)`` when some
        samples are flagged invalid (those follow each particle's ancestor bone)."""
        from torchmocap.geometry import so3_exp

        m = self.manifold
        valid = context.sensor_valid
        R = self._validated(context.sensors).to(base.dtype)
        if valid is None or bool(valid.all()) or R.dim() != 3:
            return R
        bad = (~valid.bool()).to(R.device)
        num = base.shape[0]
        anc = m.bone_orientations(base) @ m.sensor_to_bone.to(base.dtype).transpose(-1, -2)
        v = torch.randn(num, m.num_sensors, 3, generator=generator, dtype=base.dtype,
                        device=base.device) * self.dropped_spread
        out = R.expand(num, -1, -1, -1).clone()
        out[:, bad] = (anc @ so3_exp(v))[:, bad]
        return out

    def _validated(self, sensors: torch.Tensor) -> torch.Tensor:
        """:func:`sensor_rotations` of ``sensors``, checked once per tensor: every layer of a
        frame passes the same tensor, and the check costs a host sync."""
        key = (id(sensors), sensors._version)
        cached = self.__dict__.get("_sensor_cache")
        if cached is not None and cached[0] == key and cached[1] is sensors:
            return cached[2]
        R = sensor_rotations(sensors, self.manifold.num_sensors)
        self.__dict__["_sensor_cache"] = (key, sensors, R)
        return R

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
        R = self._validated(sensors).to(x_a.dtype)
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
        xa0 = self.coordinates(base)
        std = context_std(context, self.active_std, xa0)
        sensors = self._sensors(context, base, generator)
        dropped = int(sensors.dim() == 4)

        def draw(xa0, std, base, sensors):
            xa = xa0 + torch.randn(xa0.shape, generator=generator, dtype=xa0.dtype,
                                   device=xa0.device) * std
            if self.clamp_active:
                xa = torch.clamp(xa, self.active_lower.to(xa.dtype),
                                 self.active_upper.to(xa.dtype))
            return self.decode(xa, sensors, generator, reference=base)

        sol = draw(xa0, std, base, sensors)
        resampled = 0
        if self.limits == "resample" and self.limit_tries > 0:
            theta, within = sol.theta.clone(), sol.within_limits.clone()
            for _ in range(self.limit_tries):
                bad = (~within.all(-1)).nonzero()[:, 0]
                if bad.numel() == 0:
                    break
                resampled += int(bad.numel())
                s_bad = std[bad] if std.dim() == 2 else std
                redo = draw(xa0[bad], s_bad, base[bad], sensors[bad] if dropped else sensors)
                theta[bad], within[bad] = redo.theta, redo.within_limits
            sol.theta, sol.within_limits = theta, within
        stats = {
            "within_limits": sol.within_limits.to(torch.float32).mean().item(),
            "gimbal": int(sol.gimbal.sum()),
            "resampled": resampled,
            "dropped_sensors": int((~context.sensor_valid.bool()).sum())
            if dropped else 0,
        }
        if sol.residual is not None:
            stats["residual_max_deg"] = float(sol.residual.max()) * 57.29577951308232
        stats["seconds"] = time.perf_counter() - t0
        return Proposed(particles=sol.theta, stats=stats)

    def extra_repr(self) -> str:
        return (f"active={self.manifold.num_active}, clamp_active={self.clamp_active}, "
                f"limits={self.limits!r}")
