"""torchmocap-track: every tracker config composes; in-process and console runs; sweeps; errors."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.track import run
from torchmocap.filters.tracker import TrackerConfig

TRACKERS = ["p", "p_gaussian", "p_nonoise", "g", "gs", "rs", "l", "ls"]
EXE = shutil.which("torchmocap-track")


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


@pytest.mark.parametrize("name", TRACKERS)
def test_every_tracker_config_composes_and_builds(name):
    from omegaconf import OmegaConf

    cfg = _compose([f"tracker={name}"])
    tc = TrackerConfig(**OmegaConf.to_container(cfg.tracker))
    assert tc.num_particles == 200 and tc.layers == 15
    expected = {"p_gaussian": ("p", "gaussian"), "p_nonoise": ("p", "none"), "p": ("p", "vmf")}
    if name in expected:
        assert (tc.method, tc.noise) == expected[name]
    else:
        assert tc.method == name
    assert cfg.data.scenario == "studio" and cfg.seed == 0


def test_bodytrack_data_config_composes():
    cfg = _compose(["data=bodytrack"])
    assert cfg.data.kind == "bodytrack" and "bodytrack_sequenceB_1" in cfg.data.path


def test_in_process_run_writes_outputs(tmp_path):
    cfg = _compose(["data.clip.frames=6", "tracker.num_particles=30", "tracker.layers=3",
                    "progress=false", "overlays=2", "data.scenario=clean"])
    m = run(cfg, tmp_path)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved == json.loads(json.dumps(m))
    for key in ("frames", "seconds_per_frame", "orientation_error_deg", "mpjpe_mm"):
        assert key in saved
    assert saved["frames"] == 6
    assert set(saved["orientation_error_deg"]) == {"mean", "std", "per_bone"}
    assert set(saved["orientation_error_deg"]["per_bone"]) == {
        "spine", "l_shoulder", "r_shoulder", "l_hip", "r_hip"}
    assert 0 <= saved["orientation_error_deg"]["mean"] < 45
    assert (tmp_path / "track.npz").is_file() and (tmp_path / "errors.png").is_file()
    assert len(list(tmp_path.glob("overlay_*.png"))) == 2
    from torchmocap.io import load_motion

    back = load_motion(tmp_path / "tracked.bvh")
    assert back.num_frames == 6


@pytest.mark.skipif(EXE is None, reason="console script not installed")
def test_console_unreadable_clip_fails_cleanly(tmp_path):
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    r = subprocess.run([EXE, f"data.clip.path={bad}", f"hydra.run.dir={tmp_path / 'run'}"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert "torchmocap-track: error" in r.stderr and "bad.bvh" in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.skipif(EXE is None, reason="console script not installed")
def test_console_missing_imus_fails_cleanly(tmp_path):
    scen = tmp_path / "noimu.yaml"
    scen.write_text("name: noimu\nrig: ring4\nimage_size: [80, 60]\nimu: {enabled: false}\n"
                    "depth: {enabled: false}\njoints2d: {enabled: false}\n")
    r = subprocess.run([EXE, f"data.scenario={scen}", "data.clip.frames=3",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stderr
    assert "IMU" in r.stderr
    assert not (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.slow
@pytest.mark.skipif(EXE is None, reason="console script not installed")
def test_console_multirun_sweep(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([EXE, "-m", "tracker=p,g", "data.clip.frames=4",
                        "tracker.num_particles=20", "tracker.layers=2", "overlays=0",
                        "progress=false", f"hydra.sweep.dir={tmp_path}"],
                       capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    metrics = sorted(Path(tmp_path).glob("*/metrics.json"))
    assert len(metrics) == 2
    assert {json.loads(p.read_text())["method"] for p in metrics} == {"p", "g"}
    assert sys.executable  # the sweep used the installed entry point
