"""2D keypoint detections in OpenPose JSON: keypoint formats, files, folders of frames.

An OpenPose JSON file holds one frame of one camera: ``people[k].pose_keypoints_2d`` is a flat
list of ``K × (u, v, confidence)`` in pixels (a missed keypoint has confidence 0). MMPose /
RTMPose and Pose2Sim write the same layout for their COCO-17 and HALPE-26 models.

Keypoint formats (:data:`KEYPOINT_FORMATS`) are ordered lists of keypoint names in one
vocabulary (``LShoulder``, ``RKnee``, …; the pelvis centre is ``MidHip`` in every format, HALPE's
``Hip``), so consumers can map detections of any format to a skeleton by name:

* ``body_25``: OpenPose's BODY_25 (``MidHip`` at 8, between the hips at 9 and 12);
* ``body_25b``: OpenPose's BODY_25B (COCO order first, then ``Neck``, ``Head`` and the feet);
* ``coco_17``: the 17 COCO keypoints in COCO order;
* ``halpe_26``: HALPE-26 (COCO order, then ``Head``, ``Neck``, ``MidHip`` and the feet);
* ``mediapipe_33``: MediaPipe Pose's 33 landmarks (:mod:`torchmocap.detectors`): face points
  (eyes inner/centre/outer, ears, mouth corners), the limbs, three points per hand
  (``LPinky``, ``LIndex``, ``LThumb``) and the feet (``LHeel``, ``LFootIndex``). Shared names
  are the same body parts, not the same points: MediaPipe's hips, for one, lie elsewhere than
  OpenPose's (the keypoint maps place each format's keypoints on the skeleton).

BODY_25 and BODY_25B both have 25 keypoints; :func:`body25_plausibility` tells them apart from
the detections themselves (BODY_25's ``MidHip`` and ``Neck`` lie halfway between the hips and
the shoulders; at those indices BODY_25B has the right elbow and the left eye).

File names: Pose2Sim's ``camNN.FFFF.json`` and OpenPose's ``<name>_000000000123_keypoints.json``;
the frame index is the last number in the name (without a ``_keypoints`` suffix), counted from
0 (the first frame of the video): :func:`torchmocap.io.frames.numbered_files`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor

__all__ = [
    "KEYPOINT_FORMATS",
    "KeypointFormatError",
    "body25_plausibility",
    "check_keypoint_format",
    "keypoint_format",
    "read_openpose_json",
    "write_openpose_json",
]

_COCO = ["Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
         "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle"]

#: keypoint names of each supported format, in the detector's order
KEYPOINT_FORMATS: dict[str, tuple[str, ...]] = {
    "body_25": ("Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow",
                "LWrist", "MidHip", "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye",
                "LEye", "REar", "LEar", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe",
                "RHeel"),
    "body_25b": (*_COCO, "Neck", "Head", "LBigToe", "LSmallToe", "LHeel", "RBigToe",
                 "RSmallToe", "RHeel"),
    "coco_17": tuple(_COCO),
    "halpe_26": (*_COCO, "Head", "Neck", "MidHip", "LBigToe", "RBigToe", "LSmallToe",
                 "RSmallToe", "LHeel", "RHeel"),
    "mediapipe_33": ("Nose", "LEyeInner", "LEye", "LEyeOuter", "REyeInner", "REye",
                     "REyeOuter", "LEar", "REar", "LMouth", "RMouth", "LShoulder", "RShoulder",
                     "LElbow", "RElbow", "LWrist", "RWrist", "LPinky", "RPinky", "LIndex",
                     "RIndex", "LThumb", "RThumb", "LHip", "RHip", "LKnee", "RKnee", "LAnkle",
                     "RAnkle", "LHeel", "RHeel", "LFootIndex", "RFootIndex"),
}

#: BODY_25 indices of (MidHip, RHip, LHip) and (Neck, RShoulder, LShoulder)
_BODY25_MIDPOINTS = ((8, 9, 12), (1, 2, 5))


class KeypointFormatError(ValueError):
    """A keypoint file or folder is malformed or of another format (names the file)."""


def keypoint_format(name: str) -> tuple[str, ...]:
    """The keypoint names of format ``name`` (case-insensitive, ``-`` or ``_``).

    Raises:
        KeypointFormatError: an unknown format (the known ones are listed).
    """
    key = str(name).lower().replace("-", "_")
    if key not in KEYPOINT_FORMATS:
        raise KeypointFormatError(f"keypoint format {name!r} is unknown; expected one of "
                                  f"{sorted(KEYPOINT_FORMATS)}")
    return KEYPOINT_FORMATS[key]


def read_openpose_json(path: str | os.PathLike, num_keypoints: int | None = None) -> Tensor:
    """The people of one OpenPose JSON file.

    Args:
        path: the file.
        num_keypoints: the format's ``K``; a person with another count is an error. None takes
            the count of the file's first person.

    Returns:
        ``(P, K, 3)`` float64 ``(u, v, confidence)`` of the ``P`` people (``P = 0`` when no one
        was detected; then ``K = num_keypoints`` or 0). An entry without keypoints (Pose2Sim's
        ``{}`` for a view where the associated person was not found) is nobody.

    Raises:
        KeypointFormatError: naming the file for an unreadable, empty or unparsable file, a
            missing ``people`` list, non-numeric or non-finite values, negative confidences, or a
            keypoint count other than ``num_keypoints`` (expected and found counts named).
    """
    from torchmocap.inputs import read_text_input

    path = Path(path)
    text = read_text_input(path, KeypointFormatError, "keypoint file (OpenPose JSON)")
    if not text.strip():
        raise KeypointFormatError(f"{path}: empty file; expected OpenPose JSON "
                                  '({"people": [{"pose_keypoints_2d": [...]}]})')
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise KeypointFormatError(f"{path}:{e.lineno}: not valid JSON ({e.msg})") from None
    people = data.get("people") if isinstance(data, dict) else None
    if not isinstance(people, list):
        raise KeypointFormatError(f"{path}: expected OpenPose JSON with a 'people' list")
    out = []
    for k, person in enumerate(people):
        if not isinstance(person, dict):
            raise KeypointFormatError(f"{path}: people[{k}] is not a JSON object")
        flat = person.get("pose_keypoints_2d", [])
        if isinstance(flat, list) and not flat:
            continue  # Pose2Sim's {}: the person was not found in this view
        if not isinstance(flat, list):
            raise KeypointFormatError(f"{path}: people[{k}].pose_keypoints_2d is not a list")
        K = len(flat) // 3 if num_keypoints is None else num_keypoints
        if len(flat) != 3 * K or K == 0:
            raise KeypointFormatError(
                f"{path}: people[{k}].pose_keypoints_2d has {len(flat)} values = "
                f"{len(flat) / 3:g} keypoints, expected {K} keypoints ({3 * K} values: u, v, "
                "confidence each); is the keypoint format right?")
        num_keypoints = K
        try:
            x = torch.tensor(flat, dtype=torch.float64).reshape(K, 3)
        except (TypeError, ValueError) as e:
            raise KeypointFormatError(f"{path}: people[{k}] has non-numeric keypoints ({e})"
                                      ) from None
        if not bool(torch.isfinite(x).all()) or bool((x[:, 2] < 0).any()):
            raise KeypointFormatError(f"{path}: people[{k}] has non-finite values or negative "
                                      "confidences")
        out.append(x)
    if not out:
        return torch.zeros(0, num_keypoints or 0, 3, dtype=torch.float64)
    return torch.stack(out)


def write_openpose_json(path: str | os.PathLike, people: Tensor,
                        extra: dict | None = None) -> Path:
    """Write ``people (P, K, 3)`` ``(u, v, confidence)`` as an OpenPose JSON file
    (``{"version": 1.3, "people": [{"pose_keypoints_2d": [...]}, ...]}``), atomically: a reader
    sees the old file or the whole new one. :func:`read_openpose_json` reads it back.

    Args:
        path: the file (its folder is created).
        people: ``(P, K, 3)`` finite values, confidences >= 0 (``P = 0``: nobody).
        extra: more top-level JSON keys (JSON-safe), e.g. where the detections came from.

    Returns:
        the path.

    Raises:
        KeypointFormatError: another shape, non-finite values, negative confidences, an
            ``extra`` that is not JSON-safe or that overrides ``version`` or ``people``.
    """
    from torchmocap.atomic import atomic_path

    x = torch.as_tensor(people, dtype=torch.float64)
    if x.dim() != 3 or x.shape[-1] != 3:
        raise KeypointFormatError(f"people: expected shape (P, K, 3) (u, v, confidence), got "
                                  f"{tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()) or bool((x[..., 2] < 0).any()):
        raise KeypointFormatError("people: expected finite values and confidences >= 0")
    extra = dict(extra or {})
    if {"version", "people"} & set(extra):
        raise KeypointFormatError("extra: must not set 'version' or 'people'")
    data = {"version": 1.3,
            "people": [{"pose_keypoints_2d": p.flatten().tolist()} for p in x], **extra}
    try:
        text = json.dumps(data, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise KeypointFormatError(f"extra: expected JSON-safe values ({e})") from None
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def body25_plausibility(people: Sequence[Tensor]) -> float | None:
    """How well detections fit BODY_25's layout: the median, over people and over the two
    midpoints (``MidHip`` between the hips, ``Neck`` between the shoulders), of the distance of
    the middle keypoint from the midpoint of its pair, relative to the pair's distance.

    About 0.0–0.1 for BODY_25 detections; BODY_25B puts the right elbow and the left eye at
    those indices, far from the midpoints (typically > 0.5).

    Args:
        people: ``(P, 25, 3)`` tensors (e.g. one per file).

    Returns:
        the median ratio, or None when no person has all three keypoints of either triple.
    """
    ratios = []
    for x in people:
        if x.shape[0] == 0 or x.shape[1] != 25:  # nobody in the file
            continue
        for mid, a, b in _BODY25_MIDPOINTS:
            seen = (x[:, [mid, a, b], 2] > 0).all(-1)
            if not bool(seen.any()):
                continue
            y = x[seen]
            span = (y[:, a, :2] - y[:, b, :2]).norm(dim=-1)
            off = (y[:, mid, :2] - 0.5 * (y[:, a, :2] + y[:, b, :2])).norm(dim=-1)
            ok = span > 0
            ratios.append(off[ok] / span[ok])
    if not ratios or sum(r.numel() for r in ratios) == 0:
        return None
    return float(torch.cat(ratios).median())


def check_keypoint_format(fmt: str, people: Sequence[Tensor], source: str = "keypoints",
                          threshold: float = 0.3) -> str:
    """Check that detections are plausibly of format ``fmt``; ``"auto"`` picks it.

    The count of keypoints decides between 17 (``coco_17``), 25 and 26 (``halpe_26``). For 25,
    :func:`body25_plausibility` decides: below ``threshold`` the detections are BODY_25, above
    it BODY_25B.

    Args:
        fmt: a key of :data:`KEYPOINT_FORMATS`, or ``"auto"``.
        people: ``(P, K, 3)`` detections (e.g. of several files).
        source: what the detections are, for messages (a folder).
        threshold: the BODY_25 / BODY_25B boundary of the plausibility ratio.

    Returns:
        the format's key.

    Raises:
        KeypointFormatError: a count that matches no (or not the declared) format, a declared
            BODY_25 / BODY_25B contradicted by the detections, or ``auto`` on 25 keypoints with
            no person showing hips or shoulders.
    """
    counts = {int(x.shape[1]) for x in people if x.shape[0] > 0}
    if len(counts) > 1:
        raise KeypointFormatError(f"{source}: files with different keypoint counts {counts}")
    if not counts:
        if fmt == "auto":
            raise KeypointFormatError(f"{source}: nobody is detected in any file, so there "
                                      "is no subject to track (and no detection to tell the "
                                      "keypoint format from); choose other frames (data.start, "
                                      "data.stop) or load without keypoints "
                                      "(data.keypoints.source=none)")
        keypoint_format(fmt)
        return fmt.lower().replace("-", "_")
    K = counts.pop()
    if fmt != "auto":
        names = keypoint_format(fmt)
        fmt = fmt.lower().replace("-", "_")
        if K != len(names):
            raise KeypointFormatError(f"{source}: {K} keypoints per person, but format {fmt!r} "
                                      f"has {len(names)}")
        if K != 25:
            return fmt
    by_count = {len(v): k for k, v in KEYPOINT_FORMATS.items() if len(v) != 25}
    if K != 25:
        if K not in by_count:
            known = ", ".join(f"{k}: {len(v)}" for k, v in KEYPOINT_FORMATS.items())
            raise KeypointFormatError(f"{source}: {K} keypoints per person match no known "
                                      f"format ({known})")
        return by_count[K]
    ratio = body25_plausibility(people)
    if ratio is None:
        if fmt == "auto":
            raise KeypointFormatError(f"{source}: 25 keypoints, but no person shows both hips or "
                                      "both shoulders to tell BODY_25 from BODY_25B; set "
                                      "data.keypoints.format")
        return fmt
    looks = "body_25" if ratio < threshold else "body_25b"
    if fmt not in ("auto", looks):
        raise KeypointFormatError(
            f"{source}: declared {fmt!r}, but the detections look like {looks!r}: keypoints "
            f"1 and 8 lie at {ratio:.2f} of the shoulder / hip span from the midpoints of "
            f"(2, 5) and (9, 12) (BODY_25's Neck and MidHip lie near 0; BODY_25B has LEye and "
            f"RElbow there); set data.keypoints.format to {looks!r}")
    return looks
