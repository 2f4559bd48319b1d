"""Projection of joint positions onto the skeleton manifold (Hauberg & Pedersen 2011, eqs. 6-7).

The projected spatial prior samples joint positions ``x_hat ~ N(F(theta_prev), Sigma)`` in
``R^{3J}`` and maps every sample back to a pose::

    theta_hat = argmin_theta  sum_j w_j |x_hat_j - F_j(theta)|^2 + lambda^2 |theta - theta_0|^2
                subject to    lower <= theta <= upper                                  (eq. 7)

started at (and gently pulled towards) the warm start ``theta_0``, the previous pose. The pull
``lambda`` (``prior_weight``, metres per radian) is tiny; it only decides the directions the
positions do not observe — the neck twist when the head joints lie on its axis, a shoulder twist
with a straight elbow — which would otherwise drift (REFERENCE §10).

Method: batched projected Levenberg-Marquardt, each problem with its own damping (Nielsen's
update; the damping of weakly observed DoFs is floored at a fraction of the mean diagonal, since
Marquardt's diagonal scaling alone leaves them undamped). The model is the Gauss-Newton matrix
until a problem's accepted step moves no joint by more than 1 cm, then the exact Hessian, with the
Gauss-Newton matrix taking over at once wherever the damped Hessian is not positive definite
(Gauss-Newton alone converges only linearly on these large-residual problems; the exact Hessian
from the start lands in worse local minima more often). Box constraints by an active set: the
variables at a bound whose gradient points outward are frozen; where the step still leaves the
box, the crossing variables are fixed on their bound and the others re-solved (the exact
minimiser of the model on that face), else the step is truncated to the box. The gain ratio uses
the model decrease of the step actually taken and the cost change is formed from residual
differences (no cancellation), so accepted steps never increase the cost. A problem has converged,
and stops being updated, once a step moves none of its targeted joints by more than ``tol``
metres (with the damping not dominating the step).

Implementation (speed; ``experiments/benchmarks/spatial_projection.py``): kinematics in a
particles-innermost layout ``(joints, 3, 3, n)`` (3x3 products as broadcast multiply-adds, ~3x
faster than batched ``matmul`` of 3x3 matrices); each joint's local rotation and slot axes as one
product with a precomputed ``(18, 27)`` basis (Rodrigues is linear in ``1, sin, 1 - cos`` per
axis); joints without DoF folded into their descendants' offsets; all positions from one matrix
product. The normal equations are assembled without forming the ``(3M, D)`` Jacobian: every
entry is a function of weighted subtree moments (``sum w_i F_i``, ``sum w_i F_i F_i^T``, ...,
one ``(Dr, M) @ (M, 24 n)`` product) and the world axes, packed into one batched ``(D, 6) x
(6, D)`` product; only its lower triangle is kept, which is all Cholesky reads. A rejected
candidate keeps the equations of the current pose; the equations at an accepted candidate come
from the kinematics already evaluated for it. Frozen variables get a large diagonal instead of
zeroed rows. Finished problems leave the working set (it stays one vectorised batch) once enough
of them have finished.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from torchmocap.least_squares import (
    DampedProblem,
    Nielsen,
    Verdict,
    compact_when_worthwhile,
    damped_least_squares,
)
from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["ProjectionResult", "SkeletonProjection", "project_to_skeleton"]

_MU_MAX = 1e12  # damping at which a problem counts as stalled (no descent left)
_DIAG_FLOOR = 1e-9  # damping floor for DoFs the targets and prior do not observe at all
_FLOOR_REL = 0.1  # damping of weakly observed DoFs: at least this fraction of the mean diagonal
_MIN_SHRINK = 1.0 / 3.0  # Nielsen's damping update: at most this decrease per iteration
_FREEZE = 1e8  # diagonal factor of frozen variables
_NEWTON_RADIUS = 0.01  # exact Hessian once an accepted step moved no joint more than this (m)


@dataclass
class ProjectionResult:
    """Solution of :func:`project_to_skeleton`.

    Attributes:
        theta: ``(P, D)`` projected poses, inside the joint limits.
        residual: ``(P, M)`` distance of each targeted joint from its target (metres, unweighted).
        cost: ``(P,)`` final objective ``sum_j w_j |x_j - F_j|^2 + lambda^2 |theta - theta_0|^2``
            (square metres).
        converged: ``(P,)`` the problem met ``tol`` within the iteration cap (a problem whose
            damping blew up without finding a descent step stops too, unflagged).
        iterations: number of iterations run (the largest over the batch).
        cost_trace: ``(iterations + 1, P)`` the cost after each iteration (row 0: the start; a
            problem that stopped keeps its value), only with ``return_trace=True``.
    """

    theta: torch.Tensor
    residual: torch.Tensor
    cost: torch.Tensor
    converged: torch.Tensor
    iterations: int
    cost_trace: torch.Tensor | None = None


# ----------------------------------------------------------------------------- kinematic plan
class _Plan:
    """Index tensors and constant algebra of one skeleton, for one device and dtype.

    Articulated joints (the root and every joint with revolute axes) are ordered by depth, so
    each composition level is a contiguous slice; every articulated joint has 3 axis *slots*
    (missing axes padded with a zero axis, whose Rodrigues rotation is the identity).
    """

    def __init__(self, sk: Skeleton, dtype: torch.dtype, device: torch.device):
        J, D = sk.num_joints, sk.num_dofs
        parents, axes = sk.parents, sk.joint_axes
        art = [0] + [j for j in range(1, J) if axes[j]]
        art_set = set(art)

        def anc_of(j: int) -> int:  # nearest articulated strict ancestor
            q = parents[j]
            while q not in art_set:
                q = parents[q]
            return q

        def is_below(i: int, j: int) -> bool:  # joint i is a strict descendant of joint j
            q = parents[i]
            while q >= 0 and q != j:
                q = parents[q]
            return q == j

        anc = {j: anc_of(j) for j in range(1, J)}
        depth = {0: 0}
        for j in art[1:]:  # parents come first in the skeleton's topological order
            depth[j] = depth[anc[j]] + 1
        order = sorted(art, key=lambda j: (depth[j], j))
        pos = {j: k for k, j in enumerate(order)}
        Ja = len(order)
        self.num_art = Ja
        self.levels = []
        for d in range(1, max(depth.values()) + 1):
            js = [j for j in order if depth[j] == d]
            self.levels.append((pos[js[0]], pos[js[0]] + len(js),
                                torch.tensor([pos[anc[j]] + 1 for j in js], device=device)))

        # frame each joint's (folded) offset is expressed in: slot 0 of the rotation buffer is
        # the world (identity), slot k + 1 the global frame of articulated joint order[k]
        frame = [0] + [pos[anc[j]] + 1 for j in range(1, J)]
        self.frame_all = torch.tensor(frame, device=device)
        self.frame_art = torch.tensor([frame[j] for j in order], device=device)
        fold = torch.zeros(J, J, dtype=torch.float64)  # folded offset = fold @ offsets
        chain = torch.zeros(J, J, dtype=torch.float64)  # position = chain @ (folded, rotated)
        for j in range(J):
            fold[j, j] = 1.0
            if j:
                q = parents[j]
                while q != anc[j]:
                    fold[j, q] = 1.0
                    q = parents[q]
            k = j
            while True:
                chain[j, k] = 1.0
                if k == 0:
                    break
                k = anc[k]
        self.fold = fold.to(dtype=dtype, device=device)
        self.chain = chain.to(dtype=dtype, device=device)
        self.art_joints = torch.tensor(order, device=device)

        trans, rot = sk.translation_dofs, sk.rotation_dofs
        if trans and trans != [0, 1, 2]:  # pragma: no cover - the Skeleton puts them first
            raise RuntimeError(f"root translation DoFs expected at [0, 1, 2], got {trans}")
        if rot != list(range(len(trans), D)):  # pragma: no cover
            raise RuntimeError("rotation DoFs expected after the translations")
        nt = self.num_trans = len(trans)
        slot_dof = torch.zeros(Ja, 3, dtype=torch.long)
        slot_axis = torch.zeros(Ja, 3, 3, dtype=torch.float64)
        dof_slot = {}
        for k, j in enumerate(order):
            dofs = [d for d in sk.joint_dofs(sk.joint_names[j]) if d not in trans]
            for s, (d, a) in enumerate(zip(dofs, axes[j])):
                slot_dof[k, s] = d
                slot_axis[k, s] = torch.tensor(a, dtype=torch.float64)
                dof_slot[d] = 3 * k + s
        self.slot_dof = slot_dof.reshape(-1).to(device)
        x, y, z = slot_axis.unbind(-1)
        o = torch.zeros_like(x)
        K = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(Ja, 3, 3, 3)
        # Rodrigues per slot: R_s = sum_i f_i K_s^(i) with (f_0, f_1, f_2) = (1, sin, 1 - cos)
        # and K^(0) = I, K^(1) = K, K^(2) = K^2. The local rotation L = R_0 R_1 R_2 and the
        # slot axes in the joint's parent frame u_0 = a_0, u_1 = R_0 a_1, u_2 = R_0 R_1 a_2 are
        # then linear in the 27 products f_i(t_0) f_j(t_1) f_k(t_2): one (18, 27) matrix each.
        eye = torch.eye(3, dtype=torch.float64).expand(Ja, 3, 3, 3)
        powers = torch.stack([eye, K, K @ K], 2)  # (Ja, slot, power, 3, 3)
        basis = torch.zeros(Ja, 18, 3, 3, 3, dtype=torch.float64)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    Lb = powers[:, 0, i] @ powers[:, 1, j] @ powers[:, 2, k]
                    basis[:, :9, i, j, k] = Lb.reshape(Ja, 9)
            basis[:, 12:15, i, 0, 0] = (powers[:, 0, i] @ slot_axis[:, 1, :, None])[..., 0]
            for j in range(3):
                basis[:, 15:18, i, j, 0] = (powers[:, 0, i] @ powers[:, 1, j]
                                            @ slot_axis[:, 2, :, None])[..., 0]
        basis[:, 9:12, 0, 0, 0] = slot_axis[:, 0]
        self.local_basis = basis.reshape(Ja, 18, 27).to(dtype=dtype, device=device)
        self.rot_slot = torch.tensor([dof_slot[d] for d in rot], dtype=torch.long, device=device)
        self.rot_art = torch.tensor([dof_slot[d] // 3 for d in rot], dtype=torch.long,
                                    device=device)
        self.frame_wv = torch.cat([self.frame_art[self.rot_art], self.frame_all])
        # desc[d, i]: rotation DoF d moves joint i (a strict descendant of its joint)
        desc = torch.tensor([[float(is_below(i, order[dof_slot[d] // 3])) for i in range(J)]
                             for d in rot], dtype=torch.float64).reshape(len(rot), J)
        self.desc = desc.to(dtype=dtype, device=device)
        # before[d, e]: DoF d lies above e on e's chain (an ancestor joint's axis, an earlier
        # axis of the same joint; translations above every rotation and ordered among
        # themselves). The products of ``derivatives`` are valid for d above e and d = e.
        before = torch.zeros(D, D, dtype=torch.float64)
        before[:nt, nt:] = 1.0
        before[:nt, :nt] = torch.ones(nt, nt, dtype=torch.float64).triu(1)
        for ia, a in enumerate(rot):
            ja, sa = order[dof_slot[a] // 3], dof_slot[a] % 3
            for ib, b in enumerate(rot):
                jb, sb = order[dof_slot[b] // 3], dof_slot[b] % 3
                before[nt + ia, nt + ib] = float(sa < sb) if ja == jb else float(is_below(jb, ja))
        self.after = (before.t() + torch.eye(D, dtype=torch.float64)).to(dtype=dtype,
                                                                          device=device)
        self.eye = torch.eye(3, dtype=dtype, device=device)[..., None]
        anti = torch.zeros(3, 9, dtype=dtype, device=device)  # P -> (P_yz - P_zy, ...)
        for r, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
            anti[r, 3 * i + j], anti[r, 3 * j + i] = 1.0, -1.0
        self.antisym = anti
        self.left_t = torch.zeros(3, 6, 1, dtype=dtype, device=device)
        for c in range(3):
            self.left_t[c, 3 + c] = 1.0
        self.roll1 = torch.tensor([1, 2, 0], device=device)
        self.roll2 = torch.tensor([2, 0, 1], device=device)


_PLANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _plan(sk: Skeleton, dtype: torch.dtype, device: torch.device) -> _Plan:
    """The cached plan of ``sk`` (structure only: offsets and limits are read at every call)."""
    per = _PLANS.setdefault(sk, {})
    key = (dtype, str(device))
    if key not in per:
        per[key] = _Plan(sk, dtype, device)
    return per[key]


def _mm(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``(k, 3, 3, n) @ (k, 3, 3, n)`` per problem, problems innermost."""
    return (A[:, :, :, None, :] * B[:, None, :, :, :]).sum(2)


