"""The bodytrack frame loader pairs ``Camera<i>.cal`` with ``CAM<i>``/``FG<i>`` by number."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from torchmocap.cameras import CameraError, read_bouguet_rig
from torchmocap.data.bodytrack import load_bodytrack


@pytest.fixture
def frame_copy(tmp_path, shared_data):
    src = shared_data / "multiview" / "bodytrack_sequenceB_1"
    dst = tmp_path / "frame"
    shutil.copytree(src, dst)
    return dst


def test_feature_paired_by_number(frame_copy):
    """Without camera 1, cameras 2-4 keep their own calibrations (a sorted-list pairing would
    give CAM2 the calibration of Camera2.cal only by luck of the glob)."""
    for d in ("CAM1", "FG1"):
        shutil.rmtree(frame_copy / d)
    (frame_copy / "CALIB" / "Camera1.cal").unlink()
    rig, images, masks = load_bodytrack(frame_copy)
    ref = read_bouguet_rig([frame_copy / "CALIB" / f"Camera{i}.cal" for i in (2, 3, 4)])
    assert rig.names == ["Camera2", "Camera3", "Camera4"]
    torch.testing.assert_close(rig.R, ref.R, atol=0, rtol=0)
    torch.testing.assert_close(rig.t, ref.t, atol=0, rtol=0)
    cam2 = np.array(Image.open(frame_copy / "CAM2" / "image0000.png").convert("L"))
    assert torch.equal(images[0], torch.from_numpy(cam2))
    assert masks.shape == (3, 480, 640)


def test_exception_gap_and_uncalibrated_camera(frame_copy):
    (frame_copy / "CALIB" / "Camera2.cal").unlink()
    with pytest.raises(CameraError, match=r"CALIB: missing Camera2\.cal"):
        load_bodytrack(frame_copy)
    (frame_copy / "CALIB" / "Camera1.cal").unlink()
    with pytest.raises(FileNotFoundError, match=r"CAM1 has no calibration \(CALIB/Camera1\.cal"):
        load_bodytrack(frame_copy)
