"""What the commands share (torchmocap.cli.runs): a run or a cached sequence is up to date only
while every input file its data source read is unchanged — the files no setting names (a
scenario's base chain, the ASF beside an AMC, a recording's keypoint files and folders)
included; a sequence cache that is not a directory is refused."""

from __future__ import annotations

import json
import shutil
import warnings

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

TINY = ["tracker=p", "tracker.num_particles=12", "tracker.inference.layers=1", "overlays=0",
        "progress=false", "glb.enabled=false"]


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


def test_a_changed_base_scenario_reruns_the_run(tmp_path):
    """The run names only ``child.yaml``; its ``base:`` changes: not up to date any more."""
    from torchmocap.cli.track import run

    base = tmp_path / "base.yaml"
    base.write_text("base: clean\nimage_size: [80, 60]\n")
    (tmp_path / "child.yaml").write_text(f"base: {base}\n")
    cfg = _compose([*TINY, "data.clip.frames=3", f"data.scenario={tmp_path / 'child.yaml'}"])
    out = tmp_path / "run"
    out.mkdir()
    first = run(cfg, out)
    assert str(base) in first["inputs"]
    mtime = (out / "track.npz").stat().st_mtime_ns
    assert run(cfg, out) == first  # unchanged: skipped
    assert (out / "track.npz").stat().st_mtime_ns == mtime
    base.write_text("base: clean\nimage_size: [80, 60]\nimages: {pixel_noise: 9.0}\n")
    again = run(cfg, out)
    assert (out / "track.npz").stat().st_mtime_ns != mtime  # tracked again
    assert again["fingerprint"] != first["fingerprint"]
    assert again["inputs"][str(base)] != first["inputs"][str(base)]


def test_the_sequence_cache_is_rebuilt_when_the_asf_beside_the_amc_changes(tmp_path,
                                                                           shared_data):
    from torchmocap.assembly import load_sequence

    for f in ("01.asf", "01_01.amc"):
        shutil.copy(shared_data / "mocap" / "cmu" / f, tmp_path / f)
    cfg = _compose([f"data.clip.path={tmp_path / '01_01.amc'}", "data.clip.frames=3",
                    "+data.scenario_overrides.image_size=[80,60]",
                    f"sequence_cache={tmp_path / 'cache'}"])
    first = load_sequence(cfg)
    cached = load_sequence(cfg)
    assert cached.meta.inputs == first.meta.inputs
    assert cached.ground_truth.positions.equal(first.ground_truth.positions)
    asf = tmp_path / "01.asf"
    text = asf.read_text(encoding="latin-1")
    assert "length 0.45" in text
    asf.write_text(text.replace("length 0.45", "length 0.5"), encoding="latin-1")  # 10 % shorter
    rebuilt = load_sequence(cfg)
    assert rebuilt.meta.inputs[str(asf)] != first.meta.inputs[str(asf)]
    a, b = (s.ground_truth.positions[0].double() for s in (first, rebuilt))
    ratio = (b[:, 2].max() - b[:, 2].min()) / (a[:, 2].max() - a[:, 2].min())
    assert ratio == pytest.approx(0.45 / 0.5, rel=1e-3)


def test_a_recording_run_is_stale_when_a_keypoint_file_or_folder_changes(tmp_path,
                                                                         shared_data):
    """``completed_run`` takes the digests of the recorded inputs again: one edited keypoint
    file, or a mask folder added to the recording (``masks: auto`` would read it), makes the
    run stale."""
    from torchmocap.assembly import load_sequence
    from torchmocap.cli.runs import completed_run, run_fingerprint

    rec = tmp_path / "rec"
    shutil.copytree(shared_data / "multiview" / "pose2sim_balancing", rec,
                    ignore=shutil.ignore_patterns("background", "pose2sim_output"))
    cfg = _compose(["data=recording", f"data.path={rec}", "data.stop=2", "data.scale=0.25",
                    "data.cameras=[cam01,cam03]"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # cam01's codec crop
        inputs = load_sequence(cfg).meta.inputs
    kp = rec / "pose-associated" / "cam03_json"
    assert {str(rec / "videos" / "cam01.mp4"), str(rec / "calibration" / "Calib.toml"),
            str(kp / "cam03.0001.json"), str(kp), str(rec)} <= set(inputs)
    assert str(kp / "cam03.0002.json") not in inputs  # frame 2 is not read
    out = tmp_path / "run"
    out.mkdir()
    metrics = {"fingerprint": run_fingerprint("settings", inputs), "inputs": inputs}
    (out / "metrics.json").write_text(json.dumps(metrics))
    assert completed_run(out, "settings") == metrics
    assert completed_run(out, "other settings") is None
    f = kp / "cam03.0001.json"
    data = json.loads(f.read_text())
    data["people"][0]["pose_keypoints_2d"][0] += 1.0
    f.write_text(json.dumps(data))
    assert completed_run(out, "settings") is None
    f.write_text(json.dumps(json.loads(f.read_text())))  # same values: stale all the same
    (tmp_path / "saved.json").write_text(json.dumps(metrics))
    (rec / "masks").mkdir()
    metrics2 = {"fingerprint": run_fingerprint("settings", {str(rec): inputs[str(rec)]}),
                "inputs": {str(rec): inputs[str(rec)]}}
    (out / "metrics.json").write_text(json.dumps(metrics2))
    assert completed_run(out, "settings") is None  # the folder's listing changed


def test_exception_sequence_cache_that_is_a_file(tmp_path):
    from torchmocap.cli.track import run

    (tmp_path / "cache").write_text("not a folder")
    cfg = _compose([*TINY, "data.clip.frames=3", f"sequence_cache={tmp_path / 'cache'}"])
    with pytest.raises(NotADirectoryError, match=r"^sequence_cache: .*cache is a file"):
        run(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.json").exists()
