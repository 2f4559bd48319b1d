"""Inverse kinematics of one limb from target joint positions (Sminchisescu & Triggs, §3.1-3.2).

A limb is a chain ``root (3 revolute DoF) -> hinge (1 DoF) -> end (0 or 2 DoF) [-> tip (fixed)]``
hanging from a parent frame that stays as in a given pose ``theta``: in ``human31`` the arms
(shoulder, elbow, wrist, hand; the wrist has no DoF) and the legs (hip, knee, ankle with 2 DoF,
toe); in ``upper_body`` the arms with a 2-DoF wrist. Given target world positions of the hinge,
end (and tip) joints, :func:`solve_limb` returns the limb's DoFs:

1. **hinge** from the root–end distance ``D``: ``|u + rot(h, phi) v| = D`` (law of cosines,
   ``u``/``v`` the upper/lower bone offsets, ``h`` the hinge axis) gives
   ``A cos(phi) + B sin(phi) = C`` and two roots ``phi0 +- acos(C / R)``. Out of reach, ``C / R``
   is clamped: the limb is fully stretched (or folded) and ``reachable`` is False.
2. **root rotation** ``L`` with ``L b = b*`` and ``L u`` as close as possible to ``a*`` (``b``,
   ``b*`` root->end, ``a*`` root->hinge target, in the parent frame): the minimal rotation
   ("swing") of the reference pose's ``L_ref`` taking ``L_ref b`` onto ``b*``, then the rotation
   about ``b*`` (the elbow's swivel, a Paden–Kahan subproblem 1) bringing the hinge joint onto
   its target. For a straight limb the swivel is unobservable: it is left at the reference
   pose's (``straight`` flag). Out of reach, the stretched limb points at the end target.
3. the 3 root angles by the 3-axis decomposition
   (:func:`~torchmocap.geometry.subproblems.orthogonal_three_axis_decomposition`, or the general
   one when the axes are not orthogonal) — two solutions;
4. a 2-DoF **end** joint from the tip target by subproblem 2 — two solutions.

All ``2 x 2 (x 2)`` candidates reproduce the same joint positions; each angle is moved by
``+-2 pi`` into its limits when possible and the candidate within limits (else with the smallest
violation) closest to the reference pose is returned.

The iterative fallback (§3.2) is a batched, bound-constrained Levenberg–Marquardt on the limb's
DoFs only, with their analytic Jacobian (the columns of :meth:`Skeleton.jacobian` for those
DoFs, evaluated on the limb alone), an active-set projection onto the joint limits and a weak
pull towards the reference that holds unobservable twists; it starts from every closed-form
candidate clamped into the limits and from the reference. ``method="auto"`` uses it
for the samples whose closed form violated a limit or left a residual above ``tol``, and keeps
whichever answer is within limits with the smaller error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from torchmocap.geometry.rotations import axis_angle_rotation
from torchmocap.geometry.subproblems import (
    axes_are_orthogonal,
    orthogonal_three_axis_decomposition,
    subproblem2,
    three_axis_decomposition,
    three_axis_rotation,
)
from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["LimbSpec", "LimbIKResult", "LimbIK", "HUMAN31_LIMBS", "solve_limb", "limb_dofs"]


@dataclass(frozen=True)
class LimbSpec:
    """Joint names of a limb: ``root`` (3 revolute DoF), its child ``hinge`` (1 DoF), the hinge's
    child ``end`` (0 or 2 DoF) and optionally the end's fixed child ``tip`` (no DoF)."""

    root: str
    hinge: str
    end: str
    tip: str | None = None

    @property
    def targets(self) -> tuple[str, ...]:
        """Names of the joints whose target positions :func:`solve_limb` takes, in order."""
        return (self.hinge, self.end) + ((self.tip,) if self.tip else ())


#: The four limbs of ``human31`` (and of ``upper_body`` for the arms).
HUMAN31_LIMBS: dict[str, LimbSpec] = {
    "l_arm": LimbSpec("l_shoulder", "l_elbow", "l_wrist", "l_hand"),
    "r_arm": LimbSpec("r_shoulder", "r_elbow", "r_wrist", "r_hand"),
    "l_leg": LimbSpec("l_hip", "l_knee", "l_ankle", "l_toe"),
    "r_leg": LimbSpec("r_hip", "r_knee", "r_ankle", "r_toe"),
}


