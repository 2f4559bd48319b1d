"""Fitting the subject to a recording's triangulated keypoints: bone lengths and first poses.

Input: the first frames' triangulated detector keypoints ``points (T0, K, 3)`` (NaN where not
triangulated) with weights (e.g. the detections' confidences), and a
:class:`~torchmocap.skeleton.KeypointMap` placing the format's keypoints on a template skeleton
(human31). Keypoints are not joint centres, so the fit compares the *mapped keypoints* of the
skeleton (joint + offset, :func:`~torchmocap.skeleton.keypoint_positions`) with the points:

1. *Body scale*: the keypoint pairs whose distance does not depend on the pose (two keypoints
   on one bone, or on the two ends of one bone: knee-ankle, elbow-wrist, the shoulders, the
   hips, points on the head) are found from the template at random poses; the scale is the
   median over those pairs of the median over frames of the observed / template distance.
   The template's bone lengths and the map's offsets are scaled by it.
2. *First poses* by inverse kinematics with joint limits
   (:func:`~torchmocap.ik.project_to_skeleton`: each keypoint is a fixed child joint of the
   bone it rides on, :meth:`~torchmocap.skeleton.KeypointMap.attachment`), from several starts
   per frame: every posture of ``postures`` (standing; seated) turned by ``headings`` angles
   about its trunk axis, with the trunk axis tilted onto the observed one (the hips-to-shoulders
   direction of the points: no standing start is assumed) and the keypoints' centroid on the
   observed one. The start of lowest robust cost wins; iteratively reweighted (Cauchy weights
   of scale ``robust_scale``) so that a wrongly triangulated keypoint loses its pull.
3. *Bone lengths and poses together*: the skeleton's rest offsets are a linear function of a
   few parameters (:func:`_offset_basis`: a limb segment's length; each component of a bent
   offset such as human31's shoulder and toe offsets, so that e.g. the shoulders' width is
   measured apart from their height; left and right shared, mirrored), and at fixed bone
   rotations every keypoint is linear in them. They join the poses of all frames in one
   Levenberg-Marquardt refinement of the robust (Cauchy) cost, with the joint limits (an active
   set on the box), a weak pull (``length_prior``) of each parameter towards the scaled
   template, and a tiny pull of the poses towards step 2's (the directions the keypoints do not
   observe). What the keypoints do not observe keeps the scaled template's: the hands, the
   spine, and (``hold``, default :data:`TRUNK_HOLD`) the heights of the hips and shoulders in
   the trunk — the hip keypoints lie on the hip axis, so the pelvis's pitch is unseen and the
   trunk's bend between pelvis and spine trades freely against the shoulders' height above the
   spine's pivot. Alternating lengths and poses instead converges slowly: both move the same
   keypoints.

Shapes: ``T0`` frames, ``K`` keypoints of the format, ``K'`` mapped keypoints, ``D`` DoF.

Example:
    >>> from torchmocap.skeleton import human31, load_keypoint_map, keypoint_positions
    >>> sk, kmap = human31().double(), load_keypoint_map("body_25b")
    >>> kin = sk(sk.zero_pose((3,)))
    >>> pts = keypoint_positions(kin.positions, kin.rotations, kmap)      # (3, 25, 3)
    >>> fit = fit_keypoint_subject(pts, None, kmap, headings=2)
    >>> fit.theta.shape, fit.residual.shape
    (torch.Size([3, 31]), torch.Size([3, 25]))
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchmocap.geometry.rotations import axis_angle_rotation
from torchmocap.ik.projection import project_to_skeleton
from torchmocap.least_squares import DampedProblem, Marquardt, Verdict, damped_least_squares
from torchmocap.skeleton.keypoints import KeypointMap, keypoint_positions, load_keypoint_map
from torchmocap.skeleton.skeleton import Skeleton

__all__ = ["KeypointFit", "SEATED", "TRUNK_HOLD", "fit_keypoint_subject"]

#: Offset components of human31 the subject fit keeps (module docstring, step 3).
TRUNK_HOLD = {"l_hip": "z", "r_hip": "z", "l_shoulder": "z", "r_shoulder": "z"}
#: A seated start posture of human31 (degrees): hips and knees flexed 90 degrees.
SEATED = {"l_hip_flex": 90.0, "r_hip_flex": 90.0, "l_knee_flex": 90.0, "r_knee_flex": 90.0}
_MIN_KEYPOINTS = 4  # observed keypoints a frame needs (a rigid placement needs 3)
_RIGID_TOL = 1e-6  # m: spread of a pair's distance over random poses for a pose-invariant pair
_MIN_PAIR = 0.15  # m: shorter pose-invariant pairs are too noisy to measure the scale
_KP = "kp:"  # name prefix of the keypoints as child joints
_POSE_PULL = 1e-3  # m per radian: pull of the refined poses towards the first fit
_STEP_TOL = 1e-6  # the refinement stops once a step moves no angle (rad) or length (m) more,
_GAIN_TOL = 1e-6  # or lowers the cost by less than this fraction


@dataclass
class KeypointFit:
    """Result of :func:`fit_keypoint_subject`.

    Attributes:
        skeleton: the template with the subject's rest offsets (bone lengths; float64).
        keypoint_map: the map bound to ``skeleton``, offsets scaled with the body.
        theta: ``(T0, D)`` fitted poses.
        residual: ``(T0, K')`` distance (m) of each mapped keypoint from its point (NaN where
            the point is missing).
        cost: ``(T0,)`` robust cost of each frame's fit (sum of weighted Cauchy costs).
        scale: the body scale of step 1 (subject / template).
        lengths: ``{joint: length (m)}`` of the bone from each non-root joint to its parent.
        info: ``starts`` (per frame), ``start_index`` (``(T0,)`` the winning start of each
            frame), ``refine_iterations`` (of step 3), ``scale_pairs`` (the pose-invariant
            pairs used, with their observed / template ratios), ``offset_parameters`` (step 3's
            parameters by name, metres: ``knee`` a length, ``shoulder.x`` a component).
    """

    skeleton: Skeleton
    keypoint_map: KeypointMap
    theta: torch.Tensor
    residual: torch.Tensor
    cost: torch.Tensor
    scale: float
    lengths: dict[str, float]
    info: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- helpers
def _keypoint_skeleton(sk: Skeleton, kmap: KeypointMap) -> tuple[Skeleton, list[str]]:
    """``sk`` with every mapped keypoint as a fixed child joint of the bone it rides on."""
    bones, off = kmap.attachment(sk)
    spec = sk.to_dict()
    names = [_KP + n for n in kmap.names]
    for n, b, o in zip(names, bones, off.tolist()):
        spec["joints"].append({"name": n, "parent": sk.joint_names[b], "offset": o})
    aug = Skeleton.from_dict(spec).to(dtype=torch.float64)
    if aug.dof_names != sk.dof_names:  # pragma: no cover - fixed children add no DoF
        raise RuntimeError("keypoint joints changed the skeleton's DoFs")
    return aug, names


def _cauchy(r2: torch.Tensor, s2: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Cauchy cost ``log(1 + r^2 / s^2)`` and IRLS weight ``1 / (1 + r^2 / s^2)``."""
    z = r2 / s2
    return torch.log1p(z), 1.0 / (1.0 + z)


