"""What a reconstruction must satisfy without ground truth: constant bone lengths and smooth
motion (REFERENCE §11).

- :func:`bone_length_cv`: the coefficient of variation (standard deviation / mean, in percent)
  of each bone's length over the frames — 0 for a rigid skeleton; per-frame triangulation of
  keypoints gives several percent (Pose2Sim's own 4-view output of ``pose2sim_balancing``:
  3.8-10.1 % per limb bone raw).
- :func:`jitter`: the mean magnitude of the positions' second difference times ``fps^2``
  (m/s^2): the acceleration a trajectory implies; detector noise shows as large values.

The standard deviation is the population one (divided by the number of frames). Frames where
a bone's end (or a joint in a second difference) is not finite are left out of that bone's (or
joint's) statistics.

Shapes: ``T`` frames, ``J`` joints (or keypoints), ``B`` bones.

Example:
    >>> x = torch.zeros(5, 2, 3)
    >>> x[:, 1, 2] = torch.tensor([1.0, 1.1, 0.9, 1.0, 1.0])
    >>> round(bone_length_cv(x, [(0, 1)]).mean_percent, 2)
    6.32
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

__all__ = ["LIMB_KEYPOINTS", "BoneLengthCV", "Jitter", "bone_length_cv", "jitter",
           "track_consistency"]

#: the limb segments between detector keypoints whose lengths a triangulation peer reports
LIMB_KEYPOINTS = (("RHip", "RKnee"), ("RKnee", "RAnkle"), ("LHip", "LKnee"), ("LKnee", "LAnkle"),
                  ("RShoulder", "RElbow"), ("RElbow", "RWrist"), ("LShoulder", "LElbow"),
                  ("LElbow", "LWrist"))


@dataclass
class BoneLengthCV:
    """Bone-length constancy.

    Attributes:
        cv_percent: ``(B,)`` coefficient of variation of each bone's length (%), NaN for a
            bone measured in no frame.
        mean_percent: mean of ``cv_percent`` over the measured bones.
        mean_length: ``(B,)`` mean length of each bone (m).
        frames: ``(B,)`` frames each bone was measured in.
    """

    cv_percent: torch.Tensor
    mean_percent: float
    mean_length: torch.Tensor
    frames: torch.Tensor


@dataclass
class Jitter:
    """Mean acceleration magnitude.

    Attributes:
        mean: mean of ``|x[t+1] - 2 x[t] + x[t-1]| fps^2`` over joints and frames (m/s^2).
        per_joint: ``(J,)`` the same per joint (NaN for a joint without a finite triple).
        per_frame: ``(T - 2,)`` the same per middle frame ``t = 1 .. T-2``.
    """

    mean: float
    per_joint: torch.Tensor
    per_frame: torch.Tensor


def _check_positions(positions, min_frames: int) -> None:
    if not isinstance(positions, torch.Tensor) or positions.dim() != 3 \
            or positions.shape[-1] != 3:
        shape = tuple(positions.shape) if isinstance(positions, torch.Tensor) else type(positions)
        raise ValueError(f"positions: expected shape (T, J, 3), got {shape}")
    if positions.shape[0] < min_frames:
        raise ValueError(f"positions: expected at least {min_frames} frames, got "
                         f"{positions.shape[0]}")


def bone_length_cv(positions: torch.Tensor, bones: Sequence[tuple[int | str, int | str]],
                   joint_names: Sequence[str] | None = None) -> BoneLengthCV:
    """Coefficient of variation of each bone's length over the frames.

    Args:
        positions: ``(T, J, 3)`` joint or keypoint positions (metres; NaN where missing).
        bones: ``B`` pairs ``(a, b)`` of joint indices, or of names with ``joint_names``.
        joint_names: the ``J`` names of ``positions``' joints (to give bones by name).

    Returns:
        :class:`BoneLengthCV`.

    Raises:
        ValueError: bad shapes, an unknown joint name or an index out of range.
    """
    _check_positions(positions, 1)
    J = positions.shape[1]
    if not bones:
        raise ValueError("bones: expected at least one (a, b) pair")
    index = {n: i for i, n in enumerate(joint_names or [])}
    pairs = []
    for pair in bones:
        if len(pair) != 2:
            raise ValueError(f"bones: expected (a, b) pairs, got {pair!r}")
        ids = []
        for x in pair:
            if isinstance(x, str):
                if x not in index:
                    raise ValueError(f"bones: unknown joint {x!r} (joint_names: "
                                     f"{list(joint_names or [])})")
                ids.append(index[x])
            elif isinstance(x, bool) or not isinstance(x, int) or not 0 <= x < J:
                raise ValueError(f"bones: joint index {x!r} out of range for {J} joints")
            else:
                ids.append(x)
        pairs.append(ids)
    idx = torch.tensor(pairs, dtype=torch.long, device=positions.device)
    length = (positions[:, idx[:, 0]] - positions[:, idx[:, 1]]).norm(dim=-1)  # (T, B)
    ok = torch.isfinite(length)
    n = ok.sum(0)
    L = torch.where(ok, length, torch.zeros_like(length))
    mean = L.sum(0) / n.clamp_min(1)
    var = torch.where(ok, (L - mean) ** 2, torch.zeros_like(L)).sum(0) / n.clamp_min(1)
    cv = torch.where(n > 0, 100.0 * var.sqrt() / mean, torch.full_like(mean, float("nan")))
    mean = torch.where(n > 0, mean, torch.full_like(mean, float("nan")))
    measured = cv[n > 0]
    return BoneLengthCV(cv_percent=cv,
                        mean_percent=float(measured.mean()) if measured.numel() else float("nan"),
                        mean_length=mean, frames=n)


def jitter(positions: torch.Tensor, fps: float) -> Jitter:
    """Mean magnitude of the second difference of the positions times ``fps^2`` (m/s^2).

    Args:
        positions: ``(T, J, 3)`` positions (metres; NaN where missing), ``T >= 3``.
        fps: frame rate (frames per second).

    Returns:
        :class:`Jitter`.

    Raises:
        ValueError: bad shapes, fewer than 3 frames, ``fps`` not a positive finite number.
    """
    _check_positions(positions, 3)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps < float("inf"):
        raise ValueError(f"fps: expected a finite number > 0, got {fps!r}")
    acc = (positions[2:] - 2 * positions[1:-1] + positions[:-2]).norm(dim=-1) * fps * fps
    ok = torch.isfinite(acc)  # (T-2, J)
    a = torch.where(ok, acc, torch.zeros_like(acc))
    nan = float("nan")

    def mean_over(dim: int) -> torch.Tensor:
        n = ok.sum(dim)
        return torch.where(n > 0, a.sum(dim) / n.clamp_min(1), torch.full_like(a.sum(dim), nan))

    total = int(ok.sum())
    return Jitter(mean=float(a.sum() / total) if total else nan, per_joint=mean_over(0),
                  per_frame=mean_over(1))


def track_consistency(skeleton, theta: torch.Tensor, fps: float, keypoint_map=None) -> dict:
    """Bone-length constancy and jitter of a track, on the points a triangulation reports.

    With a keypoint map the points are the track's mapped detector keypoints
    (:func:`~torchmocap.skeleton.keypoint_positions`) and the bones the limb segments
    between them (:data:`LIMB_KEYPOINTS`, those the map has): a skeleton's bones are rigid, but
    a keypoint riding on the pelvis (a hip) and one on the femur (a knee) are not, so the CV
    compares with a peer's triangulated keypoints. Without one, the joints and the skeleton's
    bones (CV 0 up to rounding: the skeleton is rigid).

    Args:
        skeleton: the tracking :class:`~torchmocap.skeleton.Skeleton`.
        theta: ``(T, D)`` the track, ``T >= 3``.
        fps: frame rate.
        keypoint_map: a :class:`~torchmocap.skeleton.KeypointMap`, format name or None.

    Returns:
        ``{"points": "keypoints" | "joints", "bone_length_cv_percent": {"per_bone": {a-b: %},
        "mean": %}, "jitter_m_s2": {"mean": m/s^2, "per_point": {name: m/s^2}}}``.
    """
    from torchmocap.skeleton import keypoint_positions, load_keypoint_map

    with torch.no_grad():
        kin = skeleton(theta.to(skeleton.offsets.dtype))
        if keypoint_map is not None:
            kmap = load_keypoint_map(keypoint_map, skeleton)
            x = keypoint_positions(kin.positions, kin.rotations, kmap)
            names = list(kmap.names)
            bones = [b for b in LIMB_KEYPOINTS if b[0] in names and b[1] in names]
        else:
            x, names = kin.positions, list(skeleton.joint_names)
            bones = [(names[p], names[j]) for j, p in enumerate(skeleton.parents) if p >= 0]
    x = x.double()
    cv = bone_length_cv(x, bones, names) if bones else None
    j = jitter(x, fps)

    def r(v: float) -> float:
        return round(float(v), 4)

    return {"points": "keypoints" if keypoint_map is not None else "joints",
            "bone_length_cv_percent": None if cv is None else {
                "per_bone": {f"{a}-{b}": r(v) for (a, b), v in zip(bones, cv.cv_percent)},
                "mean": r(cv.mean_percent)},
            "jitter_m_s2": {"mean": r(j.mean),
                            "per_point": {n: r(v) for n, v in zip(names, j.per_joint)}}}
