"""Batched local optimisation of a differentiable energy (the L / LS baselines).

Minimises ``V(x (P, D)) -> (P,)`` from a start ``x0 (P, D)`` as ``P`` **independent** problems
(one per particle): each problem has its own L-BFGS history, step length and convergence test,
so one badly scaled problem never slows or stalls the others — unlike ``torch.optim.LBFGS`` on a
batch-summed loss, whose shared line search and history couple every problem (REFERENCE §10:
it stalls). Box constraints are handled by projection (projected L-BFGS: variables at a bound
whose gradient points outwards are frozen for the step, trial points are clamped into the box).
Adam (with clamping after each step) is offered for comparison.

The energy must be *row-independent*: ``V(x)[i]`` may depend only on ``x[i]`` (gradients are
taken of ``V(x).sum()``). Shapes: ``P`` problems/particles, ``D`` dims, ``I`` iterations.

Example:
    >>> V = lambda x: ((x - torch.tensor([1.0, -2.0])) ** 2).sum(-1)
    >>> res = minimise_local(V, torch.zeros(4, 2), iterations=20)
    >>> torch.allclose(res.x, torch.tensor([1.0, -2.0]).expand(4, 2), atol=1e-5)
    True
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchmocap.proposals.bounds import as_bound

__all__ = ["LocalResult", "minimise_local"]

Energy = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class LocalResult:
    """Output of :func:`minimise_local`.

    Attributes:
        x: best point found per problem ``(P, D)``.
        energy: its energy ``(P,)``.
        final: last iterate ``(P, D)``.
        trace: energy of every iterate ``(I + 1, P)`` (row 0 = start).
        converged: ``(P,)`` bool, projected-gradient norm below ``tol`` (L-BFGS) or
            ``|ΔV|`` below ``tol`` over the last step (Adam).
        iterations: iterations run (``I``).
    """

    x: torch.Tensor
    energy: torch.Tensor
    final: torch.Tensor
    trace: torch.Tensor
    converged: torch.Tensor
    iterations: int


def _value(energy: Energy, x: torch.Tensor, strict: bool) -> torch.Tensor:
    v = energy(x)
    p = x.shape[0]
    if not isinstance(v, torch.Tensor) or v.shape != (p,):
        shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
        raise ValueError(f"energy: expected a ({p},) tensor, got {shape}")
    if strict and not bool(torch.isfinite(v).all()):
        n = int((~torch.isfinite(v)).sum())
        raise ValueError(f"energy: non-finite (NaN or inf) for {n} of {p} problems")
    return v


def _value_and_grad(energy: Energy, x: torch.Tensor, strict: bool = True):
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        v = _value(energy, x, strict)
        if not v.requires_grad:
            raise ValueError("energy: output does not depend differentiably on x")
        (g,) = torch.autograd.grad(v.sum(), x)
    if strict and not bool(torch.isfinite(g).all()):
        raise ValueError("energy: non-finite gradient")
    return v.detach(), g.detach()


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _lbfgs(
    energy: Energy,
    x0: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    iterations: int,
    history: int,
    tol: float,
    max_backtracks: int = 30,
    c1: float = 1e-4,
) -> LocalResult:
    x = torch.maximum(torch.minimum(x0.detach(), hi), lo)
    p = x.shape[0]
    f, g = _value_and_grad(energy, x)
    S: list[torch.Tensor] = []
    Y: list[torch.Tensor] = []
    RHO: list[torch.Tensor] = []
    gamma = torch.ones(p, dtype=x.dtype, device=x.device)
    has_hist = torch.zeros(p, dtype=torch.bool, device=x.device)
    trace = [f.clone()]
    best_x, best_f = x.clone(), f.clone()
    converged = torch.zeros(p, dtype=torch.bool, device=x.device)

    def free_mask(x, g):
        return ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))

    for _ in range(iterations):
        free = free_mask(x, g)
        gf = g * free
        converged = gf.abs().amax(-1) <= tol
        if bool(converged.all()):
            trace.append(f.clone())
            continue
        # two-loop recursion, per problem (invalid pairs carry rho = 0)
        q = gf.clone()
        alphas = []
        for s, y, rho in zip(reversed(S), reversed(Y), reversed(RHO)):
            a = rho * _dot(s, q)
            q = q - a[:, None] * y
            alphas.append(a)
        r = gamma[:, None] * q
        for (s, y, rho), a in zip(zip(S, Y, RHO), reversed(alphas)):
            b = rho * _dot(y, r)
            r = r + s * (a - b)[:, None]
        d = -r * free
        slope = _dot(gf, d)
        bad = ~(slope < 0)
        d = torch.where(bad[:, None], -gf, d)
        # first step without curvature information: unit-length move
        gnorm = gf.norm(dim=-1).clamp(min=1e-300)
        t = torch.where(has_hist & ~bad, torch.ones_like(f), torch.clamp(1.0 / gnorm, max=1.0))
        # backtracking Armijo line search on the projected path, per problem (sufficient
        # decrease measured along the projected step, g·(x_t − x))
        active = ~converged
        accepted = torch.zeros_like(active)
        x_new, f_new = x.clone(), f.clone()
        for _ in range(max_backtracks):
            todo = active & ~accepted
            if not bool(todo.any()):
                break
            xt = torch.maximum(torch.minimum(x + t[:, None] * d, hi), lo)
            with torch.no_grad():
                ft = _value(energy, xt, strict=False)
            ok = todo & torch.isfinite(ft) & (ft <= f + c1 * _dot(g, xt - x))
            x_new = torch.where(ok[:, None], xt, x_new)
            f_new = torch.where(ok, ft, f_new)
            accepted = accepted | ok
            t = torch.where(todo & ~ok, 0.5 * t, t)
        if bool(accepted.any()):
            f_acc, g_new = _value_and_grad(energy, x_new, strict=False)
            good = accepted & torch.isfinite(f_acc) & torch.isfinite(g_new).all(-1)
            s = torch.where(good[:, None], x_new - x, torch.zeros_like(x))
            yv = torch.where(good[:, None], g_new - g, torch.zeros_like(g))
            sy = _dot(s, yv)
            pair_ok = good & (sy > 1e-10 * s.norm(dim=-1) * yv.norm(dim=-1)) & (sy > 0)
            rho = torch.where(pair_ok, 1.0 / torch.where(pair_ok, sy, torch.ones_like(sy)), 0.0)
            if bool(pair_ok.any()):
                S.append(s)
                Y.append(yv)
                RHO.append(rho)
                if len(S) > history:
                    S.pop(0)
                    Y.pop(0)
                    RHO.pop(0)
                yy = _dot(yv, yv)
                gamma = torch.where(pair_ok, sy / torch.where(pair_ok, yy, 1.0), gamma)
                has_hist = has_hist | pair_ok
            x = torch.where(good[:, None], x_new, x)
            f = torch.where(good, f_acc, f)
            g = torch.where(good[:, None], g_new, g)
        # problems whose line search failed: drop their curvature memory, restart steepest
        failed = active & ~accepted
        if bool(failed.any()):
            for rho in RHO:
                rho.masked_fill_(failed, 0.0)
            has_hist = has_hist & ~failed
            gamma = torch.where(failed, torch.ones_like(gamma), gamma)
        trace.append(f.clone())
        better = f < best_f
        best_x = torch.where(better[:, None], x, best_x)
        best_f = torch.where(better, f, best_f)
    free = free_mask(x, g)
    converged = (g * free).abs().amax(-1) <= tol
    return LocalResult(best_x, best_f, x, torch.stack(trace), converged, iterations)


def _adam(
    energy: Energy,
    x0: torch.Tensor,
    lo: torch.Tensor,
    hi: torch.Tensor,
    iterations: int,
    lr: float,
    tol: float,
) -> LocalResult:
    x = torch.maximum(torch.minimum(x0.detach(), hi), lo).clone().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=lr)
    # one evaluation per iterate: the value taken with the gradient at x_k is x_k's trace entry
    # (no separate no-grad evaluation after each step), the last iterate is evaluated once more
    trace: list[torch.Tensor] = []
    best_x = best_f = None
    for k in range(iterations + 1):
        if k == iterations:
            with torch.no_grad():
                v = _value(energy, x, strict=True)
        else:
            opt.zero_grad()
            with torch.enable_grad():
                v = _value(energy, x, strict=True)
                if not v.requires_grad:
                    raise ValueError("energy: output does not depend differentiably on x")
                v.sum().backward()
            if k == 0 and not bool(torch.isfinite(x.grad).all()):
                raise ValueError("energy: non-finite gradient")
        f = v.detach()
        trace.append(f)
        if best_f is None:
            best_x, best_f = x.detach().clone(), f.clone()
        else:
            better = f < best_f
            best_x = torch.where(better[:, None], x.detach(), best_x)
            best_f = torch.where(better, f, best_f)
        if k < iterations:
            opt.step()
            with torch.no_grad():
                x.copy_(torch.maximum(torch.minimum(x, hi), lo))
    prev = trace[-2] if iterations > 0 else trace[-1]
    converged = (trace[-1] - prev).abs() <= tol
    return LocalResult(best_x, best_f, x.detach(), torch.stack(trace), converged, iterations)


#: the optimisers of :func:`minimise_local` by name, each called as
#: ``(energy, x0, lo, hi, iterations, history, lr, tol)`` (a new one registers here)
OPTIMISERS: dict[str, Callable[..., LocalResult]] = {
    "lbfgs": lambda f, x0, lo, hi, it, history, lr, tol: _lbfgs(f, x0, lo, hi, it, history, tol),
    "adam": lambda f, x0, lo, hi, it, history, lr, tol: _adam(f, x0, lo, hi, it, lr, tol),
}


def check_method(method) -> None:
    """Raise ``ValueError`` unless ``method`` names one of :data:`OPTIMISERS`."""
    if method not in OPTIMISERS:
        raise ValueError(f"method: expected one of {sorted(OPTIMISERS)}, got {method!r}")


def minimise_local(
    energy: Energy,
    x0: torch.Tensor,
    *,
    method: str = "lbfgs",
    iterations: int = 100,
    lower: torch.Tensor | float | None = None,
    upper: torch.Tensor | float | None = None,
    history: int = 10,
    lr: float = 1e-2,
    tol: float = 1e-9,
    decode: Callable[[torch.Tensor], object] | None = None,
) -> LocalResult:
    """Minimise a differentiable, row-independent energy from ``x0`` per problem.

    Args:
        energy: ``V(y) -> (P,)`` with ``y = decode(x)`` (or ``x``); differentiable in ``x``.
        x0: start ``(P, D)``; projected onto the box first.
        method: ``"lbfgs"`` (per-problem projected L-BFGS with Armijo backtracking) or
            ``"adam"``.
        iterations: fixed number of iterations ``I`` (L-BFGS stops updating a problem whose
            projected gradient is below ``tol``).
        lower, upper: box, scalar or ``(D,)``, ±inf allowed.
        history: L-BFGS memory.
        lr: Adam learning rate (units of ``x``).
        tol: convergence tolerance (projected-gradient ∞-norm for L-BFGS, ``|ΔV|`` for Adam).
        decode: optional map from the optimised parameters to the energy's input.
    Returns:
        :class:`LocalResult` (best point, its energy, last iterate, trace ``(I + 1, P)``).
    """
    check_method(method)
    if not isinstance(x0, torch.Tensor) or not x0.is_floating_point():
        raise TypeError("x0: expected a floating-point torch.Tensor of shape (P, D)")
    if x0.dim() != 2 or x0.shape[0] < 1 or x0.shape[1] < 1:
        raise ValueError(f"x0: expected shape (P, D), got {tuple(x0.shape)}")
    if not bool(torch.isfinite(x0).all()):
        raise ValueError("x0: expected finite values, found NaN or inf")
    if not callable(energy):
        raise TypeError(f"energy: expected a callable, got {type(energy).__name__}")
    if not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations: expected an int >= 0, got {iterations!r}")
    if not isinstance(history, int) or history < 1:
        raise ValueError(f"history: expected an int >= 1, got {history!r}")
    if not (lr > 0 and math.isfinite(lr)):
        raise ValueError(f"lr: expected a positive number, got {lr}")
    lo = as_bound(lower, x0, "lower", -math.inf)
    hi = as_bound(upper, x0, "upper", math.inf)
    if bool((lo > hi).any()):
        raise ValueError("lower: must not exceed upper")
    fn = energy if decode is None else (lambda x: energy(decode(x)))
    return OPTIMISERS[method](fn, x0, lo, hi, iterations, history, lr, tol)
