"""Manifold sampling (Pons-Moll et al. 2010, §4.2–4.3): propose poses on the sensor manifold.

Per particle: diffuse the *active* coordinates ``x_a = g(theta_prev) + N(0, diag(std^2))``,
draw a noisy copy of this frame's sensor orientations, and map back with
``theta = g^{-1}(x_a, sensors~)``. Sensor noise models (the paper's ablation, §4.2 and Table 2):

* ``"none"``: the measured orientations as they are (paper: 26.8 deg tracking error);
* ``"gaussian"``: the paper's GN baseline — ``g^{-1}`` with the measured orientations, then
  Gaussian noise on the *passive joint parameters* (13 deg);
* ``"vmf"``: ``q~ = q ∘ q_w`` with ``q_w ~ vMF(mu = (1,0,0,0), kappa)`` on S^3, eq. 16
  (kappa = 1000: 7.3 deg);
* ``"tangent_gaussian"``: ``R~ = R exp(hat(v))``, ``v ~ N(0, sigma^2 I)`` (isotropic; equivalent
  to vMF at ``sigma = 2 / sqrt(kappa)``).

The proposal density of ``theta`` has no closed form (it lives on a manifold pushed through
``g^{-1}``), so ``log_q`` is not reported.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from torchmocap.distributions.tangent_gaussian import add_parameter_noise
from torchmocap.distributions.von_mises_fisher import VonMisesFisher, kappa_to_tangent_std
from torchmocap.geometry import axis_angle_to_quaternion, so3_exp
from torchmocap.ik.sensor_manifold import SensorManifold, sensor_rotations
from torchmocap.proposals.base import (
    Proposal,
    ProposalContext,
    Proposed,
    as_std,
    select_ancestors,
)

__all__ = ["ManifoldProposal", "NOISE_MODELS", "perturb_sensors", "quaternion_to_matrix_fast"]

NOISE_MODELS = ("none", "gaussian", "vmf", "tangent_gaussian")


def quaternion_to_matrix_fast(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(*, 4)`` (w, x, y, z) to rotation matrices ``(*, 3, 3)``, no checks."""
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return torch.stack([
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ], dim=-1).reshape(*q.shape[:-1], 3, 3)


