"""Annealing schedules: the inverse temperature ``β_k`` of annealed particle optimisation.

Layer ``k`` weights the particles by ``π ∝ exp(−β_k V(x))`` (energy ``V = −log p``, lower is
better). Three schedules:

- :class:`ESSSchedule` (default, Deutscher & Reid; every public implementation uses α = 0.5):
  choose ``β`` so the effective sample size fraction ``ESS/N = (Σw)² / (N Σw²)`` equals α. ESS/N
  decreases monotonically in β, so :func:`ess_target_beta` solves for it on ``log β`` (a grid
  pass, then safeguarded Newton steps) in float64 and log space. It makes the overall scale of
  ``V`` irrelevant.
- :class:`PolynomialSchedule`: ``β_k = s·(k+1)^b``.
- :class:`GeometricSchedule`: ``β_k = β_0·c^k``.

A schedule is any callable ``(layer: int, energies (P,)) -> β`` (0-dim tensor).

Example:
    >>> sol = ess_target_beta(torch.randn(200), alpha=0.5)
    >>> round(float(sol.ess_fraction), 3)
    0.5
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import numpy as np
import torch

from torchmocap.filters.optim.components import as_strategy

__all__ = [
    "BetaSolution",
    "AnnealingSchedule",
    "ESSSchedule",
    "PolynomialSchedule",
    "GeometricSchedule",
    "check_energies",
    "annealing_log_weights",
    "ess_fraction_at_beta",
    "ess_target_beta",
    "as_schedule",
]


class BetaSolution(NamedTuple):
    """Result of :func:`ess_target_beta`: ``beta (...)`` and the ``ess_fraction (...)`` achieved."""

    beta: torch.Tensor
    ess_fraction: torch.Tensor


def check_energies(energies: torch.Tensor, name: str = "energies") -> None:
    """Raise a typed error unless ``energies (..., P)`` are usable for weighting.

    ``+inf`` is allowed (an impossible particle, weight zero) but every row needs one finite
    energy; NaN and ``-inf`` are errors.
    """
    if not isinstance(energies, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(energies).__name__}")
    if not energies.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {energies.dtype}")
    if energies.dim() < 1 or energies.shape[-1] < 1:
        raise ValueError(
            f"{name}: expected shape (..., P) with P >= 1, got {tuple(energies.shape)}"
        )
    if bool(torch.isfinite(energies).all()):  # the common case: one test
        return
    if bool(torch.isnan(energies).any()):
        n = int(torch.isnan(energies).sum())
        raise ValueError(f"{name}: {n} NaN energies (the energy function returned NaN)")
    if bool((energies == -math.inf).any()):
        raise ValueError(f"{name}: -inf energies are not allowed (lower is better, must be finite)")
    if bool((~torch.isfinite(energies)).all(dim=-1).any()):
        raise ValueError(f"{name}: every particle of a row has infinite energy")


def annealing_log_weights(energies: torch.Tensor, beta: torch.Tensor | float) -> torch.Tensor:
    """Log weights ``−β (V − min V)`` of ``energies (..., P)`` at inverse temperature ``beta``.

    Shifting by the row minimum keeps every finite particle's log weight finite even for huge β;
    ``+inf`` energies get ``−inf``; with ``β = 0`` all finite particles weigh the same.
    """
    check_energies(energies)
    beta = torch.as_tensor(beta, dtype=energies.dtype, device=energies.device)
    if bool((beta < 0).any()) or bool(torch.isnan(beta).any()):
        raise ValueError("beta: expected non-negative inverse temperatures")
    finite = torch.isfinite(energies)
    vmin = torch.where(finite, energies, math.inf).amin(dim=-1, keepdim=True)
    u = torch.where(finite, energies - vmin, 0.0)
    lw = -beta[..., None] * u
    return torch.where(finite, lw, -math.inf)


_GRID = 64  # log-beta grid points of the bracketing pass of :func:`ess_target_beta`


def _lse(x: torch.Tensor) -> torch.Tensor:
    """``logsumexp`` over the last dim, keepdim, for rows with a finite maximum (a few plain ops
    instead of ``torch.logsumexp``'s general ±inf handling; this sits in the β solver's loop)."""
    m = x.amax(-1, keepdim=True)
    return (x - m).exp_().sum(-1, keepdim=True).log_().add_(m)


def _log_ess_fraction(u: torch.Tensor, finite: torch.Tensor, beta: torch.Tensor) -> torch.Tensor:
    lw = torch.where(finite, -beta[..., None] * u, -math.inf)
    n = u.shape[-1]
    return (2 * _lse(lw) - _lse(2 * lw))[..., 0] - math.log(n)


def ess_fraction_at_beta(energies: torch.Tensor, beta: torch.Tensor | float) -> torch.Tensor:
    """ESS/N of the weights ``exp(−β V)``: ``energies (..., P)``, ``beta (...)`` → ``(...)``
    (float64)."""
    check_energies(energies)
    v = energies.to(torch.float64)
    finite = torch.isfinite(v)
    vmin = torch.where(finite, v, math.inf).amin(dim=-1, keepdim=True)
    u = torch.where(finite, v - vmin, 0.0)
    b = torch.as_tensor(beta, dtype=torch.float64, device=v.device).expand(v.shape[:-1])
    return torch.exp(_log_ess_fraction(u, finite, b))


def ess_target_beta(
    energies: torch.Tensor,
    alpha: float = 0.5,
    *,
    beta_max: float = 1e12,
    iterations: int = 48,
) -> BetaSolution:
    """Inverse temperature ``β`` with ``ESS(exp(−β V)) / P = alpha``, solved on ``log β``.

    Works in float64 and log space, batched over leading dims. ``ESS/P`` decreases from
    ``P_finite/P`` at ``β → 0`` to ``P_min/P`` (the number of particles sharing the minimum
    energy) at ``β → ∞``. Outside that range the nearest end is returned:

    - target above ``P_finite/P`` (only possible with ``+inf`` energies): ``β = 0``;
    - target not reached by ``beta_max`` (e.g. all energies equal): ``β = beta_max``.

    The returned ``ess_fraction`` is the one actually achieved, so callers can see the cap.

    Args:
        energies: ``(..., P)`` energies (lower is better); ``+inf`` allowed, NaN/−inf are errors.
        alpha: target ESS fraction in ``(0, 1]``.
        beta_max: cap on β (absolute; energies are shifted by their minimum, so huge β are safe).
        iterations: at most this many safeguarded Newton steps after the grid pass (converged
            to ~1e-13 in log β after 4-6 in practice; each falls back to bisection if needed).
    Returns:
        :class:`BetaSolution` with ``beta (...)`` and ``ess_fraction (...)`` (float64).
    """
    check_energies(energies)
    if not (0.0 < float(alpha) <= 1.0):
        raise ValueError(f"alpha: expected a target ESS fraction in (0, 1], got {alpha}")
    if not (beta_max > 0 and math.isfinite(beta_max)):
        raise ValueError(f"beta_max: expected a positive finite number, got {beta_max}")
    # a few hundred values, solved on the host: numpy's per-op cost is ~10x lower than torch's,
    # and on a GPU the copy costs less than the solver's many tiny kernels
    v = energies.detach().to(device="cpu", dtype=torch.float64)
    beta, frac = _solve_beta_numpy(v.numpy(), float(alpha), beta_max, iterations)
    return BetaSolution(torch.from_numpy(beta).to(energies.device),
                        torch.from_numpy(frac).to(energies.device))


def _log_ess_fraction_np(u: np.ndarray, finite: np.ndarray, beta: np.ndarray) -> np.ndarray:
    lw = np.where(finite, -beta[..., None] * u, -np.inf)
    m = lw.max(-1, keepdims=True)
    m2 = 2 * m
    lse = np.log(np.exp(lw - m).sum(-1)) + m[..., 0]
    lse2 = np.log(np.exp(2 * lw - m2).sum(-1)) + m2[..., 0]
    return 2 * lse - lse2 - math.log(u.shape[-1])


def _solve_beta_numpy(v: np.ndarray, alpha: float, beta_max: float, iterations: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ess_target_beta`'s solver (a grid pass over ``log β``, then safeguarded Newton
    steps on ``log β``, bisection whenever a step leaves the bracket) on a float64 array
    ``v (..., P)``; returns ``beta, ess_fraction (...)``."""
    log_alpha = math.log(alpha)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        finite = np.isfinite(v)
        vmin = np.where(finite, v, np.inf).min(-1, keepdims=True)
        u = np.where(finite, v - vmin, 0.0)
        umax = u.max(-1)
        safe_umax = np.where(umax > 0, umax, 1.0)
        lo = np.log(np.minimum(1e-9 / safe_umax, beta_max * 1e-3))
        hi = np.full(v.shape[:-1], math.log(beta_max))
        grid = np.linspace(0.0, 1.0, _GRID)
        s = lo[..., None] + (hi - lo)[..., None] * grid
        above = _log_ess_fraction_np(u[..., None, :], finite[..., None, :], np.exp(s)) > log_alpha
        j = np.clip(above.sum(-1, keepdims=True) - 1, 0, _GRID - 2)
        lo = np.take_along_axis(s, j, -1)[..., 0]
        hi = np.take_along_axis(s, j + 1, -1)[..., 0]
        x = 0.5 * (lo + hi)
        uz = np.where(finite, u, 0.0)
        neg_u = np.where(finite, -u, -np.inf)
        n = math.log(u.shape[-1])
        for _ in range(iterations):
            beta = np.exp(x)[..., None]
            lw = beta * neg_u
            w = np.exp(lw - lw.max(-1, keepdims=True))
            w2 = w * w
            s1, s2 = w.sum(-1), w2.sum(-1)
            a1, a2 = (w * uz).sum(-1), (w2 * uz).sum(-1)
            g = 2 * np.log(s1) - np.log(s2) - n - log_alpha
            dfds = 2 * beta[..., 0] * (a2 / s2 - a1 / s1)
            lo = np.where(g > 0, x, lo)
            hi = np.where(g > 0, hi, x)
            done = (np.abs(g) < 1e-13) | (hi - lo < 1e-13)
            if done.all():
                break
            step = x - g / dfds
            ok = np.isfinite(step) & (step >= lo) & (step <= hi)
            x = np.where(done, x, np.where(ok, step, 0.5 * (lo + hi)))
        beta = np.exp(x)
        cap = np.full_like(beta, beta_max)
        reaches_cap = _log_ess_fraction_np(u, finite, cap) >= log_alpha
        beta = np.where(reaches_cap, cap, beta)
        f0 = finite.sum(-1) / v.shape[-1]
        beta = np.where((f0 <= alpha) & ~reaches_cap, 0.0, beta)
        frac = np.exp(_log_ess_fraction_np(u, finite, beta))
    return np.asarray(beta, dtype=np.float64), np.asarray(frac, dtype=np.float64)


