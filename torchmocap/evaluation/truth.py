"""Scores of a track against ground truth: validation orientation error (Pons-Moll eq. 19),
MPJPE (global and root-aligned), held degrees of freedom, marker-to-skin error (Hauberg &
Pedersen eq. 16), the hypotheses of multi-hypothesis inferences, and whether the likelihood's
optimum is the truth.

Every function scores frames ``1..T-1`` (frame 0 is every tracker's given start). Shapes: ``T``
frames, ``D`` DoFs, ``J`` joints, ``K`` hypotheses.
"""

from __future__ import annotations

import math
import warnings

import torch

from torchmocap.evaluation.warnings import EvaluationWarning
from torchmocap.geometry import wrap_angle

__all__ = [
    "HELD_WARN_ROTATION",
    "HELD_WARN_TRANSLATION",
    "VALIDATION_BONES_FALLBACK",
    "energy_below_truth",
    "error_means",
    "held_dofs",
    "hypothesis_errors",
    "marker_error",
    "root_joint",
    "track_errors",
    "validation_bones",
]

#: Validation bones when the sequence has no validation IMUs (Pons-Moll's five).
VALIDATION_BONES_FALLBACK = ["spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"]
#: the truth's motion of the DoFs a tracker holds that makes :func:`held_dofs` warn (m, degrees)
HELD_WARN_TRANSLATION, HELD_WARN_ROTATION = 0.25, 30.0
#: the summary keys :func:`error_means` keeps
ERROR_KEYS = ("orientation_error_deg", "mpjpe_mm", "mpjpe_root_relative_mm")


def validation_bones(seq) -> list[str]:
    """The bones whose orientation error is reported: the sequence's validation IMUs (those not
    used for tracking), else :data:`VALIDATION_BONES_FALLBACK`."""
    if seq.imu is not None:
        val = [b for b, t in zip(seq.imu.bones, seq.imu.tracking.tolist()) if not t]
        if val:
            return val
    return list(VALIDATION_BONES_FALLBACK)


def root_joint(skeleton) -> int:
    """Index of the skeleton's root joint (the one without a parent)."""
    return next(j for j, p in enumerate(skeleton.parents) if p < 0)


def track_errors(seq, skeleton, theta: torch.Tensor) -> dict:
    """Validation orientation error (eq. 19) and MPJPE of frames 1..T-1 against the truth.

    Args:
        seq: a :class:`~torchmocap.data.Sequence` with ground truth.
        skeleton: the tracking :class:`~torchmocap.skeleton.Skeleton`.
        theta: ``(T, D)`` the track.

    Returns:
        ``{"summary": {validation_bones, orientation_error_deg {mean, std, per_bone, per_frame,
        per_bone_frame}, mpjpe_mm {mean, std, per_frame}, mpjpe_root_relative_mm {...}},
        "theta_gt" (T, D), "orientation_error_deg" (T-1, B), "mpjpe_mm" (T-1,)}``.
    """
    from torchmocap.metrics import mpjpe_mm, orientation_error_deg, summarize_errors

    gt = seq.ground_truth
    if gt is None:
        raise ValueError("seq: scoring against the truth needs a sequence with ground truth")
    val = validation_bones(seq)
    kin = skeleton(theta)
    vb = [skeleton.joint_index(b) for b in val]
    ori = orientation_error_deg(kin.rotations[1:, vb], gt.rotations[1:, vb].float())
    mp = mpjpe_mm(kin.positions[1:], gt.positions[1:].float())
    mp_root = mpjpe_mm(kin.positions[1:], gt.positions[1:].float(), root=root_joint(skeleton))
    summary = {"validation_bones": val, **summarize_errors(ori, val, mp, mp_root)}
    summary["orientation_error_deg"]["per_frame"] = [round(float(v), 4) for v in ori.mean(1)]
    summary["orientation_error_deg"]["per_bone_frame"] = {
        b: [round(float(v), 4) for v in ori[:, k]] for k, b in enumerate(val)}
    summary["mpjpe_mm"]["per_frame"] = [round(float(v), 3) for v in mp]
    summary["mpjpe_root_relative_mm"]["per_frame"] = [round(float(v), 3) for v in mp_root]
    return {"summary": summary, "theta_gt": gt.theta, "orientation_error_deg": ori,
            "mpjpe_mm": mp}


def error_means(summary: dict) -> dict[str, float]:
    """The mean orientation error, MPJPE and root-aligned MPJPE of a :func:`track_errors`
    summary (the short form of a baseline or a smoother stage)."""
    return {k: summary[k]["mean"] for k in ERROR_KEYS}


