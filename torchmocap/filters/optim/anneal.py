"""Annealed particle optimisation (interacting simulated annealing) on generic particles.

Minimises an energy ``V(x) -> (P,)`` (lower is better, ``V = −log p``) over particles
``x (P, D)``, following Deutscher & Reid's annealed particle filter and Gall et al.'s
interacting simulated annealing, as used in Pons-Moll et al. §4.3 (15 layers, 200 particles):

for layer ``k = 0 … K−1``:

1. (``k > 0``) **select** ancestors from the weighted set of layer ``k−1`` (multinomial,
   systematic, stratified, residual, or Gall's keep/redraw), then **diffuse** them with a noise
   that shrinks per layer, then project onto the box ``[lower, upper]`` (clamp or reflect);
2. **evaluate** ``V(decode(x))`` — ``decode`` maps the optimisation parameters (e.g. the active
   parameters of a lower-dimensional parameterisation) to what the energy sees;
3. **weight** ``π ∝ exp(−β_k V)`` in log space, with ``β_k`` from the schedule (default: the ESS
   fraction of the weights equals α = 0.5).

The estimate is the weighted mean of the last layer (Pons-Moll eq. 18), or any
``mean_fn(particles, weights)``. ``K`` energy evaluations of ``P`` particles are made; the
annealer is gradient-free and runs the energy under ``torch.no_grad``. All randomness comes from
one ``torch.Generator``: the same seed gives the same result.

Shapes: ``P`` particles, ``D`` dims of the optimisation parameters, ``K`` layers.

Example:
    >>> energy = lambda x: ((x - 1.0) ** 2).sum(-1)
    >>> x0 = torch.randn(100, 3, generator=torch.Generator().manual_seed(0))
    >>> res = anneal(energy, x0, layers=10, generator=torch.Generator().manual_seed(1))
    >>> res.estimate.shape, res.beta.shape
    (torch.Size([3]), torch.Size([10]))
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from torchmocap.filters.optim.resampling import (
    MultinomialResampler,
    as_resampler,
    effective_sample_size,
)
from torchmocap.filters.optim.schedules import (
    AnnealingSchedule,
    annealing_log_weights,
    as_schedule,
    check_energies,
)
from torchmocap.proposals.bounds import as_bound as _as_bound
from torchmocap.proposals.bounds import bound_particles

__all__ = [
    "AnnealingResult",
    "GeometricDiffusion",
    "CovarianceDiffusion",
    "Diffusion",
    "anneal",
    "bound_particles",
    "default_diffusion",
    "rotation_mean_fn",
    "weighted_mean",
]

Energy = Callable[[torch.Tensor], torch.Tensor]
Diffusion = Callable[[torch.Tensor, int, "torch.Generator | None"], torch.Tensor]
"""``diffusion(particles (P, D), step, generator) -> (P, D)``; ``step = 0`` for the first
mutation (between layers 0 and 1)."""


# --------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------


def weighted_mean(particles: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Weighted mean ``Σ_i w_i x_i`` (eq. 18): ``particles (P, D)``, ``weights (P,)`` → ``(D,)``.

    ``weights`` must be normalised.
    """
    return (weights[:, None] * particles).sum(0)


