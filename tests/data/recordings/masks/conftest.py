"""Real frames for the mask tests: the first frames of pose2sim_balancing (four views), its
calibration, background plates and OpenPose detections, decoded and built here (the folder
loader is not what these tests are about)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchmocap.cameras import CameraRig

#: frames used: the trimmed cam01 copy repeats frame 8 at index 9 (its stream copy ends on a
#: B-frame), so frames 0-8 are the ones all four videos decode identically to the originals
FRAMES = 9
CAMERAS = ("cam01", "cam02", "cam03", "cam04")


@pytest.fixture(scope="session")
def pose2sim_frames(pose2sim_root):
    """``(T, C, 1920, 1088, 3)`` uint8 frames (cam01/cam02 decode 1080 wide: padded on the
    right) and their ``(C, 2)`` decoded sizes (width, height)."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    views, sizes = [], []
    for cam in CAMERAS:
        reader = imageio_ffmpeg.read_frames(str(pose2sim_root / "videos" / f"{cam}.mp4"))
        meta = next(reader)
        w, h = meta["size"]
        frames = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for _, f in zip(range(FRAMES),
                                                                             reader)]
        reader.close()
        views.append(np.stack(frames))
        sizes.append((w, h))
    W, H = max(s[0] for s in sizes), max(s[1] for s in sizes)
    out = torch.zeros(FRAMES, len(CAMERAS), H, W, 3, dtype=torch.uint8)
    for c, v in enumerate(views):
        out[:, c, :v.shape[1], :v.shape[2]] = torch.from_numpy(v)
    return out, torch.tensor(sizes)


@pytest.fixture(scope="session")
def pose2sim_rig(pose2sim_calibrated_rig, pose2sim_frames):
    """The calibrated rig (Calib.toml) with the decoded image sizes."""
    r = pose2sim_calibrated_rig
    return CameraRig(r.K, r.R, r.t, pose2sim_frames[1], r.dist, list(CAMERAS))


@pytest.fixture(scope="session")
def pose2sim_plates(pose2sim_root):
    """``(C, 1920, 1088, 3)`` uint8 background plates (taken at another time: people with
    drawn skeletons and moved objects in them)."""
    from PIL import Image

    plates = []
    for cam in CAMERAS:
        with Image.open(pose2sim_root / "background" / f"{cam}_ext.jpg") as im:
            plates.append(np.asarray(im.convert("RGB")))
    return torch.from_numpy(np.stack(plates))


def _people(path) -> list[np.ndarray]:
    return [np.asarray(p["pose_keypoints_2d"], dtype=np.float64).reshape(-1, 3)
            for p in json.loads(path.read_text())["people"]]


@pytest.fixture(scope="session")
def pose2sim_keypoints(pose2sim_detections):
    """The subject's BODY_25B detections ``(T, C, 25, 3)`` (pose-associated)."""
    return pose2sim_detections[:FRAMES]


@pytest.fixture(scope="session")
def pose2sim_bystander(pose2sim_root, pose2sim_keypoints):
    """Confident keypoints (u, v) of the other people in the raw detections: a list over
    frames of per-camera ``(N, 2)`` arrays (the bystander in cam01/cam02; empty elsewhere)."""
    out = []
    for t in range(FRAMES):
        row = []
        for c, cam in enumerate(CAMERAS):
            subject = pose2sim_keypoints[t, c].numpy()
            others = [p for p in _people(pose2sim_root / "pose" / f"{cam}_json" /
                                         f"{cam}.{t:04d}.json")
                      if not np.array_equal(p, subject)]
            pts = [p[p[:, 2] >= 0.3, :2] for p in others]
            row.append(np.concatenate(pts) if pts else np.zeros((0, 2)))
        out.append(row)
    return out
