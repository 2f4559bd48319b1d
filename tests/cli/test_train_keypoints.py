"""torchmocap-train --config-name train_keypoints on the trimmed real recording: a run with a
held-out camera writes the weights and the summary (cross-validation scores of the hand-set
and the learned term on the frames not trained on, the offsets in centimetres), the weights
track through term=keypoints_learned, the training is reproducible, the console runs it end to
end; bad settings are named before the recording is loaded."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.train_keypoints import run, train_frame_count
from torchmocap.likelihoods.learned import read_weights

EXE = str(Path(sys.executable).parent / "torchmocap-train")
pytestmark = pytest.mark.filterwarnings("ignore:.*codec's crop")


def _args(shared_data, *extra):
    root = shared_data / "multiview" / "pose2sim_balancing"
    return [f"data.path={root}", "data.scale=0.25", "data.subject.frames=4", "train_frames=6",
            "training.rounds=1", "training.pose_iterations=8", "training.parameter_iterations=8",
            "progress=false", *extra]


def _compose(overrides, name="train_keypoints"):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


@pytest.mark.slow
def test_heldout_training_writes_weights_and_scores(shared_data, tmp_path):
    out = tmp_path / "run"
    s = run(_compose(_args(shared_data, "evaluation.heldout_camera=cam01",
                           f"export={tmp_path / 'exported.pt'}")), out)
    saved = json.loads((out / "summary.json").read_text())
    assert saved["heldout_camera"] == "cam01" and saved["cameras"] == ["cam02", "cam03", "cam04"]
    assert saved["train_frames"] == 6 and saved["frames"] == 10
    assert saved["scored_in"] == "held-out camera"
    for name in ("hand_set", "learned"):
        sc = saved["scores"][name]
        assert sc["test"]["num_compared"] > 20 and sc["train"]["num_compared"] > 30
        assert 0 < sc["test"]["median_px"] < 200
    p = saved["parameters"]
    assert set(p["camera_scale_px"]) == {"cam02", "cam03", "cam04"}
    w = p["calibration"]["weight"]
    assert all(b >= a for a, b in zip(w, w[1:]))
    hip = p["keypoints"]["LHip"]
    assert hip["joint"] == "l_hip" and len(hip["offset_cm"]) == 3
    payload = read_weights(out / "keypoints.pt")
    assert payload["term"] == "LearnedKeypointLikelihood" and payload["cameras"] == saved["cameras"]
    assert payload["training"]["heldout_camera"] == "cam01"
    assert read_weights(tmp_path / "exported.pt")["cameras"] == saved["cameras"]
    assert "learned: test frames" in s["report"]
    # reproducible: the same run twice gives the same parameters
    run(_compose(_args(shared_data, "evaluation.heldout_camera=cam01", "evaluate=false")),
        tmp_path / "again")
    again = read_weights(tmp_path / "again" / "keypoints.pt")["state_dict"]
    for k, v in payload["state_dict"].items():
        assert torch.equal(v, again[k]), k


@pytest.mark.slow
def test_weights_track_through_the_learned_term(shared_data, tmp_path):
    """The weights of a held-out run load into a tracker of the same cameras
    (term@tracker.likelihood.terms.keypoints=keypoints_learned), whose held-out view is scored
    with the learned offsets."""
    from torchmocap.cli.track import run as track

    run(_compose(_args(shared_data, "evaluation.heldout_camera=cam01", "evaluate=false")),
        tmp_path / "train")
    weights = tmp_path / "train" / "keypoints.pt"
    root = shared_data / "multiview" / "pose2sim_balancing"
    cfg = _compose([
        "data=recording", f"data.path={root}", "data.stop=5", "data.scale=0.25",
        "data.subject.frames=4", "data.masks=none", "tracker=real_local",
        "tracker.inference.iterations=5", "evaluation.heldout_camera=cam01", "progress=false",
        "overlays=0", "term@tracker.likelihood.terms.keypoints=keypoints_learned",
        f"tracker.likelihood.terms.keypoints.weights={weights}"], name="track")
    (tmp_path / "track").mkdir()
    m = track(cfg, tmp_path / "track")
    assert m["heldout"]["num_compared"] > 10
    learned = json.loads((tmp_path / "train" / "summary.json").read_text())["parameters"]
    mapped = m["heldout"]["keypoint_mapping"]
    moved = [n for n, k in learned["keypoints"].items() if k["change_norm_cm"] > 0.05]
    assert moved
    for n, k in learned["keypoints"].items():
        torch.testing.assert_close(torch.tensor(mapped[n]["offset"]) * 100,
                                   torch.tensor(k["offset_cm"]), atol=0.006, rtol=0)


@pytest.mark.parametrize("extra,match", [
    (["train_frames=1.5"], r"train_frames: expected a fraction in \(0, 1\] or a frame count"),
    (["train_frames=1"], r"train_frames"),
    (["training.rounds=0"], r"training\.rounds: expected an integer >= 1"),
    (["+training.epochs=3"], r"training: unknown settings \['epochs'\]"),
    (["training.joint=maybe"], r"training\.joint: expected true or false"),
    (["evaluation.heldout_camera=cam09"], r"evaluation\.heldout_camera: unknown camera"),
])
def test_bad_settings_are_named(shared_data, tmp_path, extra, match):
    with pytest.raises(ValueError, match=match):
        run(_compose(_args(shared_data, *extra)), tmp_path)


def test_a_term_that_is_not_learned_is_refused(shared_data, tmp_path):
    cfg = _compose(_args(shared_data, "term._target_=torchmocap.likelihoods.KeypointLikelihood"))
    with pytest.raises(ValueError, match=r"term: torchmocap\.likelihoods\.KeypointLikelihood is "
                                         r"not a LearnedKeypointLikelihood"):
        run(cfg, tmp_path)


def test_train_frame_count():
    assert train_frame_count(0.6, 100) == 60 and train_frame_count(1.0, 7) == 7
    assert train_frame_count(30, 100) == 30
    for bad in (0.0, -0.5, 1, 101, True, float("nan"), "half"):
        with pytest.raises(ValueError, match="train_frames"):
            train_frame_count(bad, 100)


@pytest.mark.slow
def test_console_trains_end_to_end(shared_data, tmp_path):
    r = subprocess.run([EXE, "--config-name", "train_keypoints",
                        *_args(shared_data, "evaluation.heldout_camera=cam02"),
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "torchmocap-train: 6 of 10 frames of ['cam01', 'cam03', 'cam04']" in r.stderr
    assert (tmp_path / "run" / "keypoints.pt").is_file()
    bad = subprocess.run([EXE, "--config-name", "train_keypoints",
                          *_args(shared_data, "train_frames=0")], capture_output=True,
                         text=True, cwd=tmp_path)
    assert bad.returncode == 2 and "train_frames" in bad.stderr