class _Problem:
    """Constants of one batched projection (targets, weights, limits, index maps).

    Layout: joint positions, residuals and world axes are ``(k, 3, n)`` with the ``n`` problems
    innermost; poses, gradients and Hessians are ``(n, D)`` / ``(n, D, D)`` over the ``D`` free
    DoFs (all of the skeleton's by default; the others stay at the warm start and never enter
    the linear algebra).
    """

    def __init__(self, sk, plan, targets, theta0, joints, joint_weights, prior_weight,
                 free=None):
        dtype, device = targets.dtype, targets.device
        P, M, _ = targets.shape
        self.plan, self.P, self.M = plan, P, M
        nt_all, D_all = plan.num_trans, sk.num_dofs
        lo = sk.lower.to(dtype=dtype, device=device)
        hi = sk.upper.to(dtype=dtype, device=device)
        self.theta0_full = torch.minimum(torch.maximum(theta0.expand(P, D_all), lo), hi)
        fr = list(range(D_all)) if free is None else sorted(int(d) for d in free)
        self.reduced = len(fr) < D_all
        self.free = torch.tensor(fr, dtype=torch.long, device=device)
        ft = [d for d in fr if d < nt_all]  # free translations
        fr_rot = torch.tensor([d - nt_all for d in fr if d >= nt_all], dtype=torch.long,
                              device=device)  # free rotations, as rows of the plan's rot list
        self.D, self.nt, self.Dr = len(fr), len(ft), fr_rot.numel()
        self.lo, self.hi = lo[self.free], hi[self.free]
        self.theta0 = self.theta0_full[:, self.free]
        self.after = plan.after[self.free][:, self.free]
        self.rot_slot = plan.rot_slot[fr_rot]
        self.frame_wv = torch.cat([plan.frame_art[plan.rot_art[fr_rot]], plan.frame_all])
        self.lam2 = float(prior_weight) ** 2
        sel = torch.tensor(joints, dtype=torch.long, device=device)
        self.w = joint_weights  # (M,) weights of the squared distances
        # positions of the targeted joints, then of the articulated joints (DoF origins)
        self.chain_out = torch.cat([plan.chain[sel], plan.chain[plan.art_joints]], 0)
        self.off3 = (plan.fold @ sk.offsets.to(dtype=dtype, device=device))[:, :, None]
        self.x = targets.permute(1, 2, 0).contiguous()  # (M, 3, P)
        # rows of the position block holding each free rotation DoF's origin
        self.origin = M + plan.rot_art[fr_rot]
        mask = plan.desc[fr_rot][:, sel] * joint_weights  # (Dr, M): weighted descendant mask
        self.moment_mask = torch.cat([joint_weights[None], mask], 0)  # row 0: all joints
        self.mass = mask.sum(1)[:, None, None]  # (Dr, 1, 1)
        # translations enter the (D, 6) x (6, D) product as rows left = (0, e_c),
        # right = (0, m e_c) with m = sum w_i: H_tt = m I, H_te = k_e
        self.trans = torch.tensor(ft, dtype=torch.long, device=device)
        self.left_t = plan.left_t[self.trans]
        self.right_t = self.left_t * joint_weights.sum()

    def full(self, theta: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
        """The skeleton's pose ``(n, D_all)``: ``base`` with the free DoFs set to ``theta``."""
        return base.index_copy(1, self.free, theta) if self.reduced else theta

    # -- kinematics -----------------------------------------------------------------------
    def kinematics(self, theta: torch.Tensor):
        """Positions ``(M + Ja, 3, n)`` (targets first) and world axes ``(Dr, 3, n)``."""
        pl = self.plan
        thT = theta.t()
        n = thT.shape[1]
        ang = thT.index_select(0, pl.slot_dof)  # (Ja * 3, n)
        f = torch.stack([torch.ones_like(ang), torch.sin(ang), 1 - torch.cos(ang)], 1)
        f = f.view(pl.num_art, 3, 3, n)
        f27 = (f[:, 0, :, None, None] * f[:, 1, None, :, None] * f[:, 2, None, None, :])
        loc = torch.bmm(pl.local_basis, f27.view(pl.num_art, 27, n))  # (Ja, 18, n)
        L = loc[:, :9].view(pl.num_art, 3, 3, n)
        Rg = torch.empty(pl.num_art + 1, 3, 3, n, dtype=theta.dtype, device=theta.device)
        Rg[0] = pl.eye
        Rg[1] = L[0]
        for s0, s1, par in pl.levels:
            Rg[s0 + 1:s1 + 1] = _mm(Rg.index_select(0, par), L[s0:s1])
        # world axes of the DoFs, w = R_parent u, and rotated folded offsets, v = R_frame off,
        # as one product: (Dr + J) rotations times (Dr + J) vectors
        vec = torch.cat([loc[:, 9:].reshape(pl.num_art * 3, 3, n).index_select(0, self.rot_slot),
                         self.off3.expand(-1, -1, n)], 0)
        wv = (Rg.index_select(0, self.frame_wv) * vec[:, None]).sum(2)  # (Dr + J, 3, n)
        w, v = wv[: self.Dr], wv[self.Dr:]
        if pl.num_trans:
            v[0] += thT[:3]
        p = (self.chain_out @ v.reshape(v.shape[0], -1)).view(-1, 3, n)
        return p, w

    def cost(self, res: torch.Tensor, dtheta: torch.Tensor) -> torch.Tensor:
        """``sum_j w_j |res_j|^2 + lambda^2 |dtheta|^2`` ``(n,)`` from ``res (M, 3, n)``."""
        c = self.w @ (res * res).sum(1)
        if self.lam2:
            c = c + self.lam2 * (dtheta * dtheta).sum(1)
        return c

    # -- derivatives ----------------------------------------------------------------------
    def derivatives(self, p: torch.Tensor, w: torch.Tensor, x: torch.Tensor,
                    dtheta: torch.Tensor, newton: torch.Tensor | None = None):
        """Model matrix ``H (n, D, D)`` — the Gauss-Newton matrix, or the exact Hessian for the
        problems where ``newton (n,)`` is set — (lower triangle and diagonal only; the strict
        upper triangle is zero), the gradient ``g (n, D)`` of half the cost, the damping scale
        ``(n, D)`` (the Gauss-Newton diagonal, floored) and, if any problem is flagged, the
        Gauss-Newton matrices too (else ``None``), from subtree moments without forming the
        Jacobian.

        A revolute DoF ``e`` (world axis ``w_e`` through ``o_e``) moves each joint ``i`` below
        it by ``dF_i/dtheta_e = w_e x (F_i - o_e)``; ``d^2 F_i / dtheta_d dtheta_e = w_d x (w_e x
        (F_i - o_e))`` for ``d`` above ``e``. With the weighted subtree sums ``m_e = sum w_i``,
        ``c_e = sum w_i F_i``, ``c'_e = sum w_i x_i``, ``P_e = sum w_i F_i F_i^T`` and
        ``P'_e = sum w_i F_i x_i^T``, for ``d`` above ``e`` on one chain (or ``d = e``)::

            H_de  = w_d . A(P_e, c_e) - (w_d x o_d) . k_e,   k_e = w_e x (c_e - m_e o_e)
            HN_de = w_d . A(P'_e, c'_e) - (w_d x o_d) . k_e
            A(P, c) = (tr P - o_e . c) w_e - P w_e + o_e (c . w_e)
            g_e   = -w_e . vec(P'_e - P'_e^T) - (c_e - c'_e) . (w_e x o_e)

        and root translations give ``H_tt = (sum w_i) I``, ``H_te = k_e``,
        ``g_t = sum w_i (F_i - x_i)``. All sums come from one ``(Dr + 1, M) @ (M, 24 n)``
        product, the matrix from one batched ``(D, 6) x (6, D)`` product.
        """
        pl, M, Dr, nt, D = self.plan, self.M, self.Dr, self.nt, self.D
        n = p.shape[-1]
        dt = p.dtype
        pt = p[:M]
        o = p.index_select(0, self.origin)  # (Dr, 3, n)
        F = torch.empty(M, 24, n, dtype=dt, device=p.device)
        F[:, 0:3] = pt
        F[:, 3:6] = x
        torch.mul(pt[:, :, None], pt[:, None], out=F[:, 6:15].view(M, 3, 3, n))
        torch.mul(pt[:, :, None], x[:, None], out=F[:, 15:24].view(M, 3, 3, n))
        mom = (self.moment_mask @ F.view(M, -1)).view(Dr + 1, 24, n)
        mo = mom[1:]
        C2 = mo[:, 0:6].view(Dr, 2, 3, n)  # (c, c')
        P2 = mo[:, 6:24].view(Dr, 2, 3, 3, n)  # (P, P')
        # w x o and w x c in one cross product (index form: ~2x torch.linalg.cross here)
        oc = torch.stack([o, mo[:, 0:3]], 1)
        w1 = w[:, None]  # (Dr, 1, 3, n)
        wx = (w1.index_select(2, pl.roll1) * oc.index_select(2, pl.roll2)
              - w1.index_select(2, pl.roll2) * oc.index_select(2, pl.roll1))
        z = wx[:, 0]
        k = torch.addcmul(wx[:, 1], self.mass, z, value=-1.0)
        # A(P, c) = (tr P - o . c) w - P w + o (c . w), for (P, c) and (P', c') at once
        Pw = P2[:, :, :, 0] * w1[:, :, 0:1]
        Pw.addcmul_(P2[:, :, :, 1], w1[:, :, 1:2]).addcmul_(P2[:, :, :, 2], w1[:, :, 2:3])
        s = P2[:, :, 0, 0] + P2[:, :, 1, 1] + P2[:, :, 2, 2] - (o[:, None] * C2).sum(2)
        A2 = torch.addcmul(o[:, None] * (C2 * w1).sum(2, keepdim=True), s[:, :, None], w1)
        A2.sub_(Pw)  # (Dr, 2, 3, n)
        ge = (w * (pl.antisym @ P2[:, 1].reshape(Dr, 9, n))
              + (C2[:, 0] - C2[:, 1]) * z).sum(1).neg_()  # (Dr, n)
        # the Gauss-Newton diagonal (positive) scales the damping
        dgn = torch.empty(D, n, dtype=dt, device=p.device)
        if nt:
            dgn[:nt] = self.w.sum()
        dgn[nt:] = (w * A2[:, 0] - z * k).sum(1)
        # SoA operands (rows: translations, then rotations) and one transposing copy each
        # (contiguous operands: strided ones make bmm loop over the batch); the right operand
        # holds the Gauss-Newton rows, then (if asked for) the exact-Hessian rows
        # the model matrix (the exact Hessian for the rows flagged ``newton``) and, if any is
        # flagged, the Gauss-Newton matrix too (the fallback where the Hessian is not positive)
        with_gn = newton is not None and bool(newton.any())
        nv = 2 if with_gn else 1
        lb = torch.empty(D, 6, n, dtype=dt, device=p.device)
        rb = torch.empty(nv, D, 6, n, dtype=dt, device=p.device)
        if nt:
            lb[:nt] = self.left_t
            rb[:, :nt] = self.right_t
        lb[nt:, :3] = w
        torch.neg(z, out=lb[nt:, 3:])
        if with_gn:
            torch.where(newton, A2[:, 1], A2[:, 0], out=rb[0, nt:, :3])
            rb[1, nt:, :3] = A2[:, 0]
        else:
            rb[0, nt:, :3] = A2[:, 0]
        rb[:, nt:, 3:] = k
        # U[d, e] = left_d . right_e is the matrix entry for d above e on e's chain, so the
        # lower triangle (d below e) is U^T = right @ left^T, masked
        U = torch.bmm(rb.view(nv * D, 6, n).permute(2, 0, 1).contiguous(),
                      lb.permute(2, 1, 0).contiguous())  # (n, nv D, D)
        H = U[:, :D] * self.after
        HG = U[:, D:] * self.after if with_gn else None
        g = torch.empty(D, n, dtype=dt, device=p.device)
        if nt:
            g[:nt] = (mom[0, 0:3] - mom[0, 3:6]).index_select(0, self.trans)
        g[nt:] = ge
        g = g.t()
        dgn = dgn.t()
        if self.lam2:
            H.diagonal(dim1=1, dim2=2).add_(self.lam2)
            if HG is not None:
                HG.diagonal(dim1=1, dim2=2).add_(self.lam2)
            g = g + self.lam2 * dtheta
            dgn = dgn + self.lam2
        # damping scale: the Gauss-Newton diagonal, floored at a fraction of its mean (weakly
        # observed DoFs: Marquardt's scaling alone would barely damp them)
        floor = (_FLOOR_REL * dgn.mean(1, keepdim=True)).clamp_min_(_DIAG_FLOOR)
        return H, g.contiguous(), torch.maximum(dgn, floor), HG


# ----------------------------------------------------------------------------- linear algebra
def _solve_damped(Hl: torch.Tensor, damp: torch.Tensor, free: torch.Tensor | None,
                  rhs: torch.Tensor):
    """Solve ``(H + diag(damp)) s = rhs`` over the free variables (``s = 0`` on the frozen
    ones) by Cholesky, for ``H`` given as its lower triangle ``Hl (n, D, D)`` (only the lower
    triangle is read, as LAPACK's ``potrf`` does). Returns ``(s (n, D), ok (n,))``; ``ok`` is
    ``False`` where the damped matrix is not positive definite.

    Frozen variables get their diagonal multiplied by ``_FREEZE`` instead of zeroed rows and
    columns (one operation; it decouples them to ``~1 / _FREEZE``, and their step is zeroed).
    """
    # the damped diagonal goes into Hl for the factorization (which copies the lower triangle
    # anyway) and the original is put back: no copy of the (n, D, D) matrices
    diag = Hl.diagonal(dim1=1, dim2=2)
    d0 = diag.clone()
    dg = d0 + damp
    if free is None:
        diag.copy_(dg)
    else:
        diag.copy_(torch.where(free, dg, dg * _FREEZE))
        rhs = rhs * free
    L, info = torch.linalg.cholesky_ex(Hl)
    diag.copy_(d0)
    y = torch.linalg.solve_triangular(L, rhs[..., None], upper=False)
    step = torch.linalg.solve_triangular(L.transpose(1, 2), y, upper=True)[..., 0]
    if free is not None:
        step = step * free
    ok = info == 0
    return torch.where(ok[:, None], step, 0.0), ok


def _box_step(H, g, th, lo, hi, damp):
    """Minimiser of the damped quadratic model over the box, by at most two active-set passes.

    Pass 1 freezes the binding variables (at a bound, gradient pointing outward) and solves for
    the others. For the rows where some step then leaves the box, pass 2 fixes those variables
    on the bound they cross and re-solves for the rest (the exact minimiser on that face of the
    box); where that fails or does not decrease the model, the pass-1 step truncated to the box
    (a descent step of the model) is taken instead. Returns the candidate ``theta + step``
    ``(n, D)`` (inside the box) and a success flag ``(n,)`` (``False`` where the damped
    matrix is not positive definite; the step is then 0).
    """
    bind = ((th <= lo) & (g > 0)) | ((th >= hi) & (g < 0))
    free = ~bind if bool(bind.any()) else None
    step, ok = _solve_damped(H, damp, free, -g)
    new = th + step
    below, above = new < lo, new > hi
    rows = (below | above).any(1)
    if not bool(rows.any()):
        return new, ok
    sub = rows.nonzero().squeeze(1)
    ts, s1, gs, ds = torch.stack([th, step, g, damp]).index_select(1, sub).unbind(0)
    Hs = H.index_select(0, sub)
    bs, as_ = below.index_select(0, sub), above.index_select(0, sub)
    cs = bs | as_
    dfix = torch.where(bs, lo - ts, torch.where(as_, hi - ts, 0.0))
    free2 = ~cs if free is None else free.index_select(0, sub) & ~cs
    A = Hs + Hs.transpose(1, 2)  # the full damped matrix of these rows
    A.diagonal(dim1=1, dim2=2).sub_(Hs.diagonal(dim1=1, dim2=2) - ds)
    s2, ok2 = _solve_damped(Hs, ds, free2, -(gs + torch.bmm(A, dfix[..., None])[..., 0]))
    s2 = torch.minimum(torch.maximum(ts + s2 + dfix, lo), hi) - ts
    use2 = ok2 & ((s2 * (gs + 0.5 * torch.bmm(A, s2[..., None])[..., 0])).sum(1) < 0)
    if not bool(use2.all()):
        # fallback: hold the crossing variables already on their bound, truncate the rest
        s1 = torch.where(((ts <= lo) & bs) | ((ts >= hi) & as_), 0.0, s1)
        frac = torch.where(s1 < 0, (lo - ts) / s1, torch.where(s1 > 0, (hi - ts) / s1, 1.0))
        s2 = torch.where(use2[:, None], s2, s1 * frac.clamp(0.0, 1.0).amin(1, keepdim=True))
    step = step.index_copy(0, sub, s2)
    return torch.minimum(torch.maximum(th + step, lo), hi), ok


# ----------------------------------------------------------------------------- validation
def _resolve_free(D: int, free_dofs) -> list[int] | None:
    if free_dofs is None:
        return None
    if isinstance(free_dofs, torch.Tensor) and free_dofs.dtype == torch.bool:
        if free_dofs.shape != (D,):
            raise ValueError(f"free_dofs: expected a bool mask of shape ({D},), got "
                             f"{tuple(free_dofs.shape)}")
        out = free_dofs.nonzero().flatten().tolist()
    else:
        items = free_dofs.tolist() if isinstance(free_dofs, torch.Tensor) else free_dofs
        if isinstance(items, (int, str)) or not isinstance(items, Sequence) or any(
                isinstance(d, bool) or not isinstance(d, int) for d in items):
            raise ValueError(f"free_dofs: expected DoF indices or a bool mask, got {free_dofs!r}")
        out = list(items)
        if any(not 0 <= d < D for d in out):
            raise ValueError(f"free_dofs: indices must lie in [0, {D}), got {out}")
        if len(set(out)) != len(out):
            raise ValueError(f"free_dofs: duplicate indices in {out}")
    if not out:
        raise ValueError("free_dofs: expected at least one free DoF")
    return out


def _resolve_joints(sk: Skeleton, joints) -> list[int]:
    if joints is None:
        return list(range(sk.num_joints))
    if isinstance(joints, (str, int)) or not isinstance(joints, Sequence):
        raise ValueError(f"joints: expected a sequence of joint indices or names, got {joints!r}")
    out = []
    for j in joints:
        if isinstance(j, str):
            if j not in sk.joint_names:
                raise ValueError(f"joints: unknown joint {j!r}; known joints: {sk.joint_names}")
            out.append(sk.joint_index(j))
        else:
            try:
                k = int(j)
            except (TypeError, ValueError):
                raise ValueError(f"joints: expected joint indices or names, got {j!r}") from None
            if not 0 <= k < sk.num_joints:
                raise ValueError(f"joints: index {k} out of range for {sk.num_joints} joints")
            out.append(k)
    if not out:
        raise ValueError("joints: expected at least one joint")
    if len(set(out)) != len(out):
        raise ValueError(f"joints: duplicate joints in {list(joints)}")
    return out


def _check_inputs(sk, targets, theta0, joints, joint_weights, prior_weight, iterations, tol,
                  damping):
    if not isinstance(sk, Skeleton):
        raise TypeError(f"skeleton: expected a Skeleton, got {type(sk).__name__}")
    if not isinstance(targets, torch.Tensor):
        raise TypeError(f"targets: expected a torch.Tensor, got {type(targets).__name__}")
    if not isinstance(theta0, torch.Tensor):
        raise TypeError(f"theta0: expected a torch.Tensor, got {type(theta0).__name__}")
    M, D = len(joints), sk.num_dofs
    if targets.dim() != 3 or targets.shape[1:] != (M, 3):
        raise ValueError(f"targets: expected shape (P, {M}, 3), got {tuple(targets.shape)}")
    if not targets.is_floating_point():
        raise ValueError(f"targets: expected a floating-point tensor, got {targets.dtype}")
    P = targets.shape[0]
    if P == 0:
        raise ValueError("targets: expected at least one problem (P >= 1), got P = 0")
    if theta0.shape not in ((D,), (P, D)):
        raise ValueError(f"theta0: expected shape ({D},) or ({P}, {D}), got "
                         f"{tuple(theta0.shape)}")
    if not bool(torch.isfinite(targets).all()):
        raise ValueError("targets: expected finite values, found NaN or inf")
    if not bool(torch.isfinite(theta0).all()):
        raise ValueError("theta0: expected finite values, found NaN or inf")
    if joint_weights is not None:
        if not isinstance(joint_weights, torch.Tensor) or joint_weights.shape != (M,):
            shape = (tuple(joint_weights.shape) if isinstance(joint_weights, torch.Tensor)
                     else type(joint_weights).__name__)
            raise ValueError(f"joint_weights: expected shape ({M},), got {shape}")
        if not bool((torch.isfinite(joint_weights) & (joint_weights >= 0)).all()):
            raise ValueError("joint_weights: expected finite values >= 0")
        if not bool((joint_weights > 0).any()):
            raise ValueError("joint_weights: expected at least one positive weight")
    if not (math.isfinite(prior_weight) and prior_weight >= 0):
        raise ValueError(f"prior_weight: expected a finite value >= 0, got {prior_weight}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations: expected an int >= 0, got {iterations!r}")
    if not (math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol: expected a finite value >= 0 (metres), got {tol}")
    if not (math.isfinite(damping) and damping > 0):
        raise ValueError(f"damping: expected a finite value > 0, got {damping}")


# ----------------------------------------------------------------------------- solver
def project_to_skeleton(
    skeleton: Skeleton,
    targets: torch.Tensor,
    theta0: torch.Tensor,
    *,
    joints: Sequence[int] | Sequence[str] | None = None,
    joint_weights: torch.Tensor | None = None,
    prior_weight: float = 1e-3,
    iterations: int = 50,
    tol: float = 1e-4,
    damping: float = 1e-3,
    return_trace: bool = False,
    free_dofs: Sequence[int] | torch.Tensor | None = None,
) -> ProjectionResult:
    """Project joint positions onto the skeleton: ``argmin |x - F(theta)|^2`` within the limits.

    Solves, independently for every problem ``n`` of the batch (eq. 7 of Hauberg & Pedersen,
    with a small pull towards the warm start)::

        min_theta  sum_j w_j |targets[n, j] - F_j(theta)|^2 + prior_weight^2 |theta - theta0[n]|^2
        s.t.       skeleton.lower <= theta <= skeleton.upper

    by batched projected Levenberg-Marquardt started at ``theta0`` (clamped into the limits).
    No Python loop runs over problems. Converges to a local minimum near the warm start, which
    is what the projected prior wants (the previous pose is the start).

    Args:
        skeleton: the kinematic model (its ``offsets``, axes and joint limits are used).
        targets: ``(P, M, 3)`` joint positions in metres, ``M = len(joints)`` (all ``J`` joints
            of the skeleton, in its order, by default).
        theta0: ``(P, D)`` or ``(D,)`` warm start (e.g. the previous pose), radians (root
            translation in metres); clamped into the joint limits. The pull acts towards it.
        joints: optional subset of joint indices or names the targets belong to.
        joint_weights: optional ``(M,)`` weights ``w_j >= 0`` of the squared distances (e.g.
            ``1 / sigma_j^2`` up to a common factor); 1 by default. (:func:`fit_pose_lm`'s
            ``position_weights`` multiply the residuals: they are ``sqrt(w_j)``.)
        prior_weight: ``lambda``, the pull towards ``theta0`` in residual units (metres per
            radian; with ``1e-3`` a 1 rad change costs as much as 1 mm of joint error): it holds
            the directions the targets do not observe.
        iterations: maximum number of Levenberg-Marquardt iterations (0 returns the start).
        tol: a problem has converged (and stops being updated) when a step moves none of its
            targeted joints by more than ``tol`` metres while the damping does not dominate it.
            1e-4 m (the default) is well inside the centimetre noise of a spatial prior; use
            ~1e-9 for exact round trips.
        damping: initial Marquardt damping (relative to the diagonal of ``J^T J``).
        return_trace: also return the cost after every iteration (``cost_trace``).
        free_dofs: optional DoF indices (or a ``(D,)`` bool mask) to solve for; the others stay
            at ``theta0`` (clamped into the limits) and never enter the linear algebra — e.g.
            the upper body's 13 DoFs of human31's 31, for a fraction of the cost.
            Default: all DoFs.

    Returns:
        :class:`ProjectionResult` with ``theta (P, D)``, ``residual (P, M)`` (metres),
        ``cost (P,)``, ``converged (P,)``, ``iterations`` and optionally ``cost_trace``.

    Raises:
        ValueError: on wrong shapes, non-finite inputs or bad settings (the message names the
            argument and what was expected).
        TypeError: when ``skeleton`` is not a :class:`~torchmocap.skeleton.Skeleton` or
            ``targets``/``theta0`` are not tensors.

    The computation runs without autograd; the result is in the promoted dtype of ``targets``
    and ``theta0`` (float32 is accurate to ~1e-6 m), on ``targets``' device.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> theta = torch.zeros(200, sk.num_dofs)
        >>> g = torch.Generator().manual_seed(0)
        >>> x = sk(theta).positions + 0.03 * torch.randn(200, 21, 3, generator=g)
        >>> res = project_to_skeleton(sk, x, theta)
        >>> res.theta.shape, res.residual.shape
        (torch.Size([200, 31]), torch.Size([200, 21]))
    """
    sel = _resolve_joints(skeleton, joints) if isinstance(skeleton, Skeleton) else []
    _check_inputs(skeleton, targets, theta0, sel, joint_weights, float(prior_weight), iterations,
                  float(tol), float(damping))
    free = _resolve_free(skeleton.num_dofs, free_dofs)
    dtype = torch.promote_types(targets.dtype, theta0.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    device = targets.device
    targets = targets.detach().to(dtype)
    theta0 = theta0.detach().to(dtype=dtype, device=device)
    M = len(sel)
    w = (torch.ones(M, dtype=dtype, device=device) if joint_weights is None
         else joint_weights.detach().to(dtype=dtype, device=device))
    with torch.no_grad():
        prob = _Problem(skeleton, _plan(skeleton, dtype, device), targets, theta0, sel, w,
                        prior_weight, free)
        return _solve(prob, targets, iterations, float(tol), float(damping), return_trace)


class _Projection(DampedProblem):
    """The batch of one :func:`project_to_skeleton` as damped least-squares problems: a
    box-constrained (Gauss-)Newton step (:func:`_box_step`) damped by the Gauss-Newton diagonal,
    Nielsen's damping from the gain over the model's predicted decrease, the exact Hessian once
    a step moved no joint more than :data:`_NEWTON_RADIUS` (the Gauss-Newton matrix where it is
    not positive definite). Finished problems stay in the batch, frozen, until enough have
    finished; the SoA tensors carry the problems in their last dimension."""

    def __init__(self, prob: _Problem, tol: float, return_trace: bool):
        self.prob = prob
        P, M = prob.P, prob.M
        device = prob.x.device
        self.tol2, self.near2 = tol * tol, _NEWTON_RADIUS * _NEWTON_RADIUS
        self.th = prob.theta0.clone()
        self.th0 = prob.theta0
        self.base = prob.theta0_full  # the fixed DoFs' values (all of them, per problem)
        self.x = prob.x
        p, w = prob.kinematics(prob.full(self.th, self.base))
        self.res = p[:M] - self.x
        zero = torch.zeros_like(self.th)
        self.cost = prob.cost(self.res, zero)
        self.H, self.g, self.dgn, _ = prob.derivatives(p, w, self.x, zero)
        self.HG = None  # Gauss-Newton matrices where H holds the exact Hessian (``near`` rows)
        self.near = torch.zeros(P, dtype=torch.bool, device=device)
        self.out_theta = self.base.clone()
        self.out_res = self.res.clone()
        self.out_cost = self.cost.clone()
        self.trace = [self.cost.clone()] if return_trace else None

    def propose(self, mu, rows):
        # damped, projected (Gauss-)Newton step; where the exact Hessian is not positive
        # definite, the Gauss-Newton matrix replaces it (for this point) and is used at once
        prob, th, g, H = self.prob, self.th, self.g, self.H
        lo, hi = prob.lo, prob.hi
        damp = self.dgn * mu[:, None]
        cand, ok = _box_step(H, g, th, lo, hi, damp)
        if self.HG is not None:
            fb = (self.near & ~ok).nonzero().squeeze(1)
            if fb.numel():
                Hf = self.HG[fb]
                cf, okf = _box_step(Hf, g[fb], th[fb], lo, hi, damp[fb])
                cand, ok = cand.index_copy(0, fb, cf), ok.index_copy(0, fb, okf)
                H.index_copy_(0, fb, Hf)
        d = cand - th
        # model decrease of the cost, 2 (-g.d - d^T H d / 2), from the lower triangle Hl of H:
        # d^T H d = 2 d.(Hl d) - sum diag(H) d^2
        Hdd = torch.bmm(H, d[..., None])[..., 0]
        pred = (d * (H.diagonal(dim1=1, dim2=2) * d - 2 * (g + Hdd))).sum(1)
        # the candidate's cost change from residual differences (no cancellation)
        p_c, w_c = prob.kinematics(prob.full(cand, self.base))
        res_c = p_c[:prob.M] - self.x
        dp = res_c - self.res
        dcost = prob.w @ (dp * (res_c + self.res)).sum(1)
        if prob.lam2:
            dcost = dcost + prob.lam2 * (d * (d + 2 * (th - self.th0))).sum(1)
        return cand, ok, pred, p_c, w_c, res_c, dp, dcost

    def assess(self, trial, mu, rows):
        cand, ok, pred, p_c, w_c, res_c, dp, dcost = trial
        rho = torch.where(pred > 0, -dcost / pred, 0.0).clamp_(0.0, 1.0)
        self.disp2 = (dp * dp).sum(1).amax(0)
        # converged: the step (accepted or not: at the minimum the sign of a 1e-17 cost change
        # is rounding) moves no joint more than tol, with the damping not dominating it
        return Verdict(accepted=ok & (dcost <= 0) & (pred > 0), gain=rho,
                       converged=ok & (self.disp2 <= self.tol2) & (mu <= 1.0))

    def commit(self, trial, accepted, rows):
        cand, ok, pred, p_c, w_c, res_c, dp, dcost = trial
        # the exact Hessian from the first accepted step that moved no joint more than 1 cm
        self.near = self.near | (accepted & (self.disp2 <= self.near2))
        self.th = torch.where(accepted[:, None], cand, self.th)
        self.cost = torch.where(accepted, self.cost + dcost, self.cost)
        self.res = torch.where(accepted, res_c, self.res)
        self.p_c, self.w_c = p_c, w_c

    def iterated(self, iteration, ids):
        if self.trace is not None:
            self.trace.append(self.out_cost.index_copy(0, ids, self.cost))

    def retire(self, done, ids):
        sel = ids[done]
        self.out_theta[sel] = self.prob.full(self.th[done], self.base[done])
        self.out_cost[sel] = self.cost[done]
        self.out_res[..., sel] = self.res[..., done]

    def keep(self, mask):
        (self.th, self.th0, self.base, self.cost, self.H, self.g, self.dgn,
         self.near) = (t[mask] for t in (self.th, self.th0, self.base, self.cost, self.H,
                                         self.g, self.dgn, self.near))
        self.HG = None if self.HG is None else self.HG[mask]
        self.x, self.res, self.p_c, self.w_c = (t[..., mask] for t in (self.x, self.res,
                                                                      self.p_c, self.w_c))

    def relinearize(self, accepted):
        # derivatives at the accepted candidates only; the rejected keep theirs
        n_acc = int(accepted.sum())
        if not n_acc:
            return
        prob, dth = self.prob, self.th - self.th0
        if n_acc == accepted.numel():
            self.H, self.g, self.dgn, HGa = prob.derivatives(self.p_c, self.w_c, self.x, dth,
                                                             self.near)
            if HGa is not None:
                self.HG = HGa
        else:
            a = accepted.nonzero().squeeze(1)
            Ha, ga, da, HGa = prob.derivatives(
                self.p_c.index_select(-1, a), self.w_c.index_select(-1, a),
                self.x.index_select(-1, a), dth.index_select(0, a),
                self.near.index_select(0, a))
            self.H.index_copy_(0, a, Ha)
            self.g.index_copy_(0, a, ga)
            self.dgn.index_copy_(0, a, da)
            if HGa is not None:
                self.HG = self.H.clone() if self.HG is None else self.HG
                self.HG.index_copy_(0, a, HGa)


def _solve(prob: _Problem, targets, iterations, tol, damping, return_trace) -> ProjectionResult:
    solve = _Projection(prob, tol, return_trace)
    run = damped_least_squares(solve, prob.P, iterations,
                               Nielsen(initial=damping, min_shrink=_MIN_SHRINK, maximum=_MU_MAX),
                               compact=compact_when_worthwhile, device=targets.device,
                               dtype=targets.dtype)
    out_res = solve.out_res
    residual = (out_res * out_res).sum(1).sqrt_().t()
    return ProjectionResult(
        theta=solve.out_theta,
        residual=residual,
        cost=solve.out_cost,
        converged=run.converged,
        iterations=run.iterations,
        cost_trace=torch.stack(solve.trace) if return_trace else None,
    )


class SkeletonProjection(nn.Module):
    """Module form of :func:`project_to_skeleton`: stores the skeleton and the settings.

    Args:
        skeleton: the kinematic model (a submodule: ``.to()`` moves and casts it).
        joints, joint_weights, prior_weight, iterations, tol, damping, free_dofs: as in
            :func:`project_to_skeleton` (``joint_weights`` is kept as a buffer).

    Example:
        >>> from torchmocap.skeleton import upper_body
        >>> proj = SkeletonProjection(upper_body(), prior_weight=1e-3)
        >>> theta = torch.zeros(5, 14)
        >>> proj(proj.skeleton(theta).positions, theta).theta.shape
        torch.Size([5, 14])
    """

    def __init__(self, skeleton: Skeleton, *,
                 joints: Sequence[int] | Sequence[str] | None = None,
                 joint_weights: torch.Tensor | None = None, prior_weight: float = 1e-3,
                 iterations: int = 50, tol: float = 1e-4, damping: float = 1e-3,
                 free_dofs: Sequence[int] | torch.Tensor | None = None):
        super().__init__()
        self.skeleton = skeleton
        self.joints = _resolve_joints(skeleton, joints)
        self.free_dofs = _resolve_free(skeleton.num_dofs, free_dofs)
        self.register_buffer("joint_weights", None if joint_weights is None
                             else joint_weights.detach().clone())
        self.prior_weight = float(prior_weight)
        self.iterations = iterations
        self.tol = float(tol)
        self.damping = float(damping)

    def forward(self, targets: torch.Tensor, theta0: torch.Tensor,
                return_trace: bool = False) -> ProjectionResult:
        """Project ``targets (P, M, 3)`` from the warm start ``theta0 (P, D)`` or ``(D,)``."""
        return project_to_skeleton(
            self.skeleton, targets, theta0, joints=self.joints, joint_weights=self.joint_weights,
            prior_weight=self.prior_weight, iterations=self.iterations, tol=self.tol,
            damping=self.damping, return_trace=return_trace, free_dofs=self.free_dofs,
        )

    def extra_repr(self) -> str:
        return (f"joints={len(self.joints)}, prior_weight={self.prior_weight}, "
                f"iterations={self.iterations}, tol={self.tol}")
