"""Batched Levenberg-Marquardt fitting of skeleton poses to joint positions and bone orientations.

This is the projection of Hauberg & Pedersen (eqs. 6-7, "argmin ||x - F(theta)||^2 s.t. theta in
Theta") and the per-frame ground-truth fit of subject fitting. Every problem in the batch is solved
independently with its own damping, using the skeleton's analytic Jacobian (REFERENCE §10: an
autograd Jacobian costs 12-14x more per iteration). Box constraints are handled by projection
onto the joint limits after each step; unobservable directions (a shoulder twist with a straight
elbow, ...) are held by a small pull towards the prior mean. A problem leaves the batch once it has
converged, so each problem's result is the one it gets alone and a batch costs what its problems
need, not its slowest problem's iterations times the batch size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchmocap.geometry.rotations import so3_log
from torchmocap.least_squares import DampedProblem, Marquardt, Verdict, damped_least_squares
from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["LMResult", "fit_pose_lm"]


@dataclass
class LMResult:
    """Solution of :func:`fit_pose_lm`.

    Attributes:
        theta: ``(B, D)`` fitted poses.
        position_error: ``(B, M)`` distance of each targeted joint from its target (metres).
        rotation_error: ``(B, K)`` angle between each targeted frame and its target (radians), or
            ``None`` without rotation targets.
        cost: ``(B,)`` final weighted least-squares cost.
        iterations: number of iterations run (the largest over the batch).
    """

    theta: torch.Tensor
    position_error: torch.Tensor
    rotation_error: torch.Tensor | None
    cost: torch.Tensor
    iterations: int


def _residuals(sk, theta, tp, pj, pw, tr, rj, rw, prior, lw, with_jac):
    if with_jac:
        kin, Jp, Jr = sk.jacobian(theta)
    else:
        kin, Jp, Jr = sk(theta, check_finite=False), None, None
    B, D = theta.shape
    res, jac = [], []
    e_p = kin.positions[:, pj] - tp  # (B, M, 3)
    res.append((e_p * pw[:, None]).reshape(B, -1))
    if with_jac:
        jac.append((Jp[:, pj] * pw[:, None, None]).reshape(B, -1, D))
    e_r = None
    if tr is not None:
        e_r = so3_log(kin.rotations[:, rj] @ tr.transpose(-1, -2))  # world-frame error (B, K, 3)
        res.append((e_r * rw[:, None]).reshape(B, -1))
        if with_jac:
            jac.append((Jr[:, rj] * rw[:, None, None]).reshape(B, -1, D))
    res.append((theta - prior) * lw)
    if with_jac:
        jac.append(torch.diag_embed(lw.expand(B, D)))
    r = torch.cat(res, 1)
    J = torch.cat(jac, 1) if with_jac else None
    return r, J, e_p, e_r


def _subset(args, ids: torch.Tensor, B: int):
    """The per-problem arguments of :func:`_residuals` for the problems ``ids`` of ``B``."""
    if ids.numel() == B:
        return args
    tp, pj, pw, tr, rj, rw, prior, lw = args
    return (tp[ids], pj, pw, None if tr is None else tr[ids], rj, rw,
            prior[ids] if prior.dim() == 2 else prior, lw)


class _PoseProblem(DampedProblem):
    """The poses of :func:`fit_pose_lm` as damped least-squares problems: Marquardt's scaled
    damping of ``J^T J``, a step solved by LU, clamped into the joint limits."""

    relinearize_retiring = True  # the Jacobian's residuals give the reported costs

    def __init__(self, sk, theta, args, lo, hi, tol):
        self.sk, self.args, self.lo, self.hi, self.tol = sk, args, lo, hi, tol
        self.B, self.D = theta.shape
        self.theta = theta
        self.r, self.J, _, _ = _residuals(sk, theta, *args, with_jac=True)
        self.cost = (self.r * self.r).sum(1)
        self.eye = torch.eye(self.D, dtype=theta.dtype, device=theta.device)
        self.ids = torch.arange(self.B, device=theta.device)
        self.out, self.out_cost = theta.clone(), self.cost.clone()

    def propose(self, mu, rows):
        J, r = self.J, self.r
        JtJ = J.transpose(1, 2) @ J
        g = (J.transpose(1, 2) @ r[..., None])[..., 0]
        diag = JtJ.diagonal(dim1=1, dim2=2)
        A = JtJ + mu[:, None, None] * (torch.diag_embed(diag) + 1e-9 * self.eye)
        step = torch.linalg.solve(A, -g)
        return torch.maximum(torch.minimum(self.theta + step, self.hi), self.lo)

    def assess(self, trial, mu, rows):
        r_new, _, _, _ = _residuals(self.sk, trial, *_subset(self.args, self.ids, self.B),
                                    with_jac=False)
        cost_new = (r_new * r_new).sum(1)
        better = cost_new < self.cost
        rel = (self.cost - cost_new).clamp_min(0) / self.cost.clamp_min(1e-30)
        return Verdict(accepted=better, stop=(rel < self.tol) & better)

    def commit(self, trial, accepted, rows):
        self.theta = torch.where(accepted[:, None], trial, self.theta)

    def relinearize(self, accepted):
        if bool(accepted.any()):  # the accepted candidates' Jacobians (the rejected keep theirs)
            a = accepted.nonzero().squeeze(1)
            ra, Ja, _, _ = _residuals(self.sk, self.theta[a],
                                      *_subset(self.args, self.ids[a], self.B), with_jac=True)
            self.r = self.r.index_copy(0, a, ra)
            self.J = self.J.index_copy(0, a, Ja)
            self.cost = self.cost.index_copy(0, a, (ra * ra).sum(1))

    def retire(self, done, ids):
        self.out[ids[done]], self.out_cost[ids[done]] = self.theta[done], self.cost[done]

    def keep(self, mask):
        self.ids, self.theta, self.r, self.J, self.cost = (
            t[mask] for t in (self.ids, self.theta, self.r, self.J, self.cost))


def fit_pose_lm(
    skeleton: Skeleton,
    theta0: torch.Tensor,
    target_positions: torch.Tensor,
    position_joints: list[int] | list[str],
    target_rotations: torch.Tensor | None = None,
    rotation_joints: list[int] | list[str] | None = None,
    position_weights: torch.Tensor | None = None,
    rotation_weight: float = 0.1,
    prior_weight: float = 1e-3,
    prior: torch.Tensor | None = None,
    iterations: int = 30,
    damping: float = 1e-3,
    tol: float = 1e-7,
) -> LMResult:
    """Fit ``theta`` so joints hit target positions (and frames target orientations).

    Args:
        skeleton: the model.
        theta0: ``(B, D)`` start (warm start, e.g. the previous frame).
        target_positions: ``(B, M, 3)`` metres.
        position_joints: ``M`` joint indices or names the targets belong to.
        target_rotations: optional ``(B, K, 3, 3)`` global frame targets.
        rotation_joints: ``K`` joint indices or names for ``target_rotations``.
        position_weights: optional ``(M,)`` per-joint weights (1 by default).
        rotation_weight: weight (metres per radian) of the orientation residuals.
        prior_weight: pull towards ``prior`` (default ``theta0``) per DoF, in residual units.
        iterations: maximum LM iterations.
        damping: initial Marquardt damping (scaled per problem).
        tol: a problem stops (and leaves the batch) once an accepted step lowers its cost by
            less than this fraction.
    Returns:
        :class:`LMResult`.
    """
    if theta0.dim() != 2 or theta0.shape[1] != skeleton.num_dofs:
        raise ValueError(f"theta0: expected shape (B, {skeleton.num_dofs}), got "
                         f"{tuple(theta0.shape)}")
    B, D = theta0.shape
    pj = [skeleton.joint_index(j) if isinstance(j, str) else int(j) for j in position_joints]
    M = len(pj)
    if target_positions.shape != (B, M, 3):
        raise ValueError(f"target_positions: expected shape ({B}, {M}, 3), got "
                         f"{tuple(target_positions.shape)}")
    if not bool(torch.isfinite(target_positions).all()):
        raise ValueError("target_positions: expected finite values, found NaN or inf")
    rj = []
    if target_rotations is not None:
        rj = [skeleton.joint_index(j) if isinstance(j, str) else int(j)
              for j in (rotation_joints or [])]
        if target_rotations.shape != (B, len(rj), 3, 3):
            raise ValueError(f"target_rotations: expected shape ({B}, {len(rj)}, 3, 3), got "
                             f"{tuple(target_rotations.shape)}")
    dtype, device = theta0.dtype, theta0.device
    pw = (torch.ones(M, dtype=dtype, device=device) if position_weights is None
          else position_weights.to(dtype=dtype, device=device))
    rw = torch.full((len(rj),), float(rotation_weight), dtype=dtype, device=device)
    lw = torch.full((D,), float(prior_weight), dtype=dtype, device=device)
    prior = theta0.detach() if prior is None else prior.to(dtype)
    lo = skeleton.lower.to(dtype=dtype, device=device)
    hi = skeleton.upper.to(dtype=dtype, device=device)
    theta = torch.maximum(torch.minimum(theta0.detach().clone(), hi), lo)
    tr = target_rotations.to(dtype) if target_rotations is not None else None
    args = (target_positions.to(dtype), pj, pw, tr, rj, rw, prior, lw)
    # a problem leaves the batch once it has converged (an accepted step lowered its cost by
    # less than ``tol`` relative) or stalled (damping at its cap)
    prob = _PoseProblem(skeleton, theta, args, lo, hi, float(tol))
    run = damped_least_squares(prob, B, iterations, Marquardt(initial=float(damping)),
                               device=device, dtype=dtype)
    it = run.iterations
    theta, cost = prob.out, prob.out_cost
    _, _, e_p, e_r = _residuals(skeleton, theta, *args, with_jac=False)
    return LMResult(
        theta=theta,
        position_error=e_p.norm(dim=-1),
        rotation_error=None if e_r is None else e_r.norm(dim=-1),
        cost=cost,
        iterations=it,
    )
