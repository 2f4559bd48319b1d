"""Sequential importance resampling (SIR) particle filter steps (Hauberg & Pedersen §1.1).

Weights follow ``w_t ∝ w_{t−1} · p(z_t | x_t) · r_t`` with the correction factor
``r_t = p(x_t | x_{t−1}) / q(x_t | z_t, x_{t−1})`` (eqs. 1–2): ``r = 1`` when the proposal is
the motion prior (bootstrap filter); it is constant for rejection-truncated proposals; for
projected proposals (spatial prior + IK projection) ``q`` has no closed form and the filter is
approximate — pass no correction there and say so.

Everything is in log space. Resampling is adaptive: the incoming weights are resampled when
their ESS fraction drops below ``ess_threshold`` (1.0 = every step, 0 = never). Each step also
returns the log evidence increment ``log p̂(z_t | z_{1:t−1}) = logsumexp(log W_{t−1} + log
p(z_t|x_t) + log r_t)``; summed over steps it is an unbiased estimate *in the exponent*:
``E[p̂(z_{1:T})] = p(z_{1:T})``, so average likelihoods, not log-likelihoods, over repeats
(``mean(log L̂)`` is biased low by about var/2).

Shapes: ``P`` particles, ``D`` dims, ``T`` steps.

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> x = torch.randn(100, 2, generator=g)
    >>> step = sir_step(x, torch.zeros(100), lambda x, g: x + 0.1 * torch.randn(x.shape,
    ...                 generator=g), lambda x: -(x**2).sum(-1), generator=g)
    >>> step.particles.shape, step.log_weights.shape
    (torch.Size([100, 2]), torch.Size([100]))
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchmocap.filters.optim.resampling import (
    as_resampler,
    check_log_weights,
    effective_sample_size,
    normalize_log_weights,
)

__all__ = ["SIRStep", "SIRResult", "sir_step", "sir_filter"]

Propose = Callable[[torch.Tensor, "torch.Generator | None"], object]
"""``propose(particles (P, D), generator) -> new (P, D)`` or ``(new, log_r (P,))``."""


@dataclass
class SIRStep:
    """One SIR step.

    Attributes:
        particles: propagated particles ``(P, D)``.
        log_weights: normalised log weights ``(P,)``, float64.
        ancestors: ``(P,)`` index of each particle's parent in the input set.
        resampled: whether the input set was resampled first.
        ess: effective sample size of the new weights (0-dim, float64).
        log_evidence: ``log p̂(z_t | z_{1:t−1})`` (0-dim, float64).
    """

    particles: torch.Tensor
    log_weights: torch.Tensor
    ancestors: torch.Tensor
    resampled: bool
    ess: torch.Tensor
    log_evidence: torch.Tensor


def _check_vector(v, p: int, name: str, allow_neg_inf: bool = True) -> torch.Tensor:
    if not isinstance(v, torch.Tensor) or v.shape != (p,):
        shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
        raise ValueError(f"{name}: expected a ({p},) tensor, got {shape}")
    if bool(torch.isnan(v).any()):
        raise ValueError(f"{name}: returned NaN for {int(torch.isnan(v).sum())} of {p} particles")
    if bool((v == math.inf).any()):
        raise ValueError(f"{name}: returned +inf")
    if not allow_neg_inf and bool((v == -math.inf).any()):
        raise ValueError(f"{name}: returned -inf")
    return v


def sir_step(
    particles: torch.Tensor,
    log_weights: torch.Tensor,
    propose: Propose,
    log_likelihood: Callable[[torch.Tensor], torch.Tensor],
    *,
    generator: torch.Generator | None = None,
    resampler: Callable[..., torch.Tensor] | None = None,
    ess_threshold: float = 0.5,
) -> SIRStep:
    """Resample (adaptively), propose, weight.

    Args:
        particles: ``(P, D)`` particles at ``t − 1``.
        log_weights: ``(P,)`` their (unnormalised) log weights.
        propose: ``(particles, generator) -> new`` or ``(new, log_r)`` with the log correction
            factor ``log p(x_t|x_{t−1}) − log q(x_t|z_t, x_{t−1})`` per particle.
        log_likelihood: ``(P, D) -> (P,)`` ``log p(z_t | x_t)``; ``−inf`` allowed.
        generator: the only source of randomness.
        resampler: a resampler ``(log_w, generator) -> indices`` (default
            :class:`~torchmocap.filters.SystematicResampler`).
        ess_threshold: resample when ESS/P of the input weights is below this.
    Returns:
        :class:`SIRStep`.
    """
    if not isinstance(particles, torch.Tensor) or particles.dim() != 2:
        raise ValueError("particles: expected a tensor of shape (P, D)")
    p = particles.shape[0]
    check_log_weights(log_weights, "log_weights")
    if log_weights.shape != (p,):
        raise ValueError(f"log_weights: expected shape ({p},), got {tuple(log_weights.shape)}")
    if not 0.0 <= ess_threshold <= 1.0:
        raise ValueError(f"ess_threshold: expected a fraction in [0, 1], got {ess_threshold}")
    select = as_resampler(resampler)
    lw = normalize_log_weights(log_weights.to(torch.float64))
    resampled = bool(effective_sample_size(lw) < ess_threshold * p) or ess_threshold == 1.0
    if resampled:
        ancestors = select(lw, generator)
        x = particles[ancestors]
        lw = torch.full_like(lw, -math.log(p))
    else:
        ancestors = torch.arange(p, device=particles.device)
        x = particles
    out = propose(x, generator)
    if isinstance(out, tuple):
        new, log_r = out
        log_r = _check_vector(log_r, p, "propose (log correction)").to(torch.float64)
    else:
        new, log_r = out, torch.zeros_like(lw)
    if not isinstance(new, torch.Tensor) or new.shape[0] != p:
        raise ValueError(f"propose: expected {p} particles, got {getattr(new, 'shape', new)}")
    ll = _check_vector(log_likelihood(new), p, "log_likelihood").to(torch.float64)
    inc = lw + ll + log_r
    log_ev = torch.logsumexp(inc, 0)
    if not bool(torch.isfinite(log_ev)):
        raise ValueError("log_likelihood: every particle has zero likelihood (all -inf)")
    new_lw = inc - log_ev
    return SIRStep(particles=new, log_weights=new_lw, ancestors=ancestors, resampled=resampled,
                   ess=effective_sample_size(new_lw), log_evidence=log_ev)


@dataclass
class SIRResult:
    """Output of :func:`sir_filter`: per-step weighted ``means (T, D)``, ``ess (T,)``,
    ``resampled (T,)`` flags, total ``log_evidence`` and the final particles/log weights."""

    means: torch.Tensor
    ess: torch.Tensor
    resampled: torch.Tensor
    log_evidence: torch.Tensor
    particles: torch.Tensor
    log_weights: torch.Tensor


def sir_filter(
    particles: torch.Tensor,
    steps: int,
    propose: Callable[[int, torch.Tensor, torch.Generator | None], object],
    log_likelihood: Callable[[int, torch.Tensor], torch.Tensor],
    *,
    log_weights: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    resampler: Callable[..., torch.Tensor] | None = None,
    ess_threshold: float = 0.5,
) -> SIRResult:
    """Run ``steps`` SIR steps; ``propose(t, particles, generator)``,
    ``log_likelihood(t, particles)`` for ``t = 0 … T−1`` (``particles`` are the prior draws
    at ``t = −1``)."""
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    p = particles.shape[0]
    lw = (
        torch.zeros(p, dtype=particles.dtype, device=particles.device)
        if log_weights is None
        else log_weights
    )
    x = particles
    means, ess, res = [], [], []
    total = torch.zeros((), dtype=torch.float64, device=particles.device)
    for t in range(steps):
        st = sir_step(
            x,
            lw,
            lambda xx, g, t=t: propose(t, xx, g),
            lambda xx, t=t: log_likelihood(t, xx),
            generator=generator,
            resampler=resampler,
            ess_threshold=ess_threshold,
        )
        x, lw = st.particles, st.log_weights
        w = torch.exp(lw)
        means.append((w[:, None] * x.to(torch.float64)).sum(0))
        ess.append(st.ess)
        res.append(st.resampled)
        total = total + st.log_evidence
    return SIRResult(
        means=torch.stack(means),
        ess=torch.stack(ess),
        resampled=torch.tensor(res, device=particles.device),
        log_evidence=total,
        particles=x,
        log_weights=lw.to(particles.dtype),
    )