@dataclass
class LimbIKResult:
    """Solution of :func:`solve_limb`.

    Attributes:
        theta: ``(*, D)`` the input pose with the limb's DoFs replaced.
        within_limits: ``(*)`` bool, the limb's DoFs lie inside the joint limits.
        residual: ``(*)`` largest distance (metres) between a target and its joint (forward
            kinematics of ``theta``).
        reachable: ``(*)`` bool, the end target lies within the limb's reach (the annulus
            ``||u| - |v|| <= D <= |u| + |v|`` around the root, up to ``tol``) and, with a
            2-DoF end joint and a tip target, the tip is reachable by that joint (subproblem 2
            exact up to ``tol``; joint limits ignored).
        straight: ``(*)`` bool, the limb is straight (or folded) so the swivel about the
            root–end axis is unobservable and was taken from the reference pose.
        iterative: ``(*)`` bool, the returned answer comes from the iterative solver.
    """

    theta: torch.Tensor
    within_limits: torch.Tensor
    residual: torch.Tensor
    reachable: torch.Tensor
    straight: torch.Tensor
    iterative: torch.Tensor


@dataclass
class _Plan:
    spec: LimbSpec
    parent: int  # joint index of the root's parent
    root: int
    target_joints: list[int]  # hinge, end[, tip]
    root_dofs: list[int]
    hinge_dof: int
    end_dofs: list[int]  # [] or two
    dofs: list[int]  # root_dofs + [hinge_dof] + end_dofs
    root_axes: torch.Tensor  # (3, 3) float64 rows
    orthogonal: bool
    hinge_axis: torch.Tensor  # (3,)
    end_axes: torch.Tensor | None  # (2, 3)
    u: torch.Tensor  # hinge offset in the root frame (3,)
    v: torch.Tensor  # end offset in the hinge frame (3,)
    w: torch.Tensor | None  # tip offset in the end frame (3,)


def _resolve_spec(skeleton: Skeleton, limb: str | LimbSpec) -> LimbSpec:
    if isinstance(limb, LimbSpec):
        return limb
    if isinstance(limb, str):
        if limb in HUMAN31_LIMBS:
            return HUMAN31_LIMBS[limb]
        raise KeyError(f"limb: unknown limb {limb!r}; known: {list(HUMAN31_LIMBS)} "
                       "(or pass a LimbSpec)")
    raise TypeError(f"limb: expected a limb name or a LimbSpec, got {type(limb).__name__}")


def _plan(skeleton: Skeleton, limb: str | LimbSpec) -> _Plan:
    spec = _resolve_spec(skeleton, limb)
    cache = skeleton.__dict__.setdefault("_limb_plans", {})
    if spec in cache:
        return cache[spec]
    sk = skeleton
    trans = set(sk.translation_dofs)

    def rot(name: str) -> list[int]:
        return [d for d in sk.joint_dofs(name) if d not in trans]

    r, h, e = sk.joint_index(spec.root), sk.joint_index(spec.hinge), sk.joint_index(spec.end)
    if r == 0 or sk.parents[r] < 0:
        raise ValueError(f"limb: root joint {spec.root!r} must have a parent (it is the root)")
    if len(rot(spec.root)) != 3:
        raise ValueError(f"limb: root joint {spec.root!r} needs 3 revolute DoF, has "
                         f"{len(rot(spec.root))}")
    if sk.parents[h] != r or len(rot(spec.hinge)) != 1:
        raise ValueError(f"limb: hinge {spec.hinge!r} must be a 1-DoF child of {spec.root!r}")
    if sk.parents[e] != h or len(rot(spec.end)) not in (0, 2):
        raise ValueError(f"limb: end {spec.end!r} must be a child of {spec.hinge!r} with 0 or 2 "
                         "revolute DoF")
    targets = [h, e]
    w = None
    off = sk.offsets.detach().double().cpu()
    if spec.tip is not None:
        t = sk.joint_index(spec.tip)
        if sk.parents[t] != e or rot(spec.tip):
            raise ValueError(f"limb: tip {spec.tip!r} must be a child of {spec.end!r} without DoF")
        targets.append(t)
        w = off[t]
    ax = torch.tensor(sk.joint_axes[r], dtype=torch.float64)
    end_axes = (torch.tensor(sk.joint_axes[e], dtype=torch.float64)
                if sk.joint_axes[e] else None)
    plan = _Plan(
        spec=spec, parent=sk.parents[r], root=r, target_joints=targets,
        root_dofs=rot(spec.root), hinge_dof=rot(spec.hinge)[0], end_dofs=rot(spec.end),
        dofs=rot(spec.root) + rot(spec.hinge) + rot(spec.end),
        root_axes=ax, orthogonal=axes_are_orthogonal(ax, tol=1e-9),
        hinge_axis=torch.tensor(sk.joint_axes[h][0], dtype=torch.float64),
        end_axes=end_axes, u=off[h], v=off[e], w=w,
    )
    cache[spec] = plan
    return plan


