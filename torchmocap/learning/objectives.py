"""Training objectives for learned likelihoods: ranking and end-to-end (unrolled inference).

**Ranking** (:func:`ranking_loss`): for a frame with the true pose and ``K`` negatives, the
energies ``V (K+1,)`` define a distribution ``softmax(−V)`` over the candidates; the loss is its
cross-entropy to a target that puts the most mass on the truth and decays with each
candidate's pose error, ``softmax(−err / err_scale)`` (``err_scale → 0``: InfoNCE, the truth
must have the lowest energy; larger: the energy must also order the negatives by their error,
which is what annealing and descent use).

**End to end** — unroll an inference step from a perturbed start and penalise the error of its
result:

- :func:`unrolled_descent`: ``I`` steps of gradient descent on ``V`` (``create_graph``: the
  parameters' gradient flows through every step's ``∇V``), steps clipped per coordinate;
- :func:`unrolled_annealing`: ``L`` annealing layers with the tracker's proposal as the mutation
  kernel and the weighted mean as the estimate. Particles are sampled without gradient; the
  weights carry it. Resampling is **stop-gradient** resampling (REFERENCE §8): the selected
  particles keep the log weight ``lw_i − stop_gradient(lw_i)`` — zero in the forward pass, so
  the forward computation is exactly the annealer's, while the gradient of every earlier layer's
  weights reaches the estimate through its descendants.

Losses are mean joint position errors in metres (:func:`joint_error`).
Shapes: ``K`` candidates, ``P`` particles, ``D`` pose DoF, ``J`` joints.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch

from torchmocap.filters.optim.resampling import multinomial_resample
from torchmocap.filters.optim.schedules import ess_target_beta

__all__ = [
    "joint_error",
    "ranking_loss",
    "stop_gradient_resample",
    "unrolled_annealing",
    "unrolled_descent",
]

Energy = Callable[[torch.Tensor], torch.Tensor]


def joint_error(skeleton, theta: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Mean joint position error (metres) of ``theta (..., D)`` against ``truth (D,)``:
    ``(...)``; differentiable in ``theta``."""
    a = skeleton(theta.reshape(-1, theta.shape[-1]), check_finite=False).positions
    b = skeleton(truth[None].to(theta.dtype), check_finite=False).positions
    return (a - b).norm(dim=-1).mean(-1).reshape(theta.shape[:-1])


def ranking_loss(energies: torch.Tensor, errors: torch.Tensor, err_scale: float = 0.02
                 ) -> torch.Tensor:
    """Cross-entropy of ``softmax(−energies)`` to ``softmax(−errors / err_scale)``.

    Args:
        energies: ``(K,)`` candidate energies (the truth among them, error 0).
        errors: ``(K,)`` pose errors (metres); ``err_scale``: their temperature (metres, > 0).
    """
    if energies.shape != errors.shape or energies.dim() != 1:
        raise ValueError(f"energies, errors: expected two (K,) tensors, got "
                         f"{tuple(energies.shape)} and {tuple(errors.shape)}")
    if not err_scale > 0:
        raise ValueError(f"err_scale: expected a value > 0 (metres), got {err_scale!r}")
    target = torch.softmax(-errors.to(energies.dtype) / err_scale, 0)
    return -(target * torch.log_softmax(-energies, 0)).sum()


def unrolled_descent(energy: Energy, x0: torch.Tensor, steps: int = 5, lr: float = 0.02,
                     max_step: float = 0.1, lower: torch.Tensor | None = None,
                     upper: torch.Tensor | None = None) -> torch.Tensor:
    """Differentiable gradient descent ``x ← clamp(x − clip(lr ∇V(x), ±max_step), box)`` from
    ``x0 (P, D)`` for ``steps`` steps; returns the last iterate ``(P, D)``, a function of the
    energy's parameters (second-order: ``create_graph=True``).

    The energy must be row-independent (``V(x)[i]`` depends on ``x[i]`` only).
    """
    if steps < 0:
        raise ValueError(f"steps: expected an int >= 0, got {steps!r}")
    x = x0.detach().requires_grad_(True)
    for _ in range(steps):
        with torch.enable_grad():
            v = energy(x)
            (g,) = torch.autograd.grad(v.sum(), x, create_graph=True)
        step = (lr * g).clamp(-max_step, max_step)
        x = x - step
        if lower is not None and upper is not None:
            x = torch.maximum(torch.minimum(x, upper.to(x)), lower.to(x))
    return x


def stop_gradient_resample(log_w: torch.Tensor, generator: torch.Generator | None = None,
                           resampler=multinomial_resample) -> tuple[torch.Tensor, torch.Tensor]:
    """Resample ``log_w (P,)`` (normalised or not): ``indices (P,)`` drawn from the detached
    weights, and the selected particles' new log weights ``lw[idx] − stop_gradient(lw[idx])``
    (zeros in value; their gradient is the selected ancestors' log-weight gradient)."""
    lw = log_w - torch.logsumexp(log_w, 0)
    idx = resampler(lw.detach(), generator)
    sel = lw[idx]
    return idx, sel - sel.detach()


def unrolled_annealing(energy: Energy, proposal, context, num: int, layers: int = 3,
                       alpha: float = 0.5, rho: float = 0.2,
                       generator: torch.Generator | None = None
                       ) -> tuple[torch.Tensor, dict]:
    """``layers`` annealing layers (the :class:`~torchmocap.filters.AnnealedInference` loop,
    ESS-fraction β schedule, multinomial selection, mutation std ``sqrt(rho · var)`` of the
    selected particles in the proposal's coordinates) with a differentiable estimate.

    Args:
        energy: ``V(theta (P, D)) -> (P,)`` with learnable parameters.
        proposal: the tracker's proposal (draws without gradient).
        context: its :class:`~torchmocap.proposals.ProposalContext` (the start in
            ``previous``).
        num: particles ``P``.
    Returns:
        ``estimate (D,)`` — the weighted mean of the last layer, differentiable in the
        energy's parameters — and ``info`` (``beta``, ``ess`` per layer, final ``particles``
        and ``log_weights``).
    """
    info: dict = {"beta": [], "ess": []}
    with torch.no_grad():
        x = proposal.sample(context, num, generator).particles
    carried = torch.zeros(num, dtype=x.dtype, device=x.device)
    lw = carried
    for k in range(layers):
        if k > 0:
            idx, carried = stop_gradient_resample(lw, generator)
            with torch.no_grad():
                sel = x[idx]
                c = proposal.coordinates(sel).to(torch.float64)
                var = (c - c.mean(0, keepdim=True)).square().sum(0) / max(num - 1, 1)
                std = (rho * var + 1e-8).sqrt().to(x.dtype)
                ctx = dataclasses.replace(context, previous=sel, log_weights=None, std=std)
                x = proposal.sample(ctx, num, generator).particles
        v = energy(x)
        with torch.no_grad():
            beta = ess_target_beta(v.detach().to(torch.float64), alpha).beta
            beta = min(float(beta), 1e6) if math.isfinite(float(beta)) else 1.0
        lw = carried - beta * v
        info["beta"].append(beta)
        w = torch.softmax(lw.detach(), 0)
        info["ess"].append(float(1.0 / (w * w).sum()))
    w = torch.softmax(lw, 0)
    info["particles"], info["log_weights"] = x, torch.log_softmax(lw.detach(), 0)
    return (w[:, None] * x).sum(0), info