def _scale(X: torch.Tensor, W: torch.Tensor, sk: Skeleton, kmap: KeypointMap,
           gen: torch.Generator) -> tuple[float, dict[str, float]]:
    """Body scale from the pose-invariant keypoint pairs (module docstring, step 1)."""
    lo = sk.lower.double().clamp(min=-math.pi)
    hi = sk.upper.double().clamp(max=math.pi)
    th = lo + (hi - lo) * torch.rand(64, sk.num_dofs, generator=gen, dtype=torch.float64)
    kin = sk(th)
    x = keypoint_positions(kin.positions, kin.rotations, kmap)  # (64, K', 3)
    d = (x[:, :, None] - x[:, None]).norm(dim=-1)  # (64, K', K')
    rigid = (d.std(0) < _RIGID_TOL) & (d.mean(0) > _MIN_PAIR)
    rigid = rigid.triu(1)
    seen = W > 0
    ratios = {}
    for a, b in rigid.nonzero().tolist():
        both = seen[:, a] & seen[:, b]
        if not bool(both.any()):
            continue
        obs = (X[both, a] - X[both, b]).norm(dim=-1)
        ratios[f"{kmap.names[a]}-{kmap.names[b]}"] = float(obs.median() / d[0, a, b])
    if not ratios:
        return 1.0, ratios
    return float(torch.tensor(list(ratios.values())).median()), ratios