def rotation_mean_fn(
    rotation_groups: Sequence,
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """A ``mean_fn`` for :func:`anneal` that averages rotation coordinates on SO(3).

    Coordinates outside the groups get the weighted mean; each
    :class:`~torchmocap.filters.tracking.prediction.RotationGroup` (or plain index triple = rotation
    vector) gets the chordal weighted mean ``proj_SO(3)(Σ w_i R_i)`` converted back with the
    group's ``from_matrix`` (reference: the highest-weight particle). Averaging angles directly
    fails at the ±π seam: yaws of +3.1 and −3.1 average to 0, the opposite direction.
    """
    from torchmocap.filters.optim.rotations import angles_from_matrix, as_groups, euler_matrix

    groups = as_groups(rotation_groups)
    # Euler-type groups (``RotationGroup.from_axes``) are averaged and inverted in one batch
    euler = [g for g in groups if g.axes is not None and g.from_matrix is None]
    others = [g for g in groups if not (g.axes is not None and g.from_matrix is None)]
    eidx = torch.tensor([g.indices for g in euler], dtype=torch.long).reshape(-1, 3)
    eaxes = (torch.stack([g.axes for g in euler]) if euler
             else torch.zeros(0, 3, 3, dtype=torch.float64))

    def chordal(R: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """``proj_SO(3)(sum_i w_i R_i)`` of ``R (P, ..., 3, 3)`` float64 → ``(..., 3, 3)``."""
        w = weights.to(torch.float64).reshape(-1, *([1] * (R.dim() - 1)))
        U, _, Vh = torch.linalg.svd((w * R).sum(0))
        fix = torch.ones(*U.shape[:-1], dtype=R.dtype, device=R.device)
        fix[..., 2] = torch.sign(torch.linalg.det(U @ Vh))
        return (U * fix[..., None, :]) @ Vh

    def mean_fn(particles: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        out = weighted_mean(particles, weights).clone()
        ref_i = int(torch.argmax(weights))
        if euler:
            idx = eidx.to(particles.device)
            ax = eaxes.to(particles.device)
            R = euler_matrix(ax, particles[:, idx].to(torch.float64))  # (P, G, 3, 3)
            vals = angles_from_matrix(lambda t: euler_matrix(ax, t), chordal(R, weights),
                                      particles[ref_i, idx])
            out[idx.reshape(-1)] = vals.reshape(-1).to(out.dtype)
        for g in others:
            idx = list(g.indices)
            R = g.matrix(particles[:, idx]).to(torch.float64)
            ref = particles[ref_i, idx]
            out[idx] = g.values(chordal(R, weights).to(particles.dtype), ref).to(out.dtype)
        return out

    return mean_fn


def _check_sigma(sigma, name: str) -> torch.Tensor:
    s = torch.as_tensor(sigma, dtype=torch.float64)
    if s.dim() > 1 or bool((s < 0).any()) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"{name}: expected a non-negative finite scalar or (D,) vector")
    return s


class GeometricDiffusion:
    """Gaussian diffusion with per-DoF std shrinking geometrically: ``σ_k = σ_0 · decay^k``.

    ``decay = √α`` (with α = 0.5) is PARSEC bodytrack's choice (:meth:`parsec`); ``decay = 0.5``
    is VXL's halving.

    Args:
        sigma0: initial std, scalar or ``(D,)`` (units of the particle coordinates).
        decay: per-layer factor in ``(0, 1]``.
    """

    def __init__(self, sigma0: torch.Tensor | float, decay: float = math.sqrt(0.5)) -> None:
        self.sigma0 = _check_sigma(sigma0, "sigma0")
        if not (0.0 < decay <= 1.0):
            raise ValueError(f"decay: expected a factor in (0, 1], got {decay}")
        self.decay = float(decay)

    @classmethod
    def parsec(cls, sigma0: torch.Tensor | float, alpha: float = 0.5) -> GeometricDiffusion:
        """PARSEC's schedule: the std vector is scaled by ``√alpha`` per layer."""
        return cls(sigma0, math.sqrt(alpha))

    def sigma(self, step: int, like: torch.Tensor) -> torch.Tensor:
        """Std at mutation ``step``: scalar or ``(D,)`` in ``like``'s dtype/device."""
        s = self.sigma0.to(dtype=like.dtype, device=like.device) * self.decay**step
        if s.dim() == 1 and s.shape[0] != like.shape[-1]:
            raise ValueError(
                f"sigma0: has {s.shape[0]} entries but particles have D = {like.shape[-1]}"
            )
        return s

    def __call__(
        self, particles: torch.Tensor, step: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        z = torch.randn(
            particles.shape, generator=generator, dtype=particles.dtype, device=particles.device
        )
        return particles + self.sigma(step, particles) * z

    def __repr__(self) -> str:
        return f"GeometricDiffusion(sigma0={self.sigma0.tolist()}, decay={self.decay})"


class CovarianceDiffusion:
    """Gaussian diffusion from the particle covariance (Gall et al.'s ISA mutation).

    ``Σ = ρ/(P−1) Σ_i (x_i − μ)(x_i − μ)ᵀ + δ I`` of the selected particles; it shrinks as the
    particles concentrate. With ``P ≈ 200`` and ``D ≈ 16–31`` the full covariance is poorly
    estimated: ``diagonal=True`` keeps only the per-DoF variances. (Gall's constants ρ, δ are
    unverified; ``rho = 0.5`` is a common choice.)

    With a constant ``ρ`` and the ESS schedule the particle cloud settles at a constant
    "temperature" instead of contracting (selection at ESS/N = α shrinks the spread by a factor
    that diffusion by ``1 + ρ`` undoes): ``decay < 1`` scales ρ by ``decay^k`` at mutation ``k``
    so the cloud keeps cooling.

    Args:
        rho: scale of the sample covariance (at the first mutation).
        delta: ridge ``δ`` (variance units) keeping Σ positive definite.
        diagonal: use only the diagonal of the sample covariance.
        decay: per-mutation factor on ``rho`` in ``(0, 1]`` (1 = Gall's constant ρ).
    """

    def __init__(
        self,
        rho: float = 0.5,
        delta: float = 1e-8,
        diagonal: bool = False,
        decay: float = 1.0,
    ) -> None:
        if not rho > 0:
            raise ValueError(f"rho: expected a positive number, got {rho}")
        if not delta >= 0:
            raise ValueError(f"delta: expected a non-negative number, got {delta}")
        if not (0.0 < decay <= 1.0):
            raise ValueError(f"decay: expected a factor in (0, 1], got {decay}")
        self.rho = float(rho)
        self.delta = float(delta)
        self.diagonal = bool(diagonal)
        self.decay = float(decay)

    def covariance(self, particles: torch.Tensor, step: int = 0) -> torch.Tensor:
        """``(P, D) -> (D, D)`` (or ``(D,)`` variances when diagonal), float64, at ``step``."""
        x = particles.to(torch.float64)
        p = x.shape[0]
        xc = x - x.mean(0, keepdim=True)
        denom = max(p - 1, 1)
        rho = self.rho * self.decay**step
        if self.diagonal:
            return rho * (xc**2).sum(0) / denom + self.delta
        cov = rho * (xc.T @ xc) / denom
        return cov + self.delta * torch.eye(x.shape[1], dtype=x.dtype, device=x.device)

    def __call__(
        self, particles: torch.Tensor, step: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        cov = self.covariance(particles, step)
        z = torch.randn(
            particles.shape, generator=generator, dtype=torch.float64, device=particles.device
        )
        if self.diagonal:
            noise = z * cov.sqrt()
        else:
            chol, info = torch.linalg.cholesky_ex(cov)
            if int(info) != 0:  # rank-deficient with delta = 0: add a relative jitter
                jitter = 1e-10 * float(cov.diagonal().mean().clamp(min=1e-300))
                eye = torch.eye(cov.shape[0], dtype=cov.dtype, device=cov.device)
                chol = torch.linalg.cholesky(cov + jitter * eye)
            noise = z @ chol.T
        return particles + noise.to(particles.dtype)

    def __repr__(self) -> str:
        return (
            f"CovarianceDiffusion(rho={self.rho}, delta={self.delta}, "
            f"diagonal={self.diagonal}, decay={self.decay})"
        )


def default_diffusion(layers: int) -> CovarianceDiffusion:
    """The default mutation for ``layers`` layers: diagonal particle covariance with ρ = 0.5,
    scaled down 10× between the first and the last mutation (``decay = 0.1^(1/(K−2))``).

    Measured on a 16-D rippled quadratic (``tests/filters/test_annealed.py``): a constant ρ
    (Gall) keeps the cloud at a fixed spread under the ESS schedule, and the full covariance is
    poorly estimated from a few hundred particles in D ≥ 16 (max error 0.49 vs 0.09 diagonal).
    """
    decay = 0.1 ** (1.0 / max(layers - 2, 1))
    return CovarianceDiffusion(rho=0.5, diagonal=True, decay=decay)


# --------------------------------------------------------------------------------------------
# result and optimiser
# --------------------------------------------------------------------------------------------


@dataclass
class AnnealingResult:
    """Output of :func:`anneal`.

    Attributes:
        estimate: ``mean_fn(particles, weights)`` of the last layer, ``(D,)`` for the default
            weighted mean (eq. 18).
        particles: last-layer particles ``(P, D)``.
        log_weights: normalised log weights of the last layer ``(P,)``.
        energies: last-layer energies ``(P,)``.
        best: lowest-energy particle seen in any layer ``(D,)``; ``best_energy`` its energy.
        beta, ess, mean_energy, min_energy: per-layer diagnostics ``(K,)`` (float64): inverse
            temperature, effective sample size of the weights, mean of the finite energies and
            the minimum energy.
    """

    estimate: torch.Tensor
    particles: torch.Tensor
    log_weights: torch.Tensor
    energies: torch.Tensor
    best: torch.Tensor
    best_energy: torch.Tensor
    beta: torch.Tensor
    ess: torch.Tensor
    mean_energy: torch.Tensor
    min_energy: torch.Tensor

    @property
    def weights(self) -> torch.Tensor:
        """Normalised weights of the last layer ``(P,)``."""
        return torch.exp(self.log_weights)

    @property
    def num_layers(self) -> int:
        return int(self.beta.shape[0])


def _evaluate(
    energy: Energy,
    decode: Callable[[torch.Tensor], object] | None,
    x: torch.Tensor,
    layer: int,
) -> tuple[torch.Tensor, bool]:
    """The energies ``(P,)`` of ``x`` (typed errors for NaN, ``-inf`` or no finite energy) and
    whether all of them are finite."""
    with torch.no_grad():
        v = energy(decode(x) if decode is not None else x)
    p = x.shape[0]
    if not isinstance(v, torch.Tensor):
        raise TypeError(f"energy: expected a tensor of shape ({p},), got {type(v).__name__}")
    if v.shape != (p,):
        raise ValueError(
            f"energy: expected shape ({p},) for {p} particles, got {tuple(v.shape)} (layer {layer})"
        )
    if not v.is_floating_point():
        v = v.to(x.dtype)
    if bool(torch.isfinite(v).all()):  # the common case: one test
        return v, True
    nan = torch.isnan(v)
    if bool(nan.any()):
        raise ValueError(
            f"energy: returned NaN for {int(nan.sum())} of {p} particles at layer {layer}"
        )
    if bool((v == -math.inf).any()):
        raise ValueError(f"energy: returned -inf at layer {layer} (energies must be > -inf)")
    if not bool(torch.isfinite(v).any()):
        raise ValueError(f"energy: returned +inf for every particle at layer {layer}")
    check_energies(v, "energy")
    return v, False


def anneal(
    energy: Energy,
    particles: torch.Tensor,
    *,
    layers: int = 15,
    schedule: AnnealingSchedule | None = None,
    selection: Callable[..., torch.Tensor] | None = None,
    diffusion: Diffusion | None = None,
    lower: torch.Tensor | float | None = None,
    upper: torch.Tensor | float | None = None,
    boundary: str = "clamp",
    decode: Callable[[torch.Tensor], object] | None = None,
    mean_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    generator: torch.Generator | None = None,
    callback: Callable[[int, torch.Tensor, torch.Tensor, torch.Tensor], None] | None = None,
    log_prior: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> AnnealingResult:
    """Annealed particle optimisation of ``energy`` from the initial set ``particles``.

    Args:
        energy: ``V(y) -> (P,)``, lower is better, with ``y = decode(x)`` (or ``x``). NaN or
            ``−inf`` energies raise ``ValueError`` naming ``energy``; ``+inf`` means weight zero.
        particles: initial set ``(P, D)`` (e.g. predicted poses plus noise); projected onto the
            bounds before the first evaluation. ``P`` is kept for every layer.
        layers: number ``K ≥ 1`` of layers (energy evaluations); ``K − 1`` select+diffuse steps.
        schedule: a schedule object ``(layer, energies (P,)) -> β``; default
            :class:`~torchmocap.filters.ESSSchedule` (ESS fraction 0.5).
        selection: a resampler ``(log_w, generator) -> idx``; default
            :class:`~torchmocap.filters.MultinomialResampler`.
        diffusion: ``(particles, step, generator) -> particles``; default
            :func:`default_diffusion` (diagonal particle covariance, cooling 10× over the run).
        lower, upper: box bounds, scalar or ``(D,)`` (e.g. ``skeleton.lower``); ±inf allowed.
        boundary: ``"clamp"`` or ``"reflect"`` (see :func:`bound_particles`).
        decode: maps particles ``(P, D)`` to the energy's input (e.g. active parameters →
            full pose); any callable.
        mean_fn: ``(particles (P, D), weights (P,)) -> estimate``; default weighted mean. To
            average decoded poses (eq. 18) or rotations differently, pass your own.
        generator: the only source of randomness.
        callback: called as ``callback(layer, particles, energies, log_weights)`` per layer.
        log_prior: optional ``log p(y) (P,)`` (up to a constant) added to every layer's
            log-weights untempered: layer ``k`` targets ``exp(−β_k V(y)) p(y)``. ``β`` is still
            chosen from the energies alone (the schedule sees ``V``).
    Returns:
        :class:`AnnealingResult` with per-layer diagnostics of length ``K``.
    """
    if not isinstance(particles, torch.Tensor) or not particles.is_floating_point():
        raise TypeError("particles: expected a floating-point torch.Tensor of shape (P, D)")
    if particles.dim() != 2 or particles.shape[0] < 1 or particles.shape[1] < 1:
        raise ValueError(f"particles: expected shape (P, D), got {tuple(particles.shape)}")
    if not bool(torch.isfinite(particles).all()):
        raise ValueError("particles: expected finite values, found NaN or inf")
    if not isinstance(layers, int) or layers < 1:
        raise ValueError(f"layers: expected an int >= 1, got {layers!r}")
    if not callable(energy):
        raise TypeError(f"energy: expected a callable, got {type(energy).__name__}")
    sched = as_schedule(schedule)
    select = as_resampler(selection, "selection", MultinomialResampler)
    diffuse = diffusion if diffusion is not None else default_diffusion(layers)
    mean = mean_fn if mean_fn is not None else weighted_mean
    lo = _as_bound(lower, particles, "lower", -math.inf)
    hi = _as_bound(upper, particles, "upper", math.inf)
    if boundary not in ("clamp", "reflect"):
        raise ValueError(f"boundary: expected 'clamp' or 'reflect', got {boundary!r}")

    x = bound_particles(particles, lo, hi, "clamp")
    p = x.shape[0]
    f64 = dict(dtype=torch.float64, device=x.device)
    betas = torch.empty(layers, **f64)
    ess = torch.empty(layers, **f64)
    mean_e = torch.empty(layers, **f64)
    min_e = torch.empty(layers, **f64)
    best, best_e = x[0], torch.tensor(math.inf, **f64)
    log_w = torch.zeros(p, dtype=x.dtype, device=x.device)
    v = torch.zeros(p, dtype=x.dtype, device=x.device)
    for k in range(layers):
        if k > 0:
            idx = select(log_w, generator)
            if idx.shape != (p,):
                raise ValueError(f"selection: expected ({p},) indices, got {tuple(idx.shape)}")
            x = diffuse(x[idx], k - 1, generator)
            if x.shape != (p, particles.shape[1]):
                raise ValueError(f"diffusion: changed the particle shape to {tuple(x.shape)}")
            x = bound_particles(x, lo, hi, boundary)
        v, all_finite = _evaluate(energy, decode, x, k)
        beta = torch.as_tensor(sched(k, v), dtype=torch.float64)
        if beta.numel() != 1 or not bool(beta >= 0) or bool(torch.isnan(beta)):
            raise ValueError(f"schedule: returned an invalid beta {beta} at layer {k}")
        lw = annealing_log_weights(v.to(torch.float64), beta.reshape(()).to(x.device))
        if log_prior is not None:
            with torch.no_grad():
                lp = log_prior(x if decode is None else decode(x))
            if lp.shape != (p,) or bool(torch.isnan(lp).any()):
                raise ValueError(f"log_prior: expected ({p},) values, not NaN")
            lw = lw + lp.to(lw)
        log_w = (lw - torch.logsumexp(lw, 0)).to(x.dtype)
        betas[k] = beta.reshape(())
        ess[k] = effective_sample_size(lw)
        if all_finite:
            mean_e[k] = v.to(torch.float64).mean()
            i_min = int(torch.argmin(v))
        else:
            finite = torch.isfinite(v)
            mean_e[k] = v[finite].to(torch.float64).mean()
            i_min = int(torch.argmin(torch.where(finite, v, math.inf)))
        min_e[k] = float(v[i_min])
        if min_e[k] < best_e:
            best, best_e = x[i_min].clone(), min_e[k].clone()
        if callback is not None:
            callback(k, x, v, log_w)
    estimate = mean(x, torch.exp(log_w))
    return AnnealingResult(estimate=estimate, particles=x, log_weights=log_w, energies=v,
                           best=best, best_energy=best_e, beta=betas, ess=ess,
                           mean_energy=mean_e, min_energy=min_e)
