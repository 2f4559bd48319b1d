"""Subject fitting: a human31 body with the clip's bone lengths and per-frame ground truth.

From a :class:`~torchmocap.io.MotionClip` of any mapped skeleton family:

1. *Exact ground truth* from the source: world positions of the mapped human31 joints and world
   orientations of the mapped bones.
2. *Bone lengths*: limb lengths are the per-frame medians of the source joint distances (left and
   right averaged); torso, head and foot offsets are re-estimated as 3-vectors in the parent's
   frame (the source's shoulder, hip and toe placement differs from the template's direction).
3. *Closest human31 angles* per frame by batched Levenberg-Marquardt
   (:func:`torchmocap.ik.lm.fit_pose_lm`): first on positions, then on positions plus bone
   orientations after calibrating each bone's constant rest-frame difference between source and
   human31 (``C_b = mean_t R_src,b(t)^T R_h31,b(t)``, projected onto SO(3)); the orientation term
   fixes the twists that positions cannot see (upper arm with a straight elbow, ...).
4. *Continuation in time* after the last stage: every frame is re-fitted from its neighbours'
   solutions and keeps whichever fit is closer to the source; frames that improved pass their
   solution on, until none improves. Every frame starts from the same standing template, and in
   large excursions (arms swung overhead, a deep squat) that start can lead
   Levenberg-Marquardt into a wrong minimum (e.g. hips flexed backwards, knees straight: up to
   0.2 m residuals); the neighbouring frames' solutions lead it into the right one.

The per-frame residual (mean joint distance, metres) is reported; it is what the human31 model
cannot express of the real motion.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchmocap.ik.lm import LMResult, fit_pose_lm
from torchmocap.skeleton import Skeleton, human31

__all__ = ["Subject", "fit_subject"]

# Joints whose offset is estimated as a full vector (parent frame); the others keep the template
# direction and only take the measured length (limb segments: zero angle = straight limb).
_VECTOR_OFFSETS = ("spine", "neck", "head", "head_top", "l_shoulder", "r_shoulder", "l_hip",
                   "r_hip", "l_toe", "r_toe")
_MIRROR = {"l_": "r_", "r_": "l_"}


@dataclass
class Subject:
    """A fitted subject and its ground truth.

    Attributes:
        skeleton: human31 with the subject's bone geometry.
        theta: ``(T, D)`` closest human31 poses.
        positions: ``(T, J, 3)`` exact source positions of the human31 joints (skeleton order).
        rotations: ``(T, J, 3, 3)`` exact source bone orientations expressed in the human31 bone
            frames (``R_src,b C_b``) for mapped bones; fitted frames elsewhere.
        mapped_bones: names of the joints whose ``rotations`` come from the source.
        residual: ``(T,)`` mean distance (m) between fitted and source joints per frame.
        rotation_residual: ``(T,)`` mean angle (rad) between fitted and source bone frames.
        fps: frame rate.
        family: skeleton family of the source (``None`` when the joints were guessed).
        info: ``lm_iterations``; ``continuation`` (``passes``, ``frames_refitted``: the frames
            whose fit the continuation in time replaced); ``joint_map`` (human31 joint ->
            source joint) and ``guessed_joints`` (the human31 joints whose source was guessed
            from the joint names because no skeleton map applies; empty with a map).
    """

    skeleton: Skeleton
    theta: torch.Tensor
    positions: torch.Tensor
    rotations: torch.Tensor
    mapped_bones: list[str]
    residual: torch.Tensor
    rotation_residual: torch.Tensor
    fps: float
    family: str | None = None
    info: dict = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.theta.shape[0])


def _project_so3(M: torch.Tensor) -> torch.Tensor:
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    S = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return U @ S @ Vh


def _root_init(P: torch.Tensor, sk: Skeleton) -> torch.Tensor:
    """Root translation and z-x-y Euler angles from the hips and the spine direction."""
    j = sk.joint_index
    x = P[:, j("l_hip")] - P[:, j("r_hip")]
    up = P[:, j("neck")] - P[:, j("pelvis")]
    z = torch.nn.functional.normalize(up, dim=-1)
    x = torch.nn.functional.normalize(x - (x * z).sum(-1, keepdim=True) * z, dim=-1)
    y = torch.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], -1)  # columns: body axes in the world (rest: identity)
    # human31 root axes are z, x, y: R = Rz(a) Rx(b) Ry(c)
    b = torch.asin(R[:, 2, 1].clamp(-1, 1))
    c = torch.atan2(-R[:, 2, 0], R[:, 2, 2])
    a = torch.atan2(-R[:, 0, 1], R[:, 1, 1])
    theta = torch.zeros(P.shape[0], sk.num_dofs, dtype=P.dtype)
    theta[:, :3] = P[:, j("pelvis")] - sk.offsets[0].to(P.dtype)
    theta[:, 3], theta[:, 4], theta[:, 5] = a, b, c
    return theta


def _data_cost(fit, rotation_weight: float) -> torch.Tensor:
    """``(B,)`` squared distance to the source (positions, plus weighted orientations): the
    cost without the pull towards the start, comparable between fits from different starts."""
    c = (fit.position_error ** 2).sum(1)
    if fit.rotation_error is not None:
        c = c + rotation_weight ** 2 * (fit.rotation_error ** 2).sum(1)
    return c


def _continue_in_time(fit, refit, rotation_weight: float, min_gain: float = 0.002,
                      max_passes: int | None = None):
    """Continuation of a per-frame fit along time.

    Every frame is re-fitted from the solutions of its two neighbours (one batch); a frame keeps
    the new fit when its root-mean-square distance to the source (per targeted joint, the
    weighted orientation errors included) drops by more than ``min_gain`` metres: another
    minimum, not the same one fitted a little further (those differ by far less). The frames that
    improved are the sources of the next pass, for their neighbours only, until no frame
    improves (a wrong stretch of ``k`` frames is repaired in about ``k`` passes).

    Args:
        fit: the :class:`~torchmocap.ik.lm.LMResult` of all ``T`` frames.
        refit: ``refit(theta0 (N, D), frames (N,)) -> LMResult`` fits the given frames from
            the given starts.
        rotation_weight: weight of the orientation errors in the compared cost.
        min_gain: decrease of the RMS distance (metres) a new fit must reach to replace the
            old one.
        max_passes: cap on the passes (default: ``T``).

    Returns:
        ``(theta (T, D), position_error (T, M), rotation_error (T, K) | None, passes,
        frames_changed)``.
    """
    theta = fit.theta.clone()
    pe = fit.position_error.clone()
    re = None if fit.rotation_error is None else fit.rotation_error.clone()
    cost = _data_cost(fit, rotation_weight)
    T, M = pe.shape
    if T < 2:
        return theta, pe, re, 0, 0
    t = torch.arange(T)
    src = torch.cat([t[:-1], t[1:]])  # pass 1: every frame from both neighbours
    dst = torch.cat([t[1:], t[:-1]])
    changed = torch.zeros(T, dtype=torch.bool)
    passes = 0
    while src.numel() and passes < (max_passes or T):
        passes += 1
        new = refit(theta[src], dst)
        c = _data_cost(new, rotation_weight)
        best = torch.full((T,), torch.inf, dtype=c.dtype).scatter_reduce(0, dst, c, "amin")
        gain = (cost[dst] / M).sqrt() - (c / M).sqrt()
        win = torch.nonzero((c == best[dst]) & (gain > min_gain)).squeeze(1)
        if not win.numel():
            break
        # one candidate per improved frame (a tie between the two neighbours: the first)
        k = torch.full((T,), src.numel(), dtype=torch.long).scatter_reduce(
            0, dst[win], win, "amin")
        frames = torch.nonzero(k < src.numel()).squeeze(1)
        k = k[frames]
        theta[frames] = new.theta[k]
        pe[frames] = new.position_error[k]
        if re is not None:
            re[frames] = new.rotation_error[k]
        cost[frames] = c[k]
        changed[frames] = True
        left, right = frames[frames > 0], frames[frames < T - 1]
        src = torch.cat([left, right])
        dst = torch.cat([left - 1, right + 1])
    return theta, pe, re, passes, int(changed.sum())


def _continued(fit, refit, rotation_weight: float):
    """:func:`_continue_in_time` as an :class:`~torchmocap.ik.lm.LMResult`, and its
    ``(passes, frames_changed)``."""
    theta, pe, re, passes, changed = _continue_in_time(fit, refit, rotation_weight)
    out = LMResult(theta=theta, position_error=pe, rotation_error=re, cost=fit.cost,
                   iterations=fit.iterations)
    out.cost = _data_cost(out, rotation_weight)  # the cost to the source, without the pull
    return out, (passes, changed)


def _symmetric(values: dict[str, torch.Tensor], mirror_x: bool) -> dict[str, torch.Tensor]:
    out = dict(values)
    for name, v in values.items():
        if name[:2] in _MIRROR:
            other = _MIRROR[name[:2]] + name[2:]
            if other in values:
                w = values[other].clone() if mirror_x else values[other]
                if mirror_x:
                    w[..., 0] = -w[..., 0]
                out[name] = 0.5 * (v + w)
    return out


def fit_subject(
    clip,
    skeleton_map=None,
    base: Skeleton | None = None,
    iterations: int = 40,
    rotation_weight: float = 0.1,
    prior_weight: float = 1e-3,
    dtype: torch.dtype = torch.float64,
) -> Subject:
    """Fit human31 (or ``base``, with human31 joint names) to ``clip``.

    Args:
        clip: a :class:`~torchmocap.io.MotionClip` whose family has a skeleton map.
        skeleton_map: map name or YAML path (default: the clip's detected family).
        base: template skeleton (default :func:`~torchmocap.skeleton.human31`).
        iterations: LM iterations per stage.
        rotation_weight: metres per radian of the bone-orientation residuals (stage 2).
        prior_weight: pull towards the previous stage's pose (keeps unobservable DoF still).
    """
    from torchmocap.io.skeleton_maps import guessed_joints, map_joints, resolve_skeleton_map

    if clip.num_frames < 1:
        raise ValueError("clip: expected at least one frame, got an empty clip")
    base = (base or human31()).to(dtype)
    idx = map_joints(clip, skeleton_map)
    smap = resolve_skeleton_map(clip, skeleton_map)
    names = base.joint_names
    missing = [n for n in names if n not in idx]
    if missing:
        raise KeyError(f"base skeleton joints {missing} have no source joint in the map")
    clip = clip.to(dtype)
    Psrc = clip.global_positions()
    Rsrc = clip.global_rotations()
    P = Psrc[:, [idx[n] for n in names]]  # (T, J, 3) exact ground truth
    T = P.shape[0]

    # -- stage 0: bone lengths (medians over frames, left/right averaged)
    lengths = {}
    for j, n in enumerate(names):
        q = base.parents[j]
        if q >= 0:
            lengths[n] = (P[:, j] - P[:, q]).norm(dim=-1).median()
    lengths = _symmetric(lengths, mirror_x=False)
    sk = base.with_bone_lengths({n: float(v) for n, v in lengths.items()}).to(dtype)

    joints = list(range(len(names)))
    theta0 = _root_init(P, sk)
    fit = fit_pose_lm(sk, theta0, P, joints, iterations=iterations, prior_weight=prior_weight)

    # -- stage 1: offsets of torso/head/foot joints as vectors in the fitted parent frames
    kin = sk(fit.theta)
    offsets = sk.offsets.detach().clone()
    vec = {}
    for n in _VECTOR_OFFSETS:
        j = sk.joint_index(n)
        q = sk.parents[j]
        local = (kin.rotations[:, q].transpose(-1, -2) @ (P[:, j] - P[:, q])[..., None])[..., 0]
        vec[n] = local.median(dim=0).values
    vec = _symmetric(vec, mirror_x=True)
    for n, v in vec.items():
        offsets[sk.joint_index(n)] = v
    spec = sk.to_dict()
    for jd, off in zip(spec["joints"], offsets.tolist()):
        jd["offset"] = off
    sk = Skeleton.from_dict(spec).to(dtype)
    fit = fit_pose_lm(sk, fit.theta, P, joints, iterations=iterations, prior_weight=prior_weight)

    # -- stage 2: calibrate source bone frames, then fit positions + orientations
    bones = [b for b in (smap.bones if smap is not None else {}) if b in names]
    kin = sk(fit.theta)
    R_gt = kin.rotations.detach().clone()
    rot_res = torch.zeros(T, dtype=dtype)
    if bones:
        bj = [sk.joint_index(b) for b in bones]
        src = Rsrc[:, [clip.joint_index(smap.bones[b]) for b in bones]]  # (T, K, 3, 3)
        C = _project_so3((src.transpose(-1, -2) @ kin.rotations[:, bj]).mean(0))  # (K, 3, 3)
        target = src @ C

        def refit(th, fr):
            return fit_pose_lm(sk, th, P[fr], joints, target_rotations=target[fr],
                               rotation_joints=bj, rotation_weight=rotation_weight,
                               iterations=iterations, prior_weight=prior_weight)
        fit = refit(fit.theta, torch.arange(T))
    else:
        def refit(th, fr):
            return fit_pose_lm(sk, th, P[fr], joints, iterations=iterations,
                               prior_weight=prior_weight)
    # -- continuation in time: frames in a wrong minimum take a neighbour's way out
    fit, cont = _continued(fit, refit, rotation_weight)
    if bones:
        R_gt[:, bj] = target
        rot_res = fit.rotation_error.mean(1)
    return Subject(
        skeleton=sk,
        theta=fit.theta,
        positions=P,
        rotations=R_gt,
        mapped_bones=bones,
        residual=fit.position_error.mean(1),
        rotation_residual=rot_res,
        fps=float(clip.fps),
        family=getattr(smap, "family", None),
        info={"lm_iterations": fit.iterations,
              "continuation": {"passes": cont[0], "frames_refitted": cont[1]},
              "guessed_joints": guessed_joints(clip, skeleton_map),
              "joint_map": {h: clip.joint_names[i] for h, i in idx.items()}},
    )
