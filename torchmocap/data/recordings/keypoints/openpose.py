"""OpenPose JSON beside the videos as a keypoint source (``data.keypoints.source=openpose``).

One file per frame and camera (:func:`~torchmocap.io.openpose.read_openpose_json`), in
``pose-associated/<cam>_json/`` (the subject alone: one person or none per file) or
``pose/<cam>_json/`` (everyone detected), numbered by frame
(:func:`~torchmocap.io.frames.numbered_files`). With ``format: auto`` the first file with a
person sets the keypoint count every file must have, and the format is recognised from the
detections (:func:`~torchmocap.io.openpose.check_keypoint_format`).
"""

from __future__ import annotations

import torch

from torchmocap.data.recordings.files import RecordingLayoutError
from torchmocap.data.recordings.keypoints import (
    KeypointDetections,
    KeypointRequest,
    KeypointSource,
)
from torchmocap.io.frames import FrameSourceError, numbered_files
from torchmocap.io.openpose import check_keypoint_format, keypoint_format, read_openpose_json

__all__ = ["FOLDERS", "OpenPoseJson"]

#: ``folder`` setting -> the recording's folder of that kind
FOLDERS = {"associated": "pose-associated", "raw": "pose"}


class OpenPoseJson(KeypointSource):
    """OpenPose JSON files of every camera.

    Args:
        folder: ``associated`` (``pose-associated/``), ``raw`` (``pose/``) or ``auto`` (the
            associated files when every camera has them, else the raw ones).
    """

    def __init__(self, folder: str = "auto") -> None:
        if folder not in ("auto", *FOLDERS):
            raise ValueError(f"data.keypoints.folder: expected one of "
                             f"{['auto', *FOLDERS]}, got {folder!r}")
        self.folder = folder

    def _kind(self, request: KeypointRequest) -> str | None:
        """The folder kind every camera has (None: no camera has any, with ``auto``)."""
        cams = request.cameras
        kinds = tuple(FOLDERS) if self.folder == "auto" else (self.folder,)
        for kind in kinds:
            if all(kind in c.keypoints for c in cams):
                return kind
        if self.folder == "auto" and not any(c.keypoints for c in cams):
            return None
        lacking = {k: [c.name for c in cams if k not in c.keypoints] for k in kinds}
        raise RecordingLayoutError(f"{request.root}: keypoints missing for camera(s) " + "; ".join(
            f"{FOLDERS[k]}/<cam>_json: {v}" for k, v in lacking.items()) +
            " (set data.keypoints.source: none to load without keypoints)")

    def available(self, request: KeypointRequest) -> bool:
        """Every camera has OpenPose files (some but not all: an error naming them)."""
        return self._kind(request) is not None

    def read(self, request: KeypointRequest) -> KeypointDetections:
        kind = self._kind(request)
        if kind is None:
            raise RecordingLayoutError(
                f"{request.root}: no OpenPose keypoints (expected pose-associated/<cam>_json/ "
                "or pose/<cam>_json/; set data.keypoints.source: none to load without them)")
        fmt = request.format
        want = None if fmt == "auto" else len(keypoint_format(fmt))
        people: list[list[torch.Tensor]] = [[] for _ in request.frames]
        for cam in request.cameras:
            folder = cam.keypoints[kind]
            files = numbered_files(folder, (".json",))
            for i, t in enumerate(request.frames):
                if t not in files:
                    raise FrameSourceError(f"{folder}: no keypoint file for frame {t} (the "
                                           f"files are numbered {min(files)}..{max(files)})")
                x = read_openpose_json(files[t], want)
                want = want or (x.shape[1] if x.shape[0] else None)
                people[i].append(x)
        flat = [x for frame in people for x in frame]
        where = ", ".join(str(c.keypoints[kind]) for c in request.cameras)
        fmt = check_keypoint_format(fmt, flat, where)
        return KeypointDetections(people, fmt, associated=kind == "associated",
                                  report={"folder": kind, "folders": {
                                      c.name: str(c.keypoints[kind]) for c in request.cameras}})
