"""The proposal interface: ``sample(context, num, generator) -> Proposed``.

A proposal draws ``P`` candidate poses ``theta (P, D)`` given a :class:`ProposalContext` (the
previous particles or estimate, this frame's observations such as sensor orientations). It
returns a :class:`Proposed` with the particles, ``log_q`` when the proposal density is known
(so that an SIR filter can form its correction factor), a per-particle ``valid`` flag when some
slots could not be filled as asked (e.g. a capped rejection sampler), and a ``stats`` dict
(acceptance rates, tries, residuals, timings).

:class:`GaussianDiffusionProposal` is the simplest concrete proposal — per-DoF Gaussian
diffusion of the previous particles in the full pose space — used as the inner sampler of the
paper's rejection-sampling baseline (Pons-Moll et al. 2010, Fig. 9b).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

__all__ = [
    "Proposal",
    "ProposalContext",
    "Proposed",
    "GaussianDiffusionProposal",
    "select_ancestors",
    "as_std",
]


@dataclass
class ProposalContext:
    """What a proposal may condition on.

    Attributes:
        previous: ``(P0, D)`` previous particles or ``(D,)`` previous estimate.
        log_weights: optional ``(P0,)`` log weights of ``previous`` (ancestors are drawn from
            them when ``P0 != num``; uniform otherwise).
        sensors: optional ``(S, 3, 3)`` / ``(S, 4)`` sensor orientations of this frame
            (or per particle ``(P, S, ...)``).
        extras: anything else a proposal needs (observations of other modalities).
    """

    previous: torch.Tensor
    log_weights: torch.Tensor | None = None
    sensors: torch.Tensor | None = None
    extras: dict[str, Any] = field(default_factory=dict)


@dataclass
class Proposed:
    """Output of :meth:`Proposal.sample`.

    Attributes:
        particles: ``(P, D)`` proposed poses.
        log_q: ``(P,)`` log proposal density, when known.
        log_prior: ``(P,)`` log prior density, when known.
        valid: ``(P,)`` bool, False for slots that do not satisfy the proposal's constraint
            (e.g. a rejection sampler out of tries returns its best candidate there).
        stats: diagnostics (floats/ints/tensors), e.g. ``acceptance_rate``, ``tries``.
    """

    particles: torch.Tensor
    log_q: torch.Tensor | None = None
    log_prior: torch.Tensor | None = None
    valid: torch.Tensor | None = None
    stats: dict[str, Any] = field(default_factory=dict)


class Proposal(nn.Module):
    """Base class: subclasses implement :meth:`sample`; ``forward`` calls it."""

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        raise NotImplementedError(f"{type(self).__name__} must implement sample()")

    def forward(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        return self.sample(context, num, generator)


def _check_num(num: int) -> None:
    if not isinstance(num, int) or num < 1:
        raise ValueError(f"num: expected an int >= 1, got {num!r}")


def select_ancestors(
    context: ProposalContext, num: int, num_dofs: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """``(num, D)`` starting poses: the estimate repeated, the particles themselves when
    ``P0 == num`` (and no weights), or ancestors drawn by weight / uniformly otherwise."""
    _check_num(num)
    prev = context.previous
    if not isinstance(prev, torch.Tensor) or prev.shape[-1:] != (num_dofs,) or prev.dim() > 2:
        shape = tuple(prev.shape) if isinstance(prev, torch.Tensor) else type(prev).__name__
        raise ValueError(f"context.previous: expected (P0, {num_dofs}) or ({num_dofs},), "
                         f"got {shape}")
    if not bool(torch.isfinite(prev).all()):
        raise ValueError("context.previous: expected finite values, found NaN or inf")
    if prev.dim() == 1:
        return prev.expand(num, num_dofs)
    p0 = prev.shape[0]
    if context.log_weights is None:
        if p0 == num:
            return prev
        idx = torch.randint(p0, (num,), generator=generator, device=prev.device)
        return prev[idx]
    lw = context.log_weights
    if lw.shape != (p0,):
        raise ValueError(f"context.log_weights: expected ({p0},), got {tuple(lw.shape)}")
    w = torch.softmax(lw.double(), 0)
    idx = torch.multinomial(w, num, replacement=True, generator=generator)
    return prev[idx.to(prev.device)]


def as_std(std: float | Sequence[float] | torch.Tensor, n: int, name: str) -> torch.Tensor:
    """A ``(n,)`` float tensor of non-negative finite standard deviations."""
    t = torch.as_tensor(std, dtype=torch.float32).flatten()
    if t.numel() == 1:
        t = t.expand(n).clone()
    if t.shape != (n,):
        raise ValueError(f"{name}: expected a scalar or ({n},) std, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or bool((t < 0).any()):
        raise ValueError(f"{name}: expected finite values >= 0")
    return t


class GaussianDiffusionProposal(Proposal):
    """``theta = ancestor + N(0, diag(std^2))`` in the full pose space (optionally clamped).

    Args:
        std: scalar or ``(D,)`` per-DoF standard deviation (radians; metres for translations).
        num_dofs: ``D``.
        lower, upper: optional ``(D,)`` limits; samples are clamped into them when given (then
            ``log_q`` is not reported).
    """

    def __init__(
        self,
        std: float | Sequence[float] | torch.Tensor,
        num_dofs: int,
        lower: torch.Tensor | None = None,
        upper: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        self.num_dofs = num_dofs
        self.register_buffer("std", as_std(std, num_dofs, "std"))
        self.register_buffer("lower", None if lower is None else lower.detach().float().clone())
        self.register_buffer("upper", None if upper is None else upper.detach().float().clone())

    def sample(
        self, context: ProposalContext, num: int, generator: torch.Generator | None = None
    ) -> Proposed:
        base = select_ancestors(context, num, self.num_dofs, generator)
        std = self.std.to(base.dtype)
        eps = torch.randn(num, self.num_dofs, generator=generator, dtype=base.dtype,
                          device=base.device)
        theta = base + eps * std
        log_q = None
        if self.lower is not None or self.upper is not None:
            lo = self.lower.to(base.dtype) if self.lower is not None else None
            hi = self.upper.to(base.dtype) if self.upper is not None else None
            theta = torch.clamp(theta, lo, hi)
        else:
            pos = std > 0
            z = eps[:, pos]
            log_q = (-0.5 * (z * z).sum(-1) - torch.log(std[pos]).sum()
                     - 0.5 * math.log(2 * math.pi) * int(pos.sum()))
        return Proposed(particles=theta, log_q=log_q)