def perturb_sensors(
    R: torch.Tensor,
    num: int,
    noise: str,
    kappa: float = 1000.0,
    tangent_std: float | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """``num`` noisy copies of sensor orientations ``R`` ``(S, 3, 3)`` or ``(num, S, 3, 3)``.

    ``"vmf"`` right-multiplies ``R`` by the rotation of a vMF(e1, kappa) quaternion (eq. 16),
    ``"tangent_gaussian"`` by ``exp(hat(v))``, ``v ~ N(0, tangent_std^2 I)`` (default
    ``2/sqrt(kappa)``); ``"none"``/``"gaussian"`` return ``R`` expanded. Returns
    ``(num, S, 3, 3)``.
    """
    if noise not in NOISE_MODELS:
        raise ValueError(f"noise: expected one of {NOISE_MODELS}, got {noise!r}")
    S = R.shape[-3]
    R = R.expand(num, S, 3, 3)
    if noise in ("none", "gaussian"):
        return R
    if noise == "vmf":
        e1 = torch.zeros(4, dtype=R.dtype, device=R.device)
        e1[0] = 1
        d = VonMisesFisher(e1, torch.tensor(float(kappa), dtype=R.dtype, device=R.device),
                           validate_args=False)
        qw = d.sample((num, S), generator=generator)
        return R @ quaternion_to_matrix_fast(qw)
    std = kappa_to_tangent_std(kappa) if tangent_std is None else tangent_std
    v = torch.randn(num, S, 3, generator=generator, dtype=R.dtype, device=R.device) * std
    return R @ so3_exp(v)


_VMF_CACHE: dict = {}


def _vmf_identity(kappa: float, dtype: torch.dtype, device: torch.device) -> VonMisesFisher:
    """vMF on S^3 around the identity quaternion (cached per kappa/dtype/device)."""
    key = (kappa, dtype, str(device))
    d = _VMF_CACHE.get(key)
    if d is None:
        e1 = torch.zeros(4, dtype=dtype, device=device)
        e1[0] = 1
        d = VonMisesFisher(e1, torch.tensor(kappa, dtype=dtype, device=device))
        _VMF_CACHE[key] = d
    return d


class ManifoldProposal(Proposal):
    """Sample poses on the sensor manifold (the paper's manifold sampling, MS).

    Args:
        manifold: the :class:`~torchmocap.ik.SensorManifold` (skeleton + sensor placement).
        active_std: scalar or ``(d,)`` diffusion std of the active coordinates.
        noise: sensor noise model, one of :data:`NOISE_MODELS`.
        kappa: vMF concentration (``"vmf"``); also sets the default of the other noise scales.
        gaussian_std: std (radians) of the GN noise on the passive parameters; default
            ``2/sqrt(kappa)`` (3.6 deg at kappa = 1000, the "equivalent dispersion").
        tangent_std: std (radians) for ``"tangent_gaussian"``; default ``2/sqrt(kappa)``.
        clamp_active: clamp diffused active coordinates into the joint limits.
        compile: compile the manifold's ``g^{-1}`` core with ``torch.compile`` (see
            :meth:`~torchmocap.ik.SensorManifold.compile_inverse`; ~3x faster per frame on a
            CPU after tens of seconds of compilation per input signature).
        compute_residual: report the worst sensor residual in ``stats`` (~40% extra time).
            Default (None): only when some passive joint's axes are not mutually orthogonal
            (otherwise every rotation is reachable and the residual is round-off, ~1e-6 deg
            in float32).

    ``sample(context, num, generator)`` needs ``context.sensors`` (``(S, 3, 3)``/``(S, 4)``, or
    per particle). ``stats``: ``residual_max_deg``, ``within_limits`` (fraction of passive
    joints inside limits), ``gimbal`` (count), ``seconds``.
    """

    def __init__(
        self,
        manifold: SensorManifold,
        active_std: float | Sequence[float] | torch.Tensor = 0.05,
        noise: str = "vmf",
        kappa: float = 1000.0,
        gaussian_std: float | None = None,
        tangent_std: float | None = None,
        clamp_active: bool = True,
        compute_residual: bool | None = None,
        compile: bool = False,
    ) -> None:
        super().__init__()
        if noise not in NOISE_MODELS:
            raise ValueError(f"noise: expected one of {NOISE_MODELS}, got {noise!r}")
        if not kappa > 0:
            raise ValueError(f"kappa: expected a value > 0, got {kappa}")
        self.manifold = manifold
        if compile:
            manifold.compile_inverse()
        self.noise = noise
        self.kappa = float(kappa)
        self.gaussian_std = float(kappa_to_tangent_std(kappa) if gaussian_std is None
                                  else gaussian_std)
        self.tangent_std = float(kappa_to_tangent_std(kappa) if tangent_std is None
                                 else tangent_std)
        self.clamp_active = clamp_active
        self.compute_residual = (not manifold._orthogonal if compute_residual is None
                                 else bool(compute_residual))
        d = manifold.num_active
        self.register_buffer("active_std", as_std(active_std, d, "active_std"))
        sk = manifold.skeleton
        self.register_buffer("active_lower", sk.lower[manifold.active_index].clone())
        self.register_buffer("active_upper", sk.upper[manifold.active_index].clone())

    def decode(
        self,
        x_a: torch.Tensor,
        sensors: torch.Tensor,
        generator: torch.Generator | None = None,
        reference: torch.Tensor | None = None,
    ):
        """``g^{-1}(x_a, noisy sensors)`` for ``x_a (P, d)``; returns the ManifoldSolution.

        Useful as the ``decode`` of an annealer that diffuses in the active space."""
        m = self.manifold
        num, S = x_a.shape[0], m.num_sensors
        R = sensor_rotations(sensors, S).to(x_a.dtype)
        noise = None
        if self.noise == "vmf":  # right-multiplied quaternion noise (eq. 16), fused in g^{-1}
            noise = _vmf_identity(self.kappa, x_a.dtype, x_a.device).sample(
                (num, S), generator=generator)
        elif self.noise == "tangent_gaussian":
            v = torch.randn(num, S, 3, generator=generator, dtype=x_a.dtype, device=x_a.device)
            noise = axis_angle_to_quaternion(v * self.tangent_std)
        sol = m.inverse(x_a, R, reference=reference, noise=noise,
                        compute_residual=self.compute_residual, validate=False)
        if self.noise == "gaussian":
            sol.theta = add_parameter_noise(sol.theta, m.passive_index.flatten(),
                                            self.gaussian_std, generator)
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
        xa = base.index_select(-1, m.active_index)
        std = self.active_std.to(xa.dtype)
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
