"""Batched, box-constrained Levenberg–Marquardt of independent problems given their derivatives
(a mixture's local optimisation with Gauss–Newton Hessians): :func:`levenberg_marquardt`.
"""

from __future__ import annotations

import torch

__all__ = ["levenberg_marquardt"]


def levenberg_marquardt(derivs, x0: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                        iterations: int = 20, damping: float = 1e-3, gtol: float = 1e-7,
                        ftol: float = 1e-10, max_step: float | None = 0.25):
    """Batched, box-constrained Levenberg–Marquardt of ``P`` independent problems.

    ``derivs(x (B, D), rows (B,)) -> (V (B,), grad (B, D), H (B, D, D))`` (e.g. Gauss–Newton),
    ``rows`` the indices of the problems evaluated (so row-dependent terms stay aligned). Each
    problem solves ``(H + mu diag(H) + lambda I) step = -grad`` on its free variables (a
    variable at a bound whose gradient points outwards is held; a fixed ``1e-6 max(diag H)``
    Tikhonov term keeps steps along directions of zero curvature finite), shortens the step to
    at most ``max_step`` per coordinate (radians / metres: a weakly observed DoF of a robust
    energy otherwise jumps across its range in one Gauss–Newton step), clamps the trial point
    into the box and accepts it when the energy drops (``mu / 3``; else ``mu * 4``). Problems
    stop when the projected gradient is below ``gtol``, the relative decrease below ``ftol`` or
    the step vanishes; only the active ones are evaluated.

    Returns:
        ``x (P, D)``, ``V (P,)``, ``H (P, D, D)`` at the result, ``converged (P,)`` and the
        iterations run.
    """
    x = torch.maximum(torch.minimum(x0.detach(), upper), lower)
    P, D = x.shape
    dt, dev = x.dtype, x.device
    v, g, H = derivs(x, torch.arange(P, device=dev))
    mu = torch.full((P,), float(damping), dtype=dt, device=dev)
    active = torch.ones(P, dtype=torch.bool, device=dev)
    converged = torch.zeros(P, dtype=torch.bool, device=dev)
    xtol = 1e3 * torch.finfo(dt).eps
    its = 0
    for _ in range(iterations):
        free = ~(((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0)))
        pg = (g * free).abs().amax(-1)
        done = pg <= gtol
        converged = converged | (active & done)
        active = active & ~done
        if not bool(active.any()):
            break
        its += 1
        ia = active.nonzero()[:, 0]
        xa, ga, Ha, fa = x[ia], g[ia], H[ia], free[ia].to(dt)
        diag = Ha.diagonal(dim1=-2, dim2=-1)
        # Marquardt scaling plus a small fixed Tikhonov term: a DoF the energy does not see
        # (zero curvature, round-off gradient) takes no step instead of a huge one
        lam = 1e-6 * diag.amax(-1, keepdim=True).clamp_min(1e-12)
        A = Ha * fa[:, :, None] * fa[:, None, :] + torch.diag_embed(
            (mu[ia, None] * diag.clamp_min(0) + lam) * fa + (1 - fa))
        L, info = torch.linalg.cholesky_ex(A)
        rhs = -(ga * fa)[..., None]
        step = torch.cholesky_solve(rhs, L)[..., 0]
        bad = info != 0
        if bool(bad.any()):  # indefinite (a non-Gauss-Newton Hessian): gradient step
            step = torch.where(bad[:, None], -(ga * fa) / (diag.abs().amax(-1, keepdim=True)
                                                          .clamp_min(1.0) * mu[ia, None] + 1),
                               step)
        if max_step is not None:
            big = step.abs().amax(-1, keepdim=True)
            step = step * (max_step / big.clamp_min(max_step))
        cand = torch.maximum(torch.minimum(xa + step, upper), lower)
        vc, gc, Hc = derivs(cand, ia)
        ok = torch.isfinite(vc) & (vc < v[ia])
        rel = (v[ia] - vc) / v[ia].abs().clamp_min(1e-12)
        tiny = (cand - xa).abs().amax(-1) <= xtol * (1 + xa.abs().amax(-1))
        x[ia] = torch.where(ok[:, None], cand, xa)
        v[ia] = torch.where(ok, vc, v[ia])
        g[ia] = torch.where(ok[:, None], gc, ga)
        H[ia] = torch.where(ok[:, None, None], Hc, Ha)
        mu[ia] = torch.where(ok, (mu[ia] / 3).clamp_min(1e-12), (mu[ia] * 4).clamp_max(1e12))
        stop = (ok & (rel < ftol)) | tiny | (mu[ia] >= 1e10)
        converged[ia] = converged[ia] | (ok & (rel < ftol)) | tiny
        active[ia] = active[ia] & ~stop
    return x, v, H, converged, its