class AnnealingSchedule(Protocol):
    """``schedule(layer, energies (P,)) -> β`` (0-dim tensor, non-negative)."""

    def __call__(self, layer: int, energies: torch.Tensor) -> torch.Tensor: ...


class ESSSchedule:
    """β chosen per layer so the ESS fraction of ``exp(−β V)`` equals ``alpha`` (default 0.5).

    Thin wrapper of :func:`ess_target_beta`; ignores the layer index.
    """

    def __init__(self, alpha: float = 0.5) -> None:
        if not (0.0 < float(alpha) <= 1.0):
            raise ValueError(f"alpha: expected a target ESS fraction in (0, 1], got {alpha}")
        self.alpha = float(alpha)

    def __call__(self, layer: int, energies: torch.Tensor) -> torch.Tensor:
        return ess_target_beta(energies, self.alpha).beta

    def __repr__(self) -> str:
        return f"ESSSchedule(alpha={self.alpha})"


class _FixedSchedule:
    """A schedule whose ``β_k`` depends on the layer index only (not on the energies)."""

    def beta(self, layer: int) -> float:
        raise NotImplementedError

    def __call__(self, layer: int, energies: torch.Tensor | None = None) -> torch.Tensor:
        if layer < 0:
            raise ValueError(f"layer: expected a non-negative index, got {layer}")
        return torch.tensor(self.beta(layer), dtype=torch.float64)


