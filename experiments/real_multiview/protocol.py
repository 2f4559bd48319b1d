"""The protocol every row of this experiment is scored by: the recording's BODY_25B detections
and rig, leave-one-camera-out reprojection scores, bone-length constancy and jitter
(imported by ``peers.py`` and ``report.py``, run from this folder or with it on ``sys.path``).

* Held-out scores: a reconstruction ``(T, 25, 3)`` (BODY_25B order) made without camera ``c`` is
  projected into ``c`` and compared with ``c``'s detections of confidence above
  :data:`MIN_CONFIDENCE` (:func:`torchmocap.evaluation.reprojection_scores`: median and mean px,
  PCK at 5 % and 10 % of the box height of the frame's compared detections in that view). A
  keypoint a method did not reconstruct (NaN) is counted as missing, not scored.
* Bone-length CV over the sequence of the :data:`CV_BONES` (between BODY_25B keypoints), and
  jitter (mean acceleration, m/s^2) of their :data:`LIMB_KEYPOINTS`
  (:func:`torchmocap.evaluation.bone_length_cv`, :func:`torchmocap.evaluation.jitter`). Every
  method reconstructs these twelve keypoints, so every row's consistency is measured on the
  same points.

Pixels are those of the full-resolution videos (the detections' own).

Shapes: ``T`` frames, ``C`` cameras, ``K = 25`` keypoints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch

from torchmocap.cameras import CameraError, CameraRig, camera_key, read_calibration
from torchmocap.data.recordings.files import RecordingLayoutError, discover_recording
from torchmocap.evaluation import ReprojectionScores, bone_length_cv, jitter, reprojection_scores
from torchmocap.io.frames import FrameSourceError, numbered_files, open_frames
from torchmocap.io.openpose import check_keypoint_format, keypoint_format, read_openpose_json

#: the detector's keypoint format and names (column order of every reconstruction here)
FORMAT = "body_25b"
KEYPOINTS = keypoint_format(FORMAT)
#: compared detections in the held-out view: confidence above this
MIN_CONFIDENCE = 0.3
#: bones whose length constancy is measured (hip-knee, knee-ankle, shoulder-elbow,
#: elbow-wrist on both sides, the hip width and the shoulder width)
CV_BONES = (("LHip", "LKnee"), ("LKnee", "LAnkle"), ("RHip", "RKnee"), ("RKnee", "RAnkle"),
            ("LShoulder", "LElbow"), ("LElbow", "LWrist"), ("RShoulder", "RElbow"),
            ("RElbow", "RWrist"), ("LHip", "RHip"), ("LShoulder", "RShoulder"))
#: the keypoints of the bones (jitter is measured on them)
LIMB_KEYPOINTS = tuple(k for k in KEYPOINTS if any(k in b for b in CV_BONES))


def bone_name(bone: tuple[str, str]) -> str:
    """``"LHip-LKnee"``."""
    return "-".join(bone)


@dataclass
class Detections:
    """A recording's associated detections and rig.

    Attributes:
        points: ``(T, C, K, 3)`` float64 (u, v, confidence) in full-resolution pixels
            (zeros = not detected).
        rig: the float64 :class:`~torchmocap.cameras.CameraRig` of the ``C`` cameras (in
            ``cameras``' order).
        cameras: the ``C`` camera names (the recording's: ``cam01``, ...).
        frames: the ``T`` frame indices of the recording.
        fps: frame rate.
        path: the recording folder.
    """

    points: torch.Tensor
    rig: CameraRig
    cameras: list[str]
    frames: list[int]
    fps: float
    path: Path

    def camera_index(self, camera: str | int) -> int:
        """Index of ``camera``: a name or anything with its number (``cam02``, ``cam_02``,
        ``"2"``), or an index in name order (an int)."""
        if isinstance(camera, bool) or not isinstance(camera, (str, int)):
            raise ValueError(f"camera: expected a name or an index, got {camera!r}")
        if isinstance(camera, int):
            if not 0 <= camera < len(self.cameras):
                raise ValueError(f"camera index {camera} out of range; the recording has "
                                 f"{len(self.cameras)} cameras {self.cameras}")
            return camera
        hits = [i for i, n in enumerate(self.cameras) if camera_key(n) == camera_key(camera)]
        if len(hits) != 1:
            raise ValueError(f"unknown camera {camera!r}; the recording has {self.cameras}")
        return hits[0]


def load_detections(path: str | Path, start: int = 0, stop: int | None = None,
                    fps: float | None = None) -> Detections:
    """The associated BODY_25B detections (``pose-associated/<cam>_json``, one person per
    file) and the calibration of a recording folder (layout of ``docs/recordings.md``).

    Args:
        path: the recording folder.
        start, stop: frames ``start .. stop - 1`` (stop None: every frame all cameras have).
        fps: the frame rate, needed only when the cameras are image folders (videos carry it).

    Raises:
        RecordingLayoutError: no associated keypoints for a camera, a missing frame (named).
        CameraError: a camera without calibration.
        KeypointFormatError: detections that are not BODY_25B, or several people in a file.
    """
    files = discover_recording(path)
    lacking = [c.name for c in files.cameras if "associated" not in c.keypoints]
    if lacking:
        raise RecordingLayoutError(f"{files.root}: no associated keypoints "
                                   f"(pose-associated/<cam>_json) for camera(s) {lacking}")
    rig = read_calibration(files.calibration)
    keys = [camera_key(n) for n in rig.names]
    idx = []
    for cam in files.cameras:
        if keys.count(cam.key) != 1:
            raise CameraError(f"{files.calibration}: expected one calibration entry for camera "
                              f"{cam.name!r}, the calibration has {rig.names}")
        idx.append(keys.index(cam.key))
    rig = rig.subset(idx).double()
    numbered = [numbered_files(c.keypoints["associated"], (".json",)) for c in files.cameras]
    end = min(max(n) for n in numbered) + 1 if stop is None else stop
    frames = list(range(start, end))
    if not frames:
        raise ValueError(f"frames {start}..{end - 1}: no frames")
    people = []
    for cam, files_of in zip(files.cameras, numbered):
        for t in frames:
            if t not in files_of:
                raise RecordingLayoutError(f"{cam.keypoints['associated']}: no keypoint file "
                                           f"for frame {t}")
            x = read_openpose_json(files_of[t], len(KEYPOINTS))
            if x.shape[0] > 1:
                raise RecordingLayoutError(
                    f"{files_of[t]}: {x.shape[0]} people; expected the associated detections "
                    "of one person per file")
            people.append(x)
    check_keypoint_format(FORMAT, people, str(files.root / "pose-associated"))
    pts = torch.stack([x[0] if x.shape[0] else torch.zeros(len(KEYPOINTS), 3,
                                                           dtype=torch.float64)
                       for x in people]).reshape(len(files.cameras), len(frames), -1, 3)
    if fps is None:
        fps = open_frames(files.cameras[0].frames).fps
        if fps is None:
            raise FrameSourceError(f"{files.cameras[0].frames}: image folders carry no frame "
                                   "rate; pass fps")
    return Detections(points=pts.transpose(0, 1).contiguous(), rig=rig,
                      cameras=[c.name for c in files.cameras], frames=frames, fps=float(fps),
                      path=files.root)


def heldout_scores(points: torch.Tensor, det: Detections, camera: int) -> ReprojectionScores:
    """Scores of ``points (T, K, 3)`` in camera ``camera``'s detections (module docstring)."""
    return reprojection_scores(points.double(), det.points[:, camera],
                               det.rig.subset([camera]), MIN_CONFIDENCE)


def _number(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 4)


def score_row(scores: ReprojectionScores, points: torch.Tensor, fps: float) -> dict:
    """The JSON-ready scores of one reconstruction ``points (T, K, 3)`` in one held-out view:
    ``median_px``, ``mean_px``, ``pck_05``, ``pck_10``, ``compared``, ``missing``,
    ``frame_median_px`` (per frame), ``bone_cv_percent`` (per bone of :data:`CV_BONES`),
    ``bone_cv_mean``, ``jitter`` (m/s^2, :data:`LIMB_KEYPOINTS`)."""
    X = points.double()
    cv = bone_length_cv(X, CV_BONES, KEYPOINTS)
    limbs = [KEYPOINTS.index(k) for k in LIMB_KEYPOINTS]
    return {
        "median_px": _number(scores.median_px), "mean_px": _number(scores.mean_px),
        "pck_05": _number(scores.pck_05),
        "pck_10": _number(scores.pck_10),
        "compared": scores.num_compared, "missing": scores.num_missing,
        "frame_median_px": [_number(v) for v in scores.frame_median_px.tolist()],
        "bone_cv_percent": {bone_name(b): _number(v)
                            for b, v in zip(CV_BONES, cv.cv_percent.tolist())},
        "bone_cv_mean": _number(cv.mean_percent),
        "jitter": _number(jitter(X[:, limbs], fps).mean),
    }
