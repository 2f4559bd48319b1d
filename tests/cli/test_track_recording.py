"""torchmocap-track on a real recording (the trimmed pose2sim_balancing): a run with a held-out
camera writes the scores without ground truth (held-out view, tracked views, consistency), the
overlays of every view, the video, BVH and GLB, and prints them; bad settings fail naming the
setting."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.outputs import print_summary
from torchmocap.cli.track import run

EXE = str(Path(sys.executable).parent / "torchmocap-track")
pytestmark = pytest.mark.filterwarnings("ignore:.*codec's crop")


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


def _recording(shared_data, tmp_path, *extra):
    root = shared_data / "multiview" / "pose2sim_balancing"
    return ["data=recording", f"data.path={root}", "data.stop=4", "data.scale=0.25",
            f"data.mask_cache={tmp_path / 'masks'}", "progress=false", *extra]


@pytest.mark.slow
def test_heldout_run_writes_and_prints_the_scores(shared_data, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    cfg = _compose(_recording(shared_data, tmp_path, "tracker=real_keypoints",
                              "tracker.num_particles=30", "tracker.inference.layers=4",
                              "evaluation.heldout_camera=cam01", "overlays=1",
                              "video.enabled=true", "video.format=gif"))
    m = run(cfg, out)
    saved = json.loads((out / "metrics.json").read_text())
    assert saved == json.loads(json.dumps(m)) and saved["frames"] == 4
    h = saved["heldout"]
    assert h["camera"] == "cam01" and h["image_scale"] == 0.25 and h["min_confidence"] == 0.3
    for key in ("median_px", "mean_px", "pck_05", "pck_10", "num_compared", "silhouette_iou"):
        assert key in h and key in h["hold_first_pose"] or key == "num_compared"
    assert h["keypoint_mapping"]["RKnee"]["joint"] == "r_knee"
    assert h["num_compared"] > 50 and 0.0 < h["silhouette_iou"] < 1.0
    assert list(saved["tracked_views"]) == ["cam02", "cam03", "cam04"]
    c = saved["consistency"]
    assert c["points"] == "keypoints" and set(c["bone_length_cv_percent"]["per_bone"]) >= \
        {"LHip-LKnee", "RElbow-RWrist"} and c["jitter_m_s2"]["mean"] > 0
    assert saved["skeleton_scale"] > 0.8 and saved["source"] == "recording"
    z = np.load(out / "track.npz")
    assert z["heldout_errors_px"].shape == (4, 25) and z["heldout_silhouette_iou"].shape == (4,)
    from torchmocap.io import load_motion

    assert load_motion(out / "tracked.bvh").num_frames == 4
    assert (out / "track.glb").stat().st_size > 1000 and (out / "overlays.gif").is_file()
    from PIL import Image

    (grid,) = out.glob("overlay_*.png")
    with Image.open(grid) as im:  # every view: 2 x 2 panels of 272 x 480
        assert im.size == (544, 20 + 960)
    print_summary(m)
    printed = capsys.readouterr().out
    assert "held-out cam01" in printed and "holding the first pose" in printed
    assert "bone-length CV (keypoints)" in printed and "jitter (keypoints)" in printed


@pytest.mark.parametrize("extra,match", [
    (["evaluation.heldout_camera=cam09"], r"evaluation\.heldout_camera: unknown camera 'cam09'"),
    (["evaluation.heldout_camera=cam02", "data.cameras=[cam01,cam03]"],
     r"evaluation\.heldout_camera: camera 'cam02' is not among the loaded cameras"),
    (["data.masks=compute", "+data.mask_settings.scale=0.5"],
     r"data\.mask_settings\.scale: the masks are computed at the images' working scale"),
])
def test_bad_recording_settings_name_the_setting(shared_data, tmp_path, extra, match):
    cfg = _compose(_recording(shared_data, tmp_path, "tracker=real_keypoints", *extra))
    with pytest.raises(ValueError, match=match):
        run(cfg, tmp_path)


def test_heldout_camera_of_synthetic_data_is_refused(tmp_path):
    cfg = _compose(["data.clip.frames=3", "evaluation.heldout_camera=0", "progress=false"])
    with pytest.raises(ValueError, match=r"evaluation\.heldout_camera: the data source "
                                         r"torchmocap\.data\.synthetic\.clips\."
                                         r"synthesized_sequence cannot hold a camera out"):
        run(cfg, tmp_path)


def test_console_masks_compute_without_keypoints_or_plates(shared_data, tmp_path):
    """The command line's error contract: one line naming the setting, exit status 2."""
    rec = tmp_path / "rec"
    shutil.copytree(shared_data / "multiview" / "pose2sim_balancing", rec,
                    ignore=shutil.ignore_patterns("background", "pose2sim_output"))
    r = subprocess.run([EXE, "data=recording", f"data.path={rec}", "data.masks=compute",
                        "data.keypoints.source=none", "data.stop=2", "data.scale=0.25",
                        "tracker=real_keypoints", f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert r.returncode == 2, r.stderr[-2000:]
    assert "torchmocap-track: error: data.masks: compute needs the subject's keypoints or " \
           "background plates" in r.stderr
    record = json.loads((tmp_path / "run" / "failure.json").read_text())
    assert record["error"].startswith("data.masks: compute needs")


@pytest.mark.parametrize("data, tracker, presets", [
    ("recording", "default", "real_keypoints | real_local | real_sir | real_mixture"),
    ("recording", "p", "real_keypoints"),
    ("bodytrack", "gs", "real_frame | real_frame_hull"),
])
def test_tracker_needing_imus_is_refused_before_loading(tmp_path, monkeypatch, data, tracker,
                                                        presets):
    """A tracker that reads IMUs cannot track a video recording: refused before a file is read
    (a missing folder would fail later), naming the modality and the presets of that data."""
    from torchmocap.data.recordings import loader

    monkeypatch.setattr(loader, "discover_recording", lambda *a, **k: pytest.fail("loaded"))
    cfg = _compose([f"data={data}", f"tracker={tracker}", f"data.path={tmp_path / 'none'}",
                    "progress=false"])
    with pytest.raises(ValueError, match=rf"tracker '{tracker}' needs 'imu' observations \(for "
                                         rf".*\), which the data source .* never provides "
                                         rf"\(it provides images, silhouettes.*\); track it "
                                         rf"with tracker={presets}"):
        run(cfg, tmp_path)


@pytest.mark.slow
def test_console_tracks_a_recording_from_its_videos_alone(shared_data, tmp_path):
    """A folder with only videos/ and calibration/: the command computes the keypoints and
    masks with the detector (cached under the working directory, not in the recording),
    tracks with a camera held out and scores it; without naming the detector it says how."""
    import importlib.util

    if importlib.util.find_spec("mediapipe") is None:
        msg = 'mediapipe is not installed: pip install -e ".[dev]"'
        pytest.fail(msg) if os.environ.get("CI") else pytest.skip(msg)
    src = shared_data / "multiview" / "pose2sim_balancing"
    rec = tmp_path / "rec"
    for sub in ("videos", "calibration"):
        shutil.copytree(src / sub, rec / sub)
    common = [EXE, "data=recording", f"data.path={rec}", "data.stop=3", "data.scale=0.25",
              "tracker=real_keypoints", "tracker.num_particles=30", "tracker.inference.layers=3",
              "threads=1", "progress=false", "glb.enabled=false", "overlays=1"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([*common, f"hydra.run.dir={tmp_path / 'plain'}"], capture_output=True,
                       text=True, timeout=600, cwd=tmp_path, env=env)
    assert r.returncode == 2 and "data.keypoints.source=mediapipe computes keypoints" in r.stderr
    r = subprocess.run([*common, "data.keypoints.source=mediapipe", "data.masks=detector",
                        "evaluation.heldout_camera=cam02", f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    h = saved["heldout"]
    assert h["camera"] == "cam02" and h["num_compared"] > 40 and h["median_px"] < 60
    assert h["silhouette_iou"] > 0.4 and list(saved["tracked_views"]) == ["cam01", "cam03",
                                                                          "cam04"]
    assert sorted(p.name for p in rec.iterdir()) == ["calibration", "videos"]  # untouched
    entries = list((tmp_path / "outputs" / "keypoint_cache" / "image").iterdir())
    assert len(entries) == 4 and len(list(tmp_path.joinpath("run").glob("overlay_*.png"))) == 1