def held_dofs(seq, skeleton, theta: torch.Tensor) -> dict | None:
    """The DoFs the track never moved from the first frame (an upper-body tracker's torso and
    legs, say) and how far the truth moves them over the clip; ``None`` when every DoF moved.
    Warns (:class:`EvaluationWarning`) when the truth moves them far: the errors of such a run
    measure the held DoFs, not the tracker."""
    # (a weighted mean of equal values may differ from them in the last bits)
    held = torch.isclose(theta, theta[:1], rtol=1e-5, atol=1e-6).all(0)
    if not bool(held.any()):
        return None
    sk = skeleton
    gt = seq.ground_truth.theta.to(theta.dtype).cpu()
    trans = [d for d in sk.translation_dofs if held[d]]
    rot = [d for d in range(sk.num_dofs) if held[d] and d not in sk.translation_dofs]
    move = float((gt[:, trans] - gt[:1, trans]).norm(dim=-1).amax()) if trans else 0.0
    turn = wrap_angle(gt[:, rot] - gt[:1, rot])
    turn = turn.abs().amax(0) if rot else torch.zeros(0)
    deg = [math.degrees(float(v)) for v in turn]
    worst = sorted((k for k in range(len(rot)) if deg[k] > HELD_WARN_ROTATION),
                   key=lambda k: -deg[k])[:3]
    out = {"count": int(held.sum()), "truth_max_translation_m": move,
           "truth_max_rotation_deg": max(deg, default=0.0)}
    if move > HELD_WARN_TRANSLATION or worst:
        what = [f"the root moves {move:.2f} m"] if move > HELD_WARN_TRANSLATION else []
        what += [f"{sk.dof_names[rot[k]]} turns {deg[k]:.0f} deg" for k in worst]
        hint = "a Hauberg preset tracks the whole body with tracker.proposal.joints=all"
        if move > HELD_WARN_TRANSLATION:
            hint += "; data.clip.in_place=true keeps the subject at its start"
        warnings.warn(f"the tracker held {out['count']} DoFs at the first frame's pose (e.g. an "
                      f"upper-body tracker's torso), but in this clip {', '.join(what)}; the "
                      f"errors measure that, not the tracking ({hint})", EvaluationWarning,
                      stacklevel=2)
    return out


def marker_error(seq, body, skeleton, theta: torch.Tensor) -> dict:
    """Eq. 16 of Hauberg & Pedersen: distance (mm) of the true skin markers to the estimated
    capsule skin, frames 1..T-1: ``{mean, per_frame, per_part}``."""
    from torchmocap.metrics import marker_skin_distance

    d = marker_skin_distance(seq.ground_truth.markers[1:],
                             body.endpoints(skeleton(theta[1:])), body.radii) * 1000
    per_part: dict[str, list] = {}
    for k, p in enumerate(seq.ground_truth.marker_parts):
        per_part.setdefault(p, []).append(k)
    return {"mean": float(d.mean()), "per_frame": [round(float(v), 3) for v in d.mean(1)],
            "per_part": {p: float(d[:, ks].mean()) for p, ks in per_part.items()}}


def hypothesis_errors(seq, skeleton, infos: list) -> dict:
    """MPJPE (global and root-aligned) of the top-weighted and of the best of the hypotheses a
    multi-hypothesis inference keeps per frame (``FrameInfo.hypotheses`` and
    ``hypothesis_weights``), and their count; ``{}`` when no frame keeps hypotheses."""
    from torchmocap.metrics import mpjpe_mm

    top, best, top_root, best_root, modes = [], [], [], [], []
    root = root_joint(skeleton)
    for t, info in enumerate(infos):
        if t == 0 or not info.hypotheses:
            continue
        H = torch.as_tensor(info.hypotheses, dtype=torch.float32)
        w = torch.as_tensor(info.hypothesis_weights or [1.0] * H.shape[0])
        truth = seq.ground_truth.positions[t].float()
        pos, ref = skeleton(H).positions, truth.expand(H.shape[0], -1, -1)
        err = mpjpe_mm(pos, ref)
        err_root = mpjpe_mm(pos, ref, root=root)
        k = int(torch.argmax(w))
        top.append(float(err[k]))
        best.append(float(err.min()))
        top_root.append(float(err_root[k]))
        best_root.append(float(err_root.min()))
        modes.append(int(H.shape[0]))
    if not top:
        return {}

    def stats(v):
        return {"mean": sum(v) / len(v), "per_frame": [round(x, 3) for x in v]}

    return {"mpjpe_top_mm": stats(top), "mpjpe_best_mm": stats(best),
            "mpjpe_root_relative_top_mm": stats(top_root),
            "mpjpe_root_relative_best_mm": stats(best_root),
            "modes": {"mean": sum(modes) / len(modes), "per_frame": modes}}


def energy_below_truth(tracker, seq, theta: torch.Tensor) -> float:
    """Fraction of frames whose estimate has a lower energy (the tracker's own likelihood)
    than the true pose: > 0 means the likelihood's optimum is not the truth there."""
    tracking = None if seq.imu is None else seq.imu.tracking.nonzero()[:, 0]
    below = []
    for t in range(1, seq.num_frames):
        energy = tracker.frame_energy(tracker.observe(seq.frame(t), tracking))
        with torch.no_grad():
            v = energy(torch.stack([seq.ground_truth.theta[t].to(theta.dtype), theta[t]]))
        below.append(bool(v[1] < v[0]))
    return sum(below) / max(len(below), 1)