def _root_euler(sk: Skeleton, R: torch.Tensor) -> torch.Tensor:
    """Angles ``(N, 3)`` of the root's three axes giving the rotations ``R (N, 3, 3)``."""
    A = torch.tensor(sk.joint_axes[0], dtype=R.dtype).t()  # columns: the root's axes
    if A.shape != (3, 3) or not torch.allclose(A.t() @ A, torch.eye(3, dtype=R.dtype),
                                               atol=1e-9) or float(torch.linalg.det(A)) < 0:
        raise ValueError("base: the root needs three orthonormal, right-handed rotation axes "
                         "to be placed from the keypoints")
    Q = A.t() @ R @ A  # = Rx(a) Ry(b) Rz(c) in the axes' basis
    b = torch.asin(Q[:, 0, 2].clamp(-1.0, 1.0))
    a = torch.atan2(-Q[:, 1, 2], Q[:, 2, 2])
    c = torch.atan2(-Q[:, 0, 1], Q[:, 0, 0])
    return torch.stack([a, b, c], -1)


def _rotation_between(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The smallest rotation ``(3, 3)`` taking unit ``u`` to unit ``v``."""
    w = torch.linalg.cross(u, v)
    s, c = float(w.norm()), float(u @ v)
    if s > 1e-12:
        return axis_angle_rotation(w / s, torch.tensor(math.atan2(s, c), dtype=u.dtype))
    if c > 0:
        return torch.eye(3, dtype=u.dtype)
    p = torch.eye(3, dtype=u.dtype)[int(u.abs().argmin())]  # opposite: a half turn about a normal
    n = torch.nn.functional.normalize(p - (p @ u) * u, dim=0)
    return axis_angle_rotation(n, torch.tensor(math.pi, dtype=u.dtype))


def _trunk_groups(sk: Skeleton, kmap: KeypointMap) -> tuple[torch.Tensor, torch.Tensor]:
    """Masks ``(K',)`` of the keypoints riding on the root's bone (hips) and of those on the
    chain from the root to the skeleton's highest joint at rest (shoulders, neck, head)."""
    top = int(sk(sk.zero_pose((), dtype=torch.float64)).positions[:, 2].argmax())
    chain = []
    j = top
    while sk.parents[j] >= 0:
        chain.append(j)
        j = sk.parents[j]
    frames = kmap.frame_index
    return frames == 0, torch.tensor([int(f) in chain for f in frames.tolist()])


def _starts(sk: Skeleton, kmap: KeypointMap, X: torch.Tensor, seen: torch.Tensor,
            postures: list[torch.Tensor], headings: int) -> torch.Tensor:
    """Start poses ``(S, D)`` of one frame (module docstring, step 2)."""
    low, up = _trunk_groups(sk, kmap)
    low, up = low & seen, up & seen
    theta = []
    for th0 in postures:
        kin = sk(th0)
        x0 = keypoint_positions(kin.positions, kin.rotations, kmap)  # (K', 3)
        tilt = torch.eye(3, dtype=X.dtype)
        axis = torch.tensor([0.0, 0.0, 1.0], dtype=X.dtype)
        if bool(low.any()) and bool(up.any()):
            a = x0[up].mean(0) - x0[low].mean(0)
            b = X[up].mean(0) - X[low].mean(0)
            if float(a.norm()) > 1e-6 and float(b.norm()) > 1e-6:
                axis = a / a.norm()
                tilt = _rotation_between(axis, b / b.norm())
        root = kin.positions[0]
        for h in range(headings):
            turn = axis_angle_rotation(axis, torch.tensor(2.0 * math.pi * h / headings,
                                                          dtype=X.dtype))
            Rw = tilt @ turn  # world rotation applied to the posture about its root
            Rroot = Rw @ kin.rotations[0]
            th = th0.clone()
            th[sk.rotation_dofs[:3]] = _root_euler(sk, Rroot[None])[0]
            # the rotated keypoints' centroid on the observed one
            xr = (x0[seen] - root) @ Rw.t() + root
            th[sk.translation_dofs] += X[seen].mean(0) - xr.mean(0)
            theta.append(th)
    return torch.stack(theta)


def _fit_frame(aug: Skeleton, names: list[str], X: torch.Tensor, w: torch.Tensor,
               theta0: torch.Tensor, s2: float, iterations: int, reweight: int
               ) -> tuple[torch.Tensor, int]:
    """Fit one frame's observed keypoints from the starts ``theta0 (S, D)``, robustly
    reweighted ``reweight`` times; returns the best pose ``(D,)`` and the winning start."""
    seen = w > 0
    joints = [n for n, s in zip(names, seen.tolist()) if s]
    tgt = X[seen]
    res = project_to_skeleton(aug, tgt.expand(theta0.shape[0], -1, -1), theta0, joints=joints,
                              joint_weights=w[seen], iterations=iterations, tol=1e-6)
    cost = (w[seen] * _cauchy(res.residual ** 2, s2)[0]).sum(1)
    best = int(cost.argmin())
    theta = res.theta[best]
    rw = _cauchy(res.residual[best] ** 2, s2)[1]
    for _ in range(reweight):
        res = project_to_skeleton(aug, tgt[None], theta, joints=joints,
                                  joint_weights=w[seen] * rw, iterations=iterations, tol=1e-6)
        theta = res.theta[0]
        rw = _cauchy(res.residual[0] ** 2, s2)[1]
    return theta, best


def _offset_basis(sk: Skeleton, kmap: KeypointMap, hold: Mapping[str, str]
                  ) -> tuple[list[str], torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rest offsets as a linear function of a few parameters:
    ``offsets = fixed + sum_g L_g B_g``.

    The offset of a joint some mapped keypoint rides on is free (the keypoint observes where the
    joint is from its parent's keypoints); the others keep ``sk``'s. A free bone along one axis
    of its parent frame (a limb segment) has one parameter, its length; one with several
    non-zero components (human31's shoulder and toe offsets) one per component, so that e.g.
    the shoulders' width is measured apart from their height. ``hold`` keeps the named
    components of named joints (``{"l_shoulder": "z"}``). Left and right bones (``l_``/``r_``)
    share their parameters (mirrored in x).

    Returns:
        names ``(G,)``, basis ``B (G, J, 3)``, the parameters ``(G,)`` of ``sk`` itself and the
        fixed offsets ``(J, 3)``.
    """
    off = sk.offsets.detach().to(torch.float64).cpu()
    ridden = set(kmap.joint_index.tolist())
    fixed = off.clone()
    index: dict[str, int] = {}
    rows: list[torch.Tensor] = []
    values: list[float] = []
    for j, n in enumerate(sk.joint_names):
        if sk.parents[j] < 0 or j not in ridden:
            continue
        side = n[:2] in ("l_", "r_")
        nonzero = [a for a in range(3) if abs(float(off[j, a])) > 1e-9]
        comps = [a for a in nonzero if "xyz"[a] not in hold.get(n, "")]
        if len(nonzero) == 1:
            parts = [(None, off[j] / off[j].norm())] if comps else []
        else:
            parts = [("xyz"[a], torch.eye(3, dtype=torch.float64)[a]
                      * math.copysign(1.0, float(off[j, a]))) for a in comps]
        for axis, direction in parts:
            key = (n[2:] if side else n) + ("" if axis is None else f".{axis}")
            if key not in index:
                index[key] = len(rows)
                rows.append(torch.zeros(sk.num_joints, 3, dtype=torch.float64))
                values.append(float(off[j] @ direction))
            rows[index[key]][j] = direction
            fixed[j] -= (off[j] @ direction) * direction
    return list(index), torch.stack(rows), torch.tensor(values, dtype=torch.float64), fixed


class _Model:
    """Keypoints of a skeleton as functions of the poses and the offset parameters."""

    def __init__(self, sk: Skeleton, kmap: KeypointMap, basis: torch.Tensor,
                 fixed: torch.Tensor):
        self.kmap, self.basis, self.fixed = kmap, basis, fixed
        aug, names = _keypoint_skeleton(sk, kmap)
        self.aug = aug
        self.kp = torch.tensor([aug.joint_index(n) for n in names])
        self.orig = torch.tensor([aug.joint_index(n) for n in sk.joint_names])
        # (K', J): the bones on each keypoint's chain from the root to its joint
        self.chain = torch.zeros(len(kmap.names), sk.num_joints, dtype=torch.float64)
        for k, j in enumerate(kmap.joint_index.tolist()):
            while sk.parents[j] >= 0:
                self.chain[k, j] = 1.0
                j = sk.parents[j]
        self.parent = torch.tensor([max(p, 0) for p in sk.parents])

    def rest_offsets(self, params: torch.Tensor) -> torch.Tensor:
        """The skeleton's rest offsets ``(J, 3)`` for parameters ``(G,)``."""
        return self.fixed + torch.einsum("g,gjc->jc", params, self.basis)

    def offsets(self, params: torch.Tensor) -> torch.Tensor:
        """Offsets ``(J_aug, 3)`` of the keypoint skeleton for parameters ``(G,)``."""
        bone = self.rest_offsets(params)
        out = torch.zeros(self.aug.num_joints, 3, dtype=torch.float64)
        out[self.orig] = bone
        out[self.kp] = self.kmap.attachment_offsets(bone)
        return out

    def positions(self, theta: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        """Keypoints ``(T, K', 3)`` of poses ``(T, D)`` at parameters ``(G,)``."""
        return self.aug(theta, self.offsets(params), check_finite=False).positions[:, self.kp]

    def __call__(self, theta: torch.Tensor, params: torch.Tensor):
        """Keypoints ``(T, K', 3)``, their pose Jacobian ``(T, K', 3, D)`` and parameter
        Jacobian ``(T, K', 3, G)``."""
        kin, Jp, _ = self.aug.jacobian(theta, self.offsets(params))
        x = kin.positions[:, self.kp]
        R = kin.rotations[:, self.orig]  # (T, J, 3, 3) the skeleton's joints
        # d x_k / d L_g = sum over the bones j on keypoint k's chain of R[parent(j)] B_g[j]
        dirs = torch.einsum("tjab,gjb->tjag", R[:, self.parent], self.basis)  # (T, J, 3, G)
        return x, Jp[:, self.kp], torch.einsum("kj,tjag->tkag", self.chain, dirs)


class _Refinement(DampedProblem):
    """:func:`_refine`'s one problem: the poses ``(T, D)`` and offset parameters ``(G,)`` on the
    robust cost, a damped Gauss-Newton step of the IRLS-weighted normal equations (LU) with the
    box's active set held, retried with more damping until the cost drops."""

    def __init__(self, model: _Model, theta, params, X, W, prior, s2, length_prior):
        self.model, self.s2 = model, s2
        self.T, self.D = theta.shape
        self.G = params.numel()
        sk = model.aug
        self.lo, self.hi = sk.lower.double(), sk.upper.double()
        self.theta, self.params, self.theta0, self.prior = theta, params, theta.clone(), prior
        self.seen = W > 0
        self.W = W
        self.Xz = torch.where(self.seen[..., None], X, torch.zeros_like(X))
        self.lam2, self.mu2 = length_prior ** 2, _POSE_PULL ** 2
        self.current = self.cost(theta, params)
        self.relinearize(torch.ones(1, dtype=torch.bool))

    def cost(self, th, L) -> float:
        r2 = ((self.model.positions(th, L) - self.Xz) ** 2).sum(-1)
        return float((self.W * self.s2 * _cauchy(r2, self.s2)[0]).sum()
                     + self.lam2 * ((L - self.prior) ** 2).sum()
                     + self.mu2 * ((th - self.theta0) ** 2).sum())

    def relinearize(self, accepted):
        if not bool(accepted[0]):
            return
        T, D, G, seen = self.T, self.D, self.G, self.seen
        theta, params, lam2, mu2 = self.theta, self.params, self.lam2, self.mu2
        x, Jt, JL = self.model(theta, params)
        r = torch.where(seen[..., None], x - self.Xz, torch.zeros_like(x))  # (T, K', 3)
        w = self.W * _cauchy((r * r).sum(-1), self.s2)[1]  # IRLS weights (T, K')
        H = torch.zeros(T * D + G, T * D + G, dtype=torch.float64)
        g = torch.zeros(T * D + G, dtype=torch.float64)
        Htt = torch.einsum("tk,tkcd,tkce->tde", w, Jt, Jt) + mu2 * torch.eye(D, dtype=x.dtype)
        HtL = torch.einsum("tk,tkcd,tkcg->tdg", w, Jt, JL)
        for t in range(T):
            H[t * D:(t + 1) * D, t * D:(t + 1) * D] = Htt[t]
            H[t * D:(t + 1) * D, T * D:] = HtL[t]
            H[T * D:, t * D:(t + 1) * D] = HtL[t].t()
        H[T * D:, T * D:] = (torch.einsum("tk,tkcg,tkch->gh", w, JL, JL)
                             + lam2 * torch.eye(G, dtype=x.dtype))
        g[:T * D] = (torch.einsum("tk,tkc,tkcd->td", w, r, Jt)
                     + mu2 * (theta - self.theta0)).reshape(-1)
        g[T * D:] = torch.einsum("tk,tkc,tkcg->g", w, r, JL) + lam2 * (params - self.prior)
        # active set: a pose variable at a bound whose descent direction leaves the box is held
        tg = g[:T * D].reshape(T, D)
        held = (((theta <= self.lo) & (tg > 0)) | ((theta >= self.hi) & (tg < 0))).reshape(-1)
        held = torch.cat([held, torch.zeros(G, dtype=torch.bool)])
        if bool(held.any()):
            H[held] = 0.0
            H[:, held] = 0.0
            H[held, held] = 1.0
            g[held] = 0.0
        self.H, self.g, self.diag = H, g, H.diagonal().clamp_min(1e-12)

    def propose(self, mu, rows):
        TD = self.T * self.D
        step = torch.linalg.solve(self.H + mu[0] * torch.diag(self.diag), -self.g)
        th_new = torch.maximum(torch.minimum(self.theta + step[:TD].reshape(self.T, self.D),
                                             self.hi), self.lo)
        L_new = torch.maximum(self.params + step[TD:], 0.5 * self.prior)
        return th_new, L_new, self.cost(th_new, L_new)

    def assess(self, trial, mu, rows):
        th_new, L_new, new = trial
        ok = new < self.current
        stop = False
        if ok:
            moved = max(float((th_new - self.theta).abs().max()),
                        float((L_new - self.params).abs().max()))
            gain = (self.current - new) / self.current
            stop = moved < _STEP_TOL or gain < _GAIN_TOL
        return Verdict(accepted=torch.tensor([ok]), stop=torch.tensor([stop]))

    def commit(self, trial, accepted, rows):
        if bool(accepted[0]):
            self.theta, self.params, self.current = trial

    def retire(self, done, ids):
        pass  # one problem: its result is the current point

    def keep(self, mask):
        pass


def _refine(model: _Model, theta: torch.Tensor, params: torch.Tensor, X: torch.Tensor,
            W: torch.Tensor, prior: torch.Tensor, s2: float, length_prior: float,
            iterations: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Joint Levenberg-Marquardt refinement of the poses ``(T, D)`` and offset parameters ``(G,)``
    on the robust cost (module docstring, step 3). Returns both and the iterations run."""
    prob = _Refinement(model, theta, params, X, W, prior, s2, length_prior)
    run = damped_least_squares(prob, 1, iterations, Marquardt(initial=1e-3, stall=1e8),
                               retry=True)
    return prob.theta, prob.params, run.iterations


# ----------------------------------------------------------------------------- entry point
def fit_keypoint_subject(
    points: torch.Tensor,
    weights: torch.Tensor | None = None,
    keypoint_map: str | Path | KeypointMap = "body_25b",
    keypoint_names: Sequence[str] | None = None,
    base: Skeleton | None = None,
    headings: int = 8,
    postures: Sequence[Mapping[str, float]] = ({}, SEATED),
    refine_iterations: int = 50,
    robust_scale: float = 0.05,
    length_prior: float = 0.1,
    hold: Mapping[str, str] | None = None,
    iterations: int = 100,
    seed: int = 0,
) -> KeypointFit:
    """Fit the subject's bone lengths and first poses to triangulated keypoints.

    Args:
        points: ``(T0, K, 3)`` world keypoints (metres, Z up), NaN where not triangulated.
        weights: ``(T0, K)`` weights >= 0 (e.g. the mean confidence of the views that
            triangulated each point; 0 = unused); default 1 wherever the point is finite.
        keypoint_map: format name, map YAML path, or a :class:`~torchmocap.skeleton.KeypointMap`.
        keypoint_names: the ``K`` column names of ``points`` (default: the format's order).
        base: template skeleton with the map's joint names (default: the map's preset, human31).
        headings: start headings per posture (turns about the trunk axis); ``1`` starts facing
            the template's way only.
        postures: start postures, each ``{dof name: degrees}`` added to the zero pose (default:
            standing and :data:`SEATED`).
        refine_iterations: iterations of the joint refinement of bone lengths and poses (0:
            the scaled template's lengths).
        robust_scale: Cauchy scale (m) of the keypoint residuals.
        length_prior: pull (keypoint metres per metre) of each offset parameter towards the
            scaled template: decides what no keypoint observes.
        hold: ``{joint: axes}`` offset components kept at the scaled template's (default:
            :data:`TRUNK_HOLD` for the joints the skeleton has).
        iterations: Levenberg-Marquardt iterations per solve.
        seed: seed of the random poses that find the pose-invariant keypoint pairs.

    Returns:
        :class:`KeypointFit`, computed in float64 on the CPU (a few frames, once per
        recording), wherever ``points`` lie.

    Raises:
        ValueError: bad shapes or values (named), a frame with fewer than 4 usable keypoints,
            an unknown posture DoF.
        KeypointMapError: mapped keypoints missing from ``keypoint_names``.
    """
    if not isinstance(points, torch.Tensor) or points.dim() != 3 or points.shape[-1] != 3:
        shape = tuple(points.shape) if isinstance(points, torch.Tensor) else type(points).__name__
        raise ValueError(f"points: expected shape (T0, K, 3), got {shape}")
    T, K, _ = points.shape
    if T < 1:
        raise ValueError("points: expected at least one frame")
    X = points.detach().to(torch.float64).cpu()
    finite = torch.isfinite(X).all(-1)
    if weights is None:
        W = finite.to(torch.float64)
    else:
        if not isinstance(weights, torch.Tensor) or weights.shape != (T, K):
            shape = (tuple(weights.shape) if isinstance(weights, torch.Tensor)
                     else type(weights).__name__)
            raise ValueError(f"weights: expected shape ({T}, {K}), got {shape}")
        W = weights.detach().to(torch.float64).cpu()
        if not bool(torch.isfinite(W).all()) or bool((W < 0).any()):
            raise ValueError("weights: expected finite values >= 0")
        W = torch.where(finite, W, torch.zeros_like(W))
    for name, v, ok in (("headings", headings, isinstance(headings, int) and headings >= 1),
                        ("refine_iterations", refine_iterations,
                         isinstance(refine_iterations, int) and refine_iterations >= 0),
                        ("iterations", iterations, isinstance(iterations, int)
                         and iterations >= 1)):
        if isinstance(v, bool) or not ok:
            raise ValueError(f"{name}: expected a positive int, got {v!r}")
    for name, v in (("robust_scale", robust_scale), ("length_prior", length_prior)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    kmap = load_keypoint_map(keypoint_map, base)
    base = (base if base is not None else _preset_of(kmap)).to(torch.float64)
    names = list(kmap.format_keypoints) if keypoint_names is None else list(keypoint_names)
    if len(names) != K:
        raise ValueError(f"keypoint_names: {len(names)} names for {K} point columns")
    cols = kmap.columns(names)
    X, W = X[:, cols], W[:, cols]  # (T, K', 3), (T, K')
    few = [t for t in range(T) if int((W[t] > 0).sum()) < _MIN_KEYPOINTS]
    if few:
        raise ValueError(f"points: frames {few} have fewer than {_MIN_KEYPOINTS} usable mapped "
                         "keypoints")
    W = W / W[W > 0].mean()
    pose_offsets = []
    for p in postures:
        th = base.zero_pose(dtype=torch.float64)
        for dof, deg in dict(p).items():
            if dof not in base.dof_names:
                raise ValueError(f"postures: unknown DoF {dof!r}; known: {base.dof_names}")
            th[base.dof_index(dof)] = math.radians(float(deg))
        pose_offsets.append(base.clamp(th))
    if not pose_offsets:
        raise ValueError("postures: expected at least one start posture")
    if hold is None:
        hold = {j: a for j, a in TRUNK_HOLD.items() if j in base.joint_names}
    bad = [j for j, a in dict(hold).items() if j not in base.joint_names
           or not isinstance(a, str) or set(a) - set("xyz")]
    if bad:
        raise ValueError(f"hold: expected {{joint of the skeleton: axes among 'xyz'}}, got "
                         f"{ {j: hold[j] for j in bad} }")
    s2 = float(robust_scale) ** 2
    gen = torch.Generator().manual_seed(int(seed))

    # -- 1. body scale
    scale, ratios = _scale(X, W, base, kmap, gen)
    sk = base.with_bone_lengths(scale=scale)
    kmap = dataclasses.replace(kmap.bind(sk), offsets=kmap.offsets * scale)
    pnames, basis, prior, fixed = _offset_basis(sk, kmap, hold)

    # -- 2. first poses from several starts, robustly reweighted
    aug, kp_names = _keypoint_skeleton(sk, kmap)
    theta = torch.empty(T, base.num_dofs, dtype=torch.float64)
    won = []
    for t in range(T):
        starts = _starts(sk, kmap, X[t], W[t] > 0, pose_offsets, headings)
        theta[t], b = _fit_frame(aug, kp_names, X[t], W[t], starts, s2, iterations, 2)
        won.append(b)

    # -- 3. bone lengths and poses together
    params, done = prior, 0
    if refine_iterations:
        model = _Model(sk, kmap, basis, fixed)
        theta, params, done = _refine(model, theta, prior.clone(), X, W, prior, s2,
                                      length_prior, refine_iterations)
        spec = sk.to_dict()
        for jd, o in zip(spec["joints"], model.rest_offsets(params).tolist()):
            jd["offset"] = o
        sk = Skeleton.from_dict(spec).to(torch.float64)
        kmap = kmap.bind(sk)

    kin = sk(theta)
    fitted = keypoint_positions(kin.positions, kin.rotations, kmap)
    r = (fitted - X).norm(dim=-1)
    residual = torch.where(W > 0, r, torch.full_like(r, float("nan")))
    cost = (W * _cauchy(torch.nan_to_num(residual) ** 2, s2)[0]).sum(1)
    return KeypointFit(
        skeleton=sk, keypoint_map=kmap, theta=theta, residual=residual, cost=cost,
        scale=scale, lengths=sk.bone_lengths(),
        info={"starts": len(pose_offsets) * headings, "start_index": torch.tensor(won),
              "refine_iterations": done, "scale_pairs": ratios,
              "offset_parameters": dict(zip(pnames, params.tolist()))})


def _preset_of(kmap: KeypointMap) -> Skeleton:
    from torchmocap.skeleton.presets import PRESETS, preset

    for name in PRESETS:
        sk = preset(name)
        if tuple(sk.joint_names) == kmap.skeleton_joints:
            return sk
    raise ValueError("base: the keypoint map's skeleton is not a preset; pass base")