def limb_dofs(skeleton: Skeleton, limb: str | LimbSpec) -> list[int]:
    """Indices into ``theta`` of a limb's DoFs: root (3), hinge (1), end (0 or 2)."""
    return list(_plan(skeleton, limb).dofs)


# ---------------------------------------------------------------------- small batched helpers
def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b, dim=-1)


def _mv(R: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return (R @ x[..., None])[..., 0]


def _swing(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Minimal rotation taking unit ``x`` to unit ``y``, ``(*, 3) -> (*, 3, 3)``.

    ``x.y >= 0``: ``I + K + K^2 / (1 + x.y)`` with ``K = hat(x cross y)`` (smooth, also at the
    identity). ``x.y < 0``: the angle ``atan2(|y_perp|, x.y)`` about ``unit(x cross y_perp)``,
    ``y_perp = y - (x.y) x`` — crossing ``x`` with the small ``y_perp`` rather than with ``y``
    keeps the axis orthogonal to ``x`` to relative precision for nearly opposite vectors;
    exactly opposite ones get a half turn about an axis orthogonal to ``x``."""
    c = _dot(x, y)
    near = c >= 0
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    perp = _cross(x, eye[x.abs().argmin(-1)])
    perp = perp / perp.norm(dim=-1, keepdim=True)
    # c >= 0
    k = _cross(x, y)
    K = torch.zeros(*k.shape[:-1], 3, 3, dtype=x.dtype, device=x.device)
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    R_near = eye + K + (K @ K) / (1 + torch.where(near, c, torch.zeros_like(c)))[..., None, None]
    # c < 0 (inputs of the unused branch replaced by safe values: no NaN gradients)
    yp = torch.where(near[..., None], perp, y - c[..., None] * x)
    kp = _cross(x, yp)
    s2 = _dot(kp, kp)
    thr = (4 * torch.finfo(x.dtype).eps) ** 2
    degenerate = s2 <= thr
    s = torch.where(degenerate, torch.ones_like(s2), s2).sqrt()
    axis = torch.where(degenerate[..., None], perp, kp / s[..., None])
    angle = torch.atan2(torch.where(degenerate, torch.zeros_like(s), s), c)
    R_far = axis_angle_rotation(axis, angle)
    return torch.where(near[..., None, None], R_near, R_far)


def _fit_into_limits(a: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, ref: torch.Tensor
                     ) -> torch.Tensor:
    """Among ``a``, ``a +- 2 pi`` pick the one with the smallest limit violation, then the one
    closest to ``ref`` (elementwise)."""
    opts = torch.stack([a, a + 2 * math.pi, a - 2 * math.pi], -1)
    viol = (lo[..., None] - opts).clamp_min(0) + (opts - hi[..., None]).clamp_min(0)
    best = viol.min(-1, keepdim=True).values
    dist = (opts - ref[..., None]).abs()
    score = torch.where(viol <= best + 1e-12, dist, torch.full_like(dist, math.inf))
    return opts.gather(-1, score.argmin(-1, keepdim=True))[..., 0]


def _violation(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    return ((lo - x).clamp_min(0) + (x - hi).clamp_min(0)).sum(-1)


def _default_tol(dtype: torch.dtype) -> float:
    return 1e-8 if dtype == torch.float64 else 1e-5


# ---------------------------------------------------------------------- closed form
def _closed_form_candidates(plan: _Plan, R_par: torch.Tensor, p_root: torch.Tensor,
                            targets: torch.Tensor, ref: torch.Tensor, tol: float):
    """All closed-form candidates ``(B, C, n)`` plus ``reachable`` and ``straight`` ``(B,)``."""
    dt, dev = targets.dtype, targets.device
    B = targets.shape[0]
    u, v = plan.u.to(dt).to(dev), plan.v.to(dt).to(dev)
    h = plan.hinge_axis.to(dt).to(dev)
    axes = plan.root_axes.to(dt).to(dev)
    eps = torch.finfo(dt).eps

    a_t = _mv(R_par.transpose(-1, -2), targets[:, 0] - p_root)  # root->hinge target, (B, 3)
    b_t = _mv(R_par.transpose(-1, -2), targets[:, 1] - p_root)  # root->end target
    D = b_t.norm(dim=-1)

    # 1. hinge: A cos(phi) + B sin(phi) = C
    uh, vh = _dot(u, h), _dot(v, h)
    A = _dot(u, v) - uh * vh
    Bc = _dot(u, _cross(h, v))
    C = 0.5 * (D * D - _dot(u, u) - _dot(v, v)) - uh * vh
    Rn = math.hypot(float(A), float(Bc))
    phi_ref = ref[:, 3]
    if Rn <= 1e3 * eps * float(u.norm() * v.norm() + 1e-300):
        # hinge axis along a bone: the distance does not depend on phi
        phis = torch.stack([phi_ref, phi_ref], -1)
    else:
        phi0 = math.atan2(float(Bc), float(A))
        ratio = (C / Rn).clamp(-1.0, 1.0)
        acos = torch.acos(ratio)
        # collinear targets (hinge joint on the root-end line) at the extreme distance: the
        # limb is exactly straight (folded); acos near +-1 would leave a ~sqrt(eps) bend
        bt = b_t / D.clamp_min(torch.finfo(dt).tiny)[:, None]
        off_line = (a_t - _dot(a_t, bt)[:, None] * bt).norm(dim=-1)
        snap = (off_line <= 64 * eps * u.norm()) & (1 - ratio.abs() <= eps ** 0.5)
        acos = torch.where(snap, torch.where(ratio >= 0, torch.zeros_like(acos),
                                             torch.full_like(acos, math.pi)), acos)
        phis = torch.stack([phi0 + acos, phi0 - acos], -1)  # (B, 2)
    b_of = u + _mv(axis_angle_rotation(h.expand(B, 2, 3), phis), v.expand(B, 2, 3))  # (B, 2, 3)
    reach_gap = (b_of.norm(dim=-1)[:, 0] - D).abs()
    reachable = reach_gap <= tol

    # 2. root rotation: swing of the reference onto the end direction, then swivel about it
    L_ref = three_axis_rotation(axes.expand(B, 3, 3), ref[:, :3])  # (B, 3, 3)
    Lb = _mv(L_ref[:, None], b_of)  # (B, 2, 3)
    Lb_hat = Lb / Lb.norm(dim=-1, keepdim=True)
    tiny = D <= 1e3 * eps
    bt_hat = torch.where(tiny[:, None], Lb_hat[:, 0],
                         b_t / torch.where(tiny, torch.ones_like(D), D)[:, None])
    bt_hat = bt_hat[:, None].expand(B, 2, 3)
    L0 = _swing(Lb_hat, bt_hat) @ L_ref[:, None]  # (B, 2, 3, 3)
    x = _mv(L0, u.expand(B, 2, 3))  # hinge joint after the swing
    y = a_t[:, None].expand(B, 2, 3)
    xp = x - _dot(x, bt_hat)[..., None] * bt_hat
    yp = y - _dot(y, bt_hat)[..., None] * bt_hat
    thr = 64 * eps * u.norm()
    straight2 = (xp.norm(dim=-1) <= thr) | (yp.norm(dim=-1) <= thr)  # (B, 2)
    psi = torch.atan2(_dot(bt_hat, _cross(xp, yp)), _dot(xp, yp))
    psi = torch.where(straight2, torch.zeros_like(psi), psi)
    L = axis_angle_rotation(bt_hat, psi) @ L0  # (B, 2, 3, 3)

    # 3. root angles: two decompositions per hinge root
    t1_ref = ref[:, 0, None].expand(B, 2)
    if plan.orthogonal:
        ang, _ = orthogonal_three_axis_decomposition(L, axes.expand(B, 2, 3, 3), t1_ref)
    else:
        ang = three_axis_decomposition(L, axes[0], axes[1], axes[2], default_theta1=t1_ref,
                                       compute_residual=False).angles
    # ang (B, 2 hinge, 2 decomp, 3)
    root = ang.reshape(B, 4, 3)
    hinge = phis[:, :, None].expand(B, 2, 2).reshape(B, 4, 1)
    cands = torch.cat([root, hinge], -1)  # (B, 4, 4)

    # 4. end joint (2 DoF) from the tip target
    if plan.end_dofs:
        end_ref = ref[:, 4:6]
        if plan.w is not None and targets.shape[1] >= 3:
            k1, k2 = plan.end_axes.to(dt).to(dev).unbind(0)
            w = plan.w.to(dt).to(dev)
            R_hinge = R_par[:, None] @ L @ axis_angle_rotation(h.expand(B, 2, 3), phis)
            end_pos = p_root[:, None] + _mv(R_par[:, None], _mv(L, b_of))
            q = _mv(R_hinge.transpose(-1, -2), targets[:, None, 2] - end_pos)  # (B, 2, 3)
            sp = subproblem2(k1.expand(B, 2, 3), k2.expand(B, 2, 3), w.expand(B, 2, 3), q,
                             default_theta1=end_ref[:, 0, None].expand(B, 2))
            end = torch.stack([sp.theta1, sp.theta2], -1)  # (B, 2 hinge, 2 sol, 2)
            reachable = reachable & (sp.residual.amin(-1)[:, 0] <= tol)
        else:
            end = end_ref[:, None, None].expand(B, 2, 1, 2)
        ns = end.shape[2]
        rh = cands.reshape(B, 2, 2, 1, 4).expand(B, 2, 2, ns, 4)
        ee = end[:, :, None].expand(B, 2, 2, ns, 2)
        cands = torch.cat([rh, ee], -1).reshape(B, 4 * ns, 6)
    return cands, reachable, straight2.any(-1)


def _select(cands: torch.Tensor, ref: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Fit each angle into its limits, then pick the least-violating candidate closest to
    ``ref``; returns ``(B, n)`` angles and the violation ``(B,)``."""
    fitted = _fit_into_limits(cands, lo, hi, ref[:, None].expand_as(cands))
    viol = _violation(fitted, lo, hi)  # (B, C)
    dist = ((fitted - ref[:, None]) ** 2).sum(-1)
    best = viol.min(-1, keepdim=True).values
    score = torch.where(viol <= best + 1e-12, dist, torch.full_like(dist, math.inf))
    idx = score.argmin(-1)
    ar = torch.arange(cands.shape[0], device=cands.device)
    return fitted[ar, idx], viol[ar, idx], fitted


# ---------------------------------------------------------------------- iterative fallback
def _limb_forward(plan: _Plan, R_par: torch.Tensor, p_root: torch.Tensor, x: torch.Tensor,
                  num_targets: int, with_jac: bool):
    """Forward kinematics of the limb alone: target-joint positions ``(B, M, 3)`` for limb
    angles ``x (B, n)`` below a fixed parent frame, and (optionally) their geometric Jacobian
    ``(B, M, 3, n)`` — the columns of :meth:`Skeleton.jacobian` for the limb's DoFs
    (``w x (p_i - p_joint)`` with ``w`` the DoF's world axis)."""
    dt, dev = x.dtype, x.device
    B = x.shape[0]
    ax = plan.root_axes.to(dtype=dt, device=dev)
    h = plan.hinge_axis.to(dtype=dt, device=dev)
    u, v = plan.u.to(dtype=dt, device=dev), plan.v.to(dtype=dt, device=dev)
    R = R_par
    axes_w, pivots = [], []
    for k in range(3):
        axes_w.append(_mv(R, ax[k].expand(B, 3)))
        pivots.append(0)
        R = R @ axis_angle_rotation(ax[k].expand(B, 3), x[:, k])
    p_h = p_root + _mv(R, u.expand(B, 3))
    axes_w.append(_mv(R, h.expand(B, 3)))
    pivots.append(1)
    R = R @ axis_angle_rotation(h.expand(B, 3), x[:, 3])
    p_e = p_h + _mv(R, v.expand(B, 3))
    pos = [p_h, p_e]
    if plan.end_axes is not None:
        ke = plan.end_axes.to(dtype=dt, device=dev)
        for k in range(2):
            axes_w.append(_mv(R, ke[k].expand(B, 3)))
            pivots.append(2)
            R = R @ axis_angle_rotation(ke[k].expand(B, 3), x[:, 4 + k])
    if num_targets > 2:
        pos.append(p_e + _mv(R, plan.w.to(dtype=dt, device=dev).expand(B, 3)))
    P = torch.stack(pos, 1)  # (B, M, 3)
    if not with_jac:
        return P, None
    joint_pos = [p_root, p_h, p_e]
    cols = []
    for w, piv in zip(axes_w, pivots):
        lever = P - joint_pos[piv][:, None]
        col = torch.linalg.cross(w[:, None].expand_as(lever), lever, dim=-1)
        below = torch.tensor([m >= piv for m in range(P.shape[1])], device=dev)
        cols.append(torch.where(below[None, :, None], col, torch.zeros_like(col)))
    return P, torch.stack(cols, -1)  # (B, M, 3, n)


def _limb_lm(plan: _Plan, R_par: torch.Tensor, p_root: torch.Tensor, x0: torch.Tensor,
             targets: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, prior: torch.Tensor,
             prior_weight: float, iterations: int, damping: float = 1e-3) -> torch.Tensor:
    """Bound-constrained Levenberg–Marquardt on the limb angles ``x (B, n)`` (rows independent).

    Cost ``sum_i |p_i(x) - target_i|^2 + w^2 |x - prior|^2``; Marquardt damping per problem;
    active-set projection: a DoF at a bound whose gradient points outwards is held, the others
    take the damped Gauss–Newton step, clamped into the box.
    """
    B, n = x0.shape
    M = targets.shape[1]
    dt, dev = x0.dtype, x0.device
    eye = torch.eye(n, dtype=dt, device=dev)
    wp = float(prior_weight)

    def residuals(x: torch.Tensor, with_jac: bool):
        P, Jp = _limb_forward(plan, R_par, p_root, x, M, with_jac)
        r = torch.cat([(P - targets).reshape(B, -1), wp * (x - prior)], 1)
        J = None if Jp is None else torch.cat([Jp.reshape(B, 3 * M, n),
                                               (wp * eye).expand(B, n, n)], 1)
        return r, J

    x = torch.maximum(torch.minimum(x0, hi), lo)
    r, J = residuals(x, True)
    cost = (r * r).sum(1)
    mu = torch.full((B,), float(damping), dtype=dt, device=dev)
    active = torch.ones(B, dtype=torch.bool, device=dev)
    eps = torch.finfo(dt).eps
    rtol, xtol, ctol = 1e3 * eps, 1e3 * eps, (16 * eps) ** 2
    for _ in range(iterations):
        g = (J.transpose(1, 2) @ r[..., None])[..., 0]  # (B, n)
        JtJ = J.transpose(1, 2) @ J
        fixed = ((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0))
        free = (~fixed).to(dt)
        A = JtJ * (free[:, :, None] * free[:, None, :]) + torch.diag_embed(
            mu[:, None] * (JtJ.diagonal(dim1=1, dim2=2) + 1e-9) * free + (1 - free))
        step = torch.linalg.solve(A, -(g * free)[..., None])[..., 0]
        cand = torch.maximum(torch.minimum(x + step, hi), lo)
        r_new, J_new = residuals(cand, True)
        cost_new = (r_new * r_new).sum(1)
        better = (cost_new < cost) & active
        rel = (cost - cost_new).clamp_min(0) / cost.clamp_min(ctol)
        small = (cand - x).abs().amax(-1) <= xtol
        x = torch.where(better[:, None], cand, x)
        r = torch.where(better[:, None], r_new, r)
        J = torch.where(better[:, None, None], J_new, J)
        cost = torch.where(better, cost_new, cost)
        mu = torch.where(better, (mu / 3).clamp_min(1e-12), (mu * 4).clamp_max(1e12))
        active = active & ~((better & (rel < rtol)) | small | (mu >= 1e6) | (cost <= ctol))
        if not bool(active.any()):
            break
    return x


# ---------------------------------------------------------------------- public API
def solve_limb(
    skeleton: Skeleton,
    theta: torch.Tensor,
    limb: str | LimbSpec,
    targets: torch.Tensor,
    method: str = "auto",
    reference: torch.Tensor | None = None,
    tol: float | None = None,
    iterations: int = 50,
    prior_weight: float = 1e-6,
) -> LimbIKResult:
    """Joint angles of one limb that put its joints on target world positions.

    Everything above the limb (the root joint's parent frame) stays as in ``theta``.

    Args:
        skeleton: the model (e.g. :func:`torchmocap.skeleton.human31`).
        theta: ``(*, D)`` poses; the limb's DoFs are replaced, the rest is kept.
        limb: ``"l_arm"``, ``"r_arm"``, ``"l_leg"``, ``"r_leg"`` (:data:`HUMAN31_LIMBS`) or a
            :class:`LimbSpec`.
        targets: ``(*, M, 3)`` world positions (metres) of the limb's joints after the root, in
            the order of :attr:`LimbSpec.targets`: hinge, end and (``M = 3``) tip — human31 arm:
            elbow, wrist[, hand]; leg: knee, ankle[, toe]. Without a tip target a 2-DoF end
            joint keeps its reference angles.
        method: ``"closed_form"``, ``"iterative"`` (LM from the reference only) or ``"auto"``
            (closed form, LM fallback where it violated a limit or left a residual > ``tol``).
        reference: ``(*, D)`` pose that picks among the solutions and supplies unobservable
            angles (swivel of a straight limb, gimbal lock); default ``theta``.
        tol: residual (metres) above which ``auto`` falls back, also the reach tolerance;
            default ``1e-8`` in float64 and ``1e-5`` otherwise.
        iterations: maximum LM iterations.
        prior_weight: LM pull towards the reference (metres of residual per radian).

    Returns:
        :class:`LimbIKResult` with ``theta (*, D)`` and ``(*)`` flags.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> sk = human31()
        >>> theta = torch.zeros(4, sk.num_dofs)
        >>> idx = [sk.joint_index(j) for j in ("l_knee", "l_ankle", "l_toe")]
        >>> pos = sk(theta).positions[:, idx]
        >>> solve_limb(sk, theta, "l_leg", pos).theta.shape
        torch.Size([4, 31])
    """
    if not isinstance(skeleton, Skeleton):
        raise TypeError(f"skeleton: expected a Skeleton, got {type(skeleton).__name__}")
    if method not in ("closed_form", "iterative", "auto"):
        raise ValueError(f"method: expected 'closed_form', 'iterative' or 'auto', got {method!r}")
    plan = _plan(skeleton, limb)
    skeleton._check_theta(theta)
    if not isinstance(targets, torch.Tensor):
        raise TypeError(f"targets: expected a torch.Tensor, got {type(targets).__name__}")
    Mmax = len(plan.target_joints)
    if targets.dim() < 2 or targets.shape[-1] != 3 or not 2 <= targets.shape[-2] <= Mmax:
        raise ValueError(f"targets: expected shape (*, M, 3) with M in 2..{Mmax} "
                         f"({', '.join(plan.spec.targets)}), got {tuple(targets.shape)}")
    if not bool(torch.isfinite(theta).all()):
        raise ValueError("theta: expected finite values, found NaN or inf")
    if not bool(torch.isfinite(targets).all()):
        raise ValueError("targets: expected finite values, found NaN or inf")
    if reference is None:
        reference = theta
    else:
        skeleton._check_theta(reference)
        if not bool(torch.isfinite(reference).all()):
            raise ValueError("reference: expected finite values, found NaN or inf")
    dt, dev = theta.dtype, theta.device
    targets = targets.to(dt)
    M = targets.shape[-2]
    batch = torch.broadcast_shapes(theta.shape[:-1], targets.shape[:-2], reference.shape[:-1])
    D = skeleton.num_dofs
    Bn = int(math.prod(batch))
    th = theta.expand(*batch, D).reshape(Bn, D)
    tg = targets.expand(*batch, M, 3).reshape(Bn, M, 3)
    rf_full = reference.to(dt).expand(*batch, D).reshape(Bn, D)
    tol = _default_tol(dt) if tol is None else float(tol)
    didx = torch.tensor(plan.dofs, device=dev)
    lo = skeleton.lower.to(dt).to(dev).index_select(0, didx)
    hi = skeleton.upper.to(dt).to(dev).index_select(0, didx)
    ref = rf_full.index_select(1, didx)

    # the frame above the limb depends on theta alone: posed once per distinct theta (a
    # theta broadcast over many targets, as the leaves of an interpretation tree, is not
    # posed again for each)
    lead = theta.shape[:-1]
    kin = skeleton(theta.reshape(-1, D), check_finite=False)
    R_par = kin.rotations[:, plan.parent].reshape(*lead, 3, 3).expand(*batch, 3, 3)
    R_par = R_par.reshape(Bn, 3, 3)
    p_root = kin.positions[:, plan.root].reshape(*lead, 3).expand(*batch, 3).reshape(Bn, 3)

    def assemble(x: torch.Tensor) -> torch.Tensor:
        out = th.clone()
        out[:, didx] = x
        return out

    def evaluate(t: torch.Tensor, goal: torch.Tensor, R: torch.Tensor, p: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        # poses t differ from th only in the limb's DoFs: the limb's own kinematics below
        # its fixed parent frame (R, p) places its joints
        e = (_limb_forward(plan, R, p, t.index_select(1, didx), M, False)[0] - goal).norm(dim=-1)
        return e.amax(-1), (e * e).sum(-1)

    cands, reachable, straight = _closed_form_candidates(plan, R_par, p_root, tg, ref, tol)
    lim_tol = 1e3 * torch.finfo(dt).eps

    def inside_limits(t: torch.Tensor) -> torch.Tensor:
        x = t.index_select(1, didx)
        return ((x >= lo) & (x <= hi)).all(-1)

    zeros = torch.zeros(Bn, dtype=torch.bool, device=dev)
    if method == "iterative":
        x = _limb_lm(plan, R_par, p_root, ref, tg, lo, hi, ref, prior_weight, iterations)
        t_out = assemble(x)
        iterative = ~zeros
    else:
        x, viol, fitted = _select(cands, ref, lo, hi)
        x = torch.where((viol <= lim_tol)[:, None], torch.maximum(torch.minimum(x, hi), lo), x)
        t_out = assemble(x)
        iterative = zeros
        if method == "auto":
            res, sse = evaluate(t_out, tg, R_par, p_root)
            inside = inside_limits(t_out)
            bad = (~inside) | (res > tol)
            if bool(bad.any()):
                ib = bad.nonzero()[:, 0]
                starts = torch.cat([fitted[ib], ref[ib, None]], 1)  # (b, S, n)
                b, S, n = starts.shape

                def rep(z: torch.Tensor, ib=ib, S=S) -> torch.Tensor:
                    return z[ib].repeat_interleave(S, 0)

                tgb = rep(tg)
                xs = _limb_lm(plan, rep(R_par), rep(p_root), starts.reshape(b * S, n), tgb,
                              lo, hi, rep(ref), prior_weight, iterations)
                tb = th[ib].repeat_interleave(S, 0)
                tb[:, didx] = xs
                _, c_s = evaluate(tb, tgb, rep(R_par), rep(p_root))
                pick = c_s.reshape(b, S).argmin(-1)
                ar = torch.arange(b, device=dev)
                sol = tb.reshape(b, S, D)[ar, pick]
                c_best = c_s.reshape(b, S)[ar, pick]
                use = (~inside[ib]) | (c_best < sse[ib])
                t_out = t_out.clone()
                t_out[ib] = torch.where(use[:, None], sol, t_out[ib])
                iterative = iterative.clone()
                iterative[ib] = use
    residual, _ = evaluate(t_out, tg, R_par, p_root)
    within = inside_limits(t_out)
    return LimbIKResult(
        theta=t_out.reshape(*batch, D),
        within_limits=within.reshape(batch),
        residual=residual.reshape(batch),
        reachable=reachable.reshape(batch),
        straight=straight.reshape(batch),
        iterative=iterative.reshape(batch),
    )


class LimbIK(nn.Module):
    """Thin module around :func:`solve_limb` for one limb of one skeleton.

    Args:
        skeleton: the model (registered as a submodule).
        limb: limb name or :class:`LimbSpec`.
        method, tol, iterations, prior_weight: as in :func:`solve_limb`.

    Example:
        >>> from torchmocap.skeleton import human31
        >>> ik = LimbIK(human31(), "r_arm")
        >>> th = torch.zeros(2, 31)
        >>> ik(th, ik.skeleton(th).positions[:, [10, 11]]).residual.shape
        torch.Size([2])
    """

    def __init__(self, skeleton: Skeleton, limb: str | LimbSpec, method: str = "auto",
                 tol: float | None = None, iterations: int = 50, prior_weight: float = 1e-6):
        super().__init__()
        self.skeleton = skeleton
        self.spec = _resolve_spec(skeleton, limb)
        _plan(skeleton, self.spec)  # validate now
        if method not in ("closed_form", "iterative", "auto"):
            raise ValueError(f"method: expected 'closed_form', 'iterative' or 'auto', got "
                             f"{method!r}")
        self.method, self.tol = method, tol
        self.iterations, self.prior_weight = iterations, prior_weight

    @property
    def dofs(self) -> list[int]:
        """Indices into ``theta`` of the limb's DoFs."""
        return limb_dofs(self.skeleton, self.spec)

    def forward(self, theta: torch.Tensor, targets: torch.Tensor,
                reference: torch.Tensor | None = None) -> LimbIKResult:
        return solve_limb(self.skeleton, theta, self.spec, targets, self.method, reference,
                          self.tol, self.iterations, self.prior_weight)

    def extra_repr(self) -> str:
        return f"limb={self.spec}, method={self.method!r}"
