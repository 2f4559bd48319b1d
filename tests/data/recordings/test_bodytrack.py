"""The bodytrack frame loader pairs ``Camera<i>.cal`` with ``CAM<i>``/``FG<i>`` by number."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from torchmocap.cameras import CameraError, read_bouguet_rig
from torchmocap.data.recordings.bodytrack import load_bodytrack


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


def _rewrite_masks(folder, fn) -> None:
    for p in sorted(folder.glob("FG*/image0000.*")):
        a = np.asarray(Image.open(p).convert("L"))
        Image.fromarray(fn(a).astype(np.uint8)).save(p)


@pytest.mark.parametrize("value", [1, 2, 100])
def test_feature_binary_masks_of_any_foreground_value(frame_copy, value):
    """Masks saved as 0/1 (numpy booleans), 0/2 or 0/100 were read as empty (foreground only
    above 127: 'visual hull empty'); a two-level mask is binary whatever its foreground."""
    _, _, want = load_bodytrack(frame_copy)
    _rewrite_masks(frame_copy, lambda a: (a > 127) * value)
    _, _, got = load_bodytrack(frame_copy)
    assert torch.equal(got, want) and 0.03 < got.float().mean() < 0.1


TALL = r"visual hull is 2\.28 m tall, a subject 1\.30 x .* the skeleton is held at 1\.15"


@pytest.mark.parametrize("case, messages", [
    ("inverted", [r"masks of FG1, FG2, FG3, FG4 are more than 50 % foreground \(FG1 93\.6 %",
                  TALL]),
    ("all", [r"masks of FG1, FG2, FG3, FG4 are more than 50 % foreground \(FG1 100\.0 %",
             TALL]),
    ("swapped", [r"^data\.cameras: no three views' masks agree \(FG1 \d+ %, FG2 \d+ %, FG3 "
                 r"\d+ %, FG4 \d+ % agreement with the hull of the others; the limit is 70 %\)",
                 r"visual hull is 1\.28 m tall, a subject 0\.73 x human31's 1\.75 m, outside "
                 r"the scale range \[0\.85, 1\.15\]: the skeleton is held at 0\.85"]),
])
def test_implausible_masks_or_calibrations_are_reported(frame_copy, case, messages):
    """Inverted or all-foreground masks and swapped calibrations fitted a body at the clamp of
    its scale range with no warning. Swapped calibrations are refused by the views' agreement
    (reported, with the fit's warning, with ``checks="warn"``)."""
    import re
    import warnings

    from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence

    if case == "inverted":
        _rewrite_masks(frame_copy, lambda a: 255 - a)
    elif case == "all":
        _rewrite_masks(frame_copy, lambda a: np.full_like(a, 255))
    else:
        cal = frame_copy / "CALIB"
        (cal / "Camera1.cal").rename(cal / "tmp")
        (cal / "Camera3.cal").rename(cal / "Camera1.cal")
        (cal / "tmp").rename(cal / "Camera3.cal")
    from torchmocap.data.recordings.checks import RecordingCheckError

    if case == "swapped":
        with pytest.raises(RecordingCheckError, match=messages[0]):
            load_bodytrack_sequence(frame_copy)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        seq = load_bodytrack_sequence(frame_copy, checks="warn")
    got = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert len(got) == len(messages), got
    assert all(re.search(m, g) for m, g in zip(messages, got)), got
    assert seq.meta.skeleton_scale in (0.85, 1.15)


def test_feature_plausible_frame_gives_no_warning(frame_copy):
    import warnings

    from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_bodytrack_sequence(frame_copy)
    assert 0.85 < seq.meta.skeleton_scale < 1.15


def test_exception_empty_hull_says_what_was_read(frame_copy):
    from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence

    _rewrite_masks(frame_copy, lambda a: np.where(np.arange(a.shape[1]) < 320, a, 0))
    p = frame_copy / "FG2" / "image0000.png"
    Image.fromarray(np.zeros((480, 640), np.uint8)).save(p)
    with pytest.raises(ValueError, match=r"no three views' masks agree .*; the mask of FG2 is "
                                         r"empty \(foreground read: FG1 \d\.\d %, FG2 0\.0 %, "
                                         r"FG3"):
        load_bodytrack_sequence(frame_copy)
    with pytest.raises(ValueError, match=r"visual hull of the masks is empty: .*foreground "
                                         r"read: FG1 \d\.\d %, FG2 0\.0 %, FG3"), \
            pytest.warns(UserWarning, match="no three views' masks agree"):
        load_bodytrack_sequence(frame_copy, checks="warn")


def test_exception_binary_calibration_names_the_file(frame_copy):
    (frame_copy / "CALIB" / "Camera2.cal").write_bytes(bytes(range(200, 256)) * 4)
    with pytest.raises(CameraError, match=r"Camera2\.cal: not a text file \(byte 0xc8 at "
                                          r"offset 0 is not UTF-8\); expected a Bouguet"):
        load_bodytrack(frame_copy)
