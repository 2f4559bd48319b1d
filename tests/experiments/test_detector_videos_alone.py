"""experiments/detector/videos_alone.py: the videos-only folder (links to the recording's videos
and calibration, nothing else) and the results table."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("detector/videos_alone.py")


def test_prepare(script, pose2sim_root, tmp_path):
    out = tmp_path / "alone"
    script.prepare(pose2sim_root, out)
    assert sorted(p.name for p in out.iterdir()) == ["calibration", "videos"]
    videos = sorted(p.name for p in (out / "videos").iterdir())
    assert videos == sorted(p.name for p in (pose2sim_root / "videos").iterdir())
    assert all((out / "videos" / v).resolve() == (pose2sim_root / "videos" / v).resolve()
               for v in videos)
    script.prepare(pose2sim_root, out)  # again: unchanged
    from torchmocap.data.recordings.files import discover_recording

    files = discover_recording(out)
    assert [c.name for c in files.cameras] == ["cam01", "cam02", "cam03", "cam04"]
    assert all(not c.keypoints and c.masks is None and not c.background for c in files.cameras)
    (out / "pose").mkdir()
    with pytest.raises(SystemExit, match=r"holds \['pose'\] besides videos/ and calibration/"):
        script.prepare(pose2sim_root, out)


def test_table(script):
    row = {"camera": "cam01", "seconds_per_frame": 0.3,
           **{k: {"median_px": 20.0, "mean_px": 21.0, "pck_05": 0.8, "pck_10": 0.99,
                  "compared": 10} for k in ("own", "vs_openpose", "vs_mediapipe")},
           "silhouette_iou": {"detector": 0.7, "computed (OpenPose, plates)": 0.6}}
    result = {"groups": {"openpose": "OpenPose", "mediapipe_detector": "videos alone"},
              "runs": {"openpose": {"cam01": row}, "mediapipe_detector": {
                  "cam01": {**row, "own": {**row["own"], "median_px": 30.0}}}},
              "mask_iou": {"detector vs computed": {c: 0.75 for c in script.CAMERAS}},
              "keypoint_check": {"cam01": {"frames_dropped": [], "frames_relabelled": [3],
                                           "frames_searched_in_box": [], "frames_unchecked": [],
                                           "median_agreement_px": 20.0}},
              "timing": {"detect_ms_per_frame": {"cam01": 40.0},
                         "cold_cache": {"frames": 400, "ms_per_frame": 90.0}}}
    text = script.table(result)
    assert "| OpenPose | own detections | 20.0 | – | – | – | 20.0 | 80.0 | 0.30 |" in text
    assert "| videos alone | own detections | 30.0 |" in text
    assert "| cam01 | 0 | 1 | 0 | 20.0 | – | – |" in text and "90.0 ms per frame" in text
