"""Batched, box-constrained Levenberg–Marquardt of independent problems given their derivatives
(a mixture's local optimisation with Gauss–Newton Hessians): :func:`levenberg_marquardt`.
"""

from __future__ import annotations

import torch

from torchmocap.least_squares import DampedProblem, Marquardt, Verdict, damped_least_squares

__all__ = ["levenberg_marquardt"]


class _BoxNewton(DampedProblem):
    """:func:`levenberg_marquardt`'s problems: a damped Newton step on the free variables
    (Cholesky; a gradient step where the matrix is not positive definite), shortened to
    ``max_step``, clamped into the box; stationary when the projected gradient vanishes."""

    def __init__(self, derivs, x, lower, upper, gtol, ftol, max_step):
        self.derivs, self.lower, self.upper = derivs, lower, upper
        self.gtol, self.ftol, self.max_step = gtol, ftol, max_step
        P = x.shape[0]
        self.ids = torch.arange(P, device=x.device)
        self.x = x
        self.v, self.g, self.H = derivs(x, self.ids)
        self.out_x, self.out_v, self.out_H = x.clone(), self.v.clone(), self.H.clone()
        self.xtol = 1e3 * torch.finfo(x.dtype).eps

    def stationary(self):
        x, g = self.x, self.g
        self.free = ~(((x <= self.lower) & (g > 0)) | ((x >= self.upper) & (g < 0)))
        return (g * self.free).abs().amax(-1) <= self.gtol

    def propose(self, mu, rows):
        xa, ga, Ha, fa = self.x, self.g, self.H, self.free.to(self.x.dtype)
        diag = Ha.diagonal(dim1=-2, dim2=-1)
        # Marquardt scaling plus a small fixed Tikhonov term: a DoF the energy does not see
        # (zero curvature, round-off gradient) takes no step instead of a huge one
        lam = 1e-6 * diag.amax(-1, keepdim=True).clamp_min(1e-12)
        A = Ha * fa[:, :, None] * fa[:, None, :] + torch.diag_embed(
            (mu[:, None] * diag.clamp_min(0) + lam) * fa + (1 - fa))
        L, info = torch.linalg.cholesky_ex(A)
        rhs = -(ga * fa)[..., None]
        step = torch.cholesky_solve(rhs, L)[..., 0]
        bad = info != 0
        if bool(bad.any()):  # indefinite (a non-Gauss-Newton Hessian): gradient step
            step = torch.where(bad[:, None], -(ga * fa) / (diag.abs().amax(-1, keepdim=True)
                                                          .clamp_min(1.0) * mu[:, None] + 1),
                               step)
        if self.max_step is not None:
            big = step.abs().amax(-1, keepdim=True)
            step = step * (self.max_step / big.clamp_min(self.max_step))
        cand = torch.maximum(torch.minimum(xa + step, self.upper), self.lower)
        return cand, self.derivs(cand, self.ids)

    def assess(self, trial, mu, rows):
        cand, (vc, _, _) = trial
        xa, va = self.x, self.v
        ok = torch.isfinite(vc) & (vc < va)
        rel = (va - vc) / va.abs().clamp_min(1e-12)
        tiny = (cand - xa).abs().amax(-1) <= self.xtol * (1 + xa.abs().amax(-1))
        return Verdict(accepted=ok, converged=(ok & (rel < self.ftol)) | tiny)

    def commit(self, trial, accepted, rows):
        cand, (vc, gc, Hc) = trial
        self.x = torch.where(accepted[:, None], cand, self.x)
        self.v = torch.where(accepted, vc, self.v)
        self.g = torch.where(accepted[:, None], gc, self.g)
        self.H = torch.where(accepted[:, None, None], Hc, self.H)

    def retire(self, done, ids):
        sel = ids[done]
        self.out_x[sel], self.out_v[sel], self.out_H[sel] = (self.x[done], self.v[done],
                                                             self.H[done])

    def keep(self, mask):
        self.ids, self.x, self.v, self.g, self.H, self.free = (
            t[mask] for t in (self.ids, self.x, self.v, self.g, self.H, self.free))


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
    prob = _BoxNewton(derivs, x, lower, upper, gtol, ftol, max_step)
    run = damped_least_squares(prob, P, iterations,
                               Marquardt(initial=float(damping), minimum=1e-12, maximum=1e12,
                                         stall=1e10), device=x.device, dtype=x.dtype)
    return prob.out_x, prob.out_v, prob.out_H, run.converged, run.iterations