def _positive(name: str, v) -> float:
    if not v > 0:
        raise ValueError(f"{name}: expected a positive number, got {v}")
    return float(v)


class PolynomialSchedule(_FixedSchedule):
    """``β_k = scale · (k + 1)^power`` for layer ``k = 0, 1, …``."""

    def __init__(self, power: float = 2.0, scale: float = 1.0) -> None:
        self.power = float(power)
        self.scale = _positive("scale", scale)

    def beta(self, layer: int) -> float:
        return self.scale * (layer + 1) ** self.power

    def __repr__(self) -> str:
        return f"PolynomialSchedule(power={self.power}, scale={self.scale})"


class GeometricSchedule(_FixedSchedule):
    """``β_k = beta0 · ratio^k`` for layer ``k = 0, 1, …``."""

    def __init__(self, ratio: float = 2.0, beta0: float = 1.0) -> None:
        self.ratio = _positive("ratio", ratio)
        self.beta0 = _positive("beta0", beta0)

    def beta(self, layer: int) -> float:
        return self.beta0 * self.ratio**layer

    def __repr__(self) -> str:
        return f"GeometricSchedule(ratio={self.ratio}, beta0={self.beta0})"


def as_schedule(schedule: AnnealingSchedule | None) -> AnnealingSchedule:
    """``schedule`` itself (a callable ``(layer, energies) -> β``), or :class:`ESSSchedule` with
    α = 0.5 for ``None``. Schedules are objects: a config chooses one by its ``_target_``."""
    return as_strategy(schedule, "schedule", ESSSchedule,
                       "schedule object such as torchmocap.filters.ESSSchedule()")
