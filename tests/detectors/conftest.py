"""Fixtures of the detector tests: the detector (built once), real frames of the vendored
recordings (bodytrack's 4 views with their FG masks; frame 0 of pose2sim_balancing's 4 videos
with their OpenPose detections).

mediapipe is part of the dev extra (Python 3.10-3.12): without it these tests fail in CI (the
``CI`` variable set) and are skipped elsewhere, with what to install.
"""

from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest

CAMERAS = ("cam01", "cam02", "cam03", "cam04")


def require_mediapipe() -> None:
    if importlib.util.find_spec("mediapipe") is None:
        msg = ('mediapipe is not installed: pip install -e ".[dev]" (or ".[detector]"; Python '
               "3.10-3.12)")
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)


@pytest.fixture(scope="session")
def detector():
    require_mediapipe()
    from torchmocap.detectors import MediaPipePoseDetector

    det = MediaPipePoseDetector()
    yield det
    det.close()


@pytest.fixture(scope="session")
def bodytrack_views(data_file):
    """``[(rgb (480, 640, 3) uint8, fg (480, 640) bool)]`` of bodytrack's 4 views."""
    from PIL import Image

    from torchmocap.io.frames import read_mask

    root = data_file("multiview/bodytrack_sequenceB_1")
    out = []
    for c in range(1, 5):
        with Image.open(root / f"CAM{c}" / "image0000.png") as im:
            rgb = np.asarray(im.convert("RGB"))
        out.append((rgb, read_mask(root / f"FG{c}" / "image0000.png")))
    return out


@pytest.fixture(scope="session")
def pose2sim_frames(pose2sim_root):
    """``{cam: (rgb (1920, W, 3) uint8, subject (25, 3), raw (P, 25, 3))}`` of frame 0: the
    image, Pose2Sim's associated (subject) and raw (everyone) OpenPose detections."""
    from torchmocap.io.frames import open_frames
    from torchmocap.io.openpose import read_openpose_json

    out = {}
    for cam in CAMERAS:
        rgb = next(open_frames(pose2sim_root / "videos" / f"{cam}.mp4").frames(0, 1))
        sub = read_openpose_json(pose2sim_root / "pose-associated" / f"{cam}_json" /
                                 f"{cam}.0000.json", 25)[0]
        raw = read_openpose_json(pose2sim_root / "pose" / f"{cam}_json" / f"{cam}.0000.json", 25)
        out[cam] = (rgb, sub, raw)
    return out
