"""Launchers and sweepers: a tiny sweep through the submitit_local launcher (the SLURM
launcher's local twin) and aggregated; the SLURM preset composes; a tiny Optuna study of GS's
sensor-orientation weight through torchmocap-tune (training clips, then the best weight and
the preset's on held-out clips); the tune settings are added to the command line."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra

from torchmocap.cli.aggregate import aggregate_sweep
from torchmocap.cli.tune import _clip_overrides, _with_tune_settings

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
TINY = ["tracker.num_particles=20", "tracker.inference.layers=2",
        "+data.scenario_overrides.image_size=[80,60]", "overlays=0", "progress=false"]


def _console(exe, args, cwd, timeout=300):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([str(BIN / exe), *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", return_hydra_config=True,
                       overrides=[f"hydra.searchpath=[file://{ROOT / 'conf'}]", *overrides])


def test_submitit_local_launcher_runs_a_sweep(tmp_path):
    sweep = tmp_path / "sweep"
    r = _console("torchmocap-track", ["-m", "hydra/launcher=submitit_local", "seed=0,1",
                                      "data.clip.frames=3", "tracker=p", *TINY,
                                      f"hydra.sweep.dir={sweep}"],
                 tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    metrics = sorted(sweep.glob("*/metrics.json"))
    assert len(metrics) == 2
    assert {json.loads(p.read_text())["seed"] for p in metrics} == {0, 1}
    # the jobs ran as submitit jobs (their logs and pickles in the launcher's folder)
    assert list((sweep / ".submitit").glob("*/*_0_log.out"))
    table = aggregate_sweep(sweep, plots=False)["table"]
    (row,) = table.rows
    assert row["jobs"] == 2 and row["over"]["seed"] == ["0", "1"] and table.columns == []
    ori = [json.loads(p.read_text())["orientation_error_deg"]["mean"] for p in metrics]
    assert row["stats"]["orientation_error_deg.mean"][0] == pytest.approx(sum(ori) / 2)


def test_slurm_preset_composes():
    cfg = _compose(["hydra/launcher=slurm", "hydra.launcher.partition=cpu"])
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert launcher.partition == "cpu" and launcher.timeout_min == 120
    assert launcher.array_parallelism == 64 and launcher.tasks_per_node == 1
    assert any("OMP_NUM_THREADS" in line for line in launcher.setup)


def test_optuna_study_config_composes():
    cfg = _compose(["+tune=gs_orientation_weight"])
    assert cfg.tracker.name == "gs"
    assert cfg.hydra.sweeper._target_.endswith("OptunaSweeper")
    assert cfg.hydra.sweeper.direction == "minimize" and cfg.tune.direction == "minimize"
    assert "tracker.likelihood.weights.orientation" in cfg.hydra.sweeper.params
    train, heldout = set(cfg.tune.train_clips), set(cfg.tune.heldout_clips)
    assert train and heldout and not train & heldout
    for clip in train | heldout:  # every clip is an option of the repository's data/clip
        assert (ROOT / "conf" / "data" / "clip" / f"{clip}.yaml").is_file(), clip


def test_tiny_optuna_study_tunes_on_training_clips_and_reports_held_out(tmp_path):
    clips = tmp_path / "conf" / "data" / "clip"
    clips.mkdir(parents=True)
    for name, start in (("first", 0.0), ("second", 1.0)):
        (clips / f"{name}.yaml").write_text(yaml.safe_dump(
            {"name": name, "path": None, "asf": None, "skeleton_map": None, "fps": 25,
             "skip_frames": 0, "start": start, "frames": 3}))
    sweep = tmp_path / "sweep"
    r = _console("torchmocap-tune", [
        "-m", "tune=gs_orientation_weight",
        f"hydra.searchpath=[file://{ROOT / 'conf'},file://{tmp_path / 'conf'}]",
        "tune.train_clips=[first]", "tune.heldout_clips=[second]",
        "hydra.sweeper.n_trials=2", "hydra.sweeper.n_jobs=1", *TINY,
        f"sequence_cache={tmp_path / 'cache'}", f"hydra.sweep.dir={sweep}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    trials = sorted(sweep.glob("*/tune.json"))
    assert len(trials) == 2
    recs = [json.loads(p.read_text()) for p in trials]
    weights = []
    for p, rec in zip(trials, recs):  # each trial tracked the training clip only
        assert set(rec["clips"]) == {"first"} and not rec["failed"]
        m = json.loads((p.parent / "first" / "metrics.json").read_text())
        assert m["tracker"] == "gs" and m["frames"] == 3 and m["clip"]["start"] == 0.0
        assert rec["objective"] == pytest.approx(m["orientation_error_deg"]["mean"])
        (w,) = [o for o in rec["overrides"]
                if o.startswith("tracker.likelihood.weights.orientation=")]
        weights.append(float(w.split("=")[1]))
    assert len(set(weights)) == 2 and all(0.05 <= w <= 10 for w in weights)
    # Optuna's result is the trial with the lowest objective
    best = min(range(2), key=lambda i: recs[i]["objective"])
    opt = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert opt["best_value"] == pytest.approx(recs[best]["objective"])
    assert opt["best_params"]["tracker.likelihood.weights.orientation"] == pytest.approx(
        weights[best])
    # the report: the best weight and the preset's 0.5 tracked on the held-out clip
    rep = json.loads((sweep / "tune_report.json").read_text())
    assert rep["best"]["settings"] == [
        f"tracker.likelihood.weights.orientation={weights[best]}"]
    held = json.loads((sweep / "heldout" / "second" / "metrics.json").read_text())
    base = json.loads((sweep / "baseline" / "second" / "metrics.json").read_text())
    assert held["clip"]["start"] == 1.0 and base["clip"]["start"] == 1.0
    assert rep["heldout"]["clips"]["second"] == pytest.approx(
        held["orientation_error_deg"]["mean"])
    assert rep["baseline"]["clips"]["second"] == pytest.approx(
        base["orientation_error_deg"]["mean"])
    assert not any(o.startswith("tracker.likelihood.weights.orientation=")
                   for o in rep["baseline"]["overrides"])
    assert math.isfinite(rep["heldout"]["mean"])
    md = (sweep / "tune_report.md").read_text()
    assert "| held-out | second |" in md and "preset" in md


def test_tune_settings_on_the_command_line():
    assert _with_tune_settings(["-m", "a=1", "b=2"]) == ["-m", "+tune=default", "a=1", "b=2"]
    assert _with_tune_settings(["a=1", "-m", "b=2"]) == ["+tune=default", "a=1", "-m", "b=2"]
    assert _with_tune_settings(["-m"]) == ["-m", "+tune=default"]
    assert _with_tune_settings(["-m", "tune=x", "a=1"]) == ["-m", "+tune=x", "a=1"]
    assert _with_tune_settings(["+tune=x"]) == ["+tune=x"]
    assert _clip_overrides(["data/clip=a", "seed=1", "+data.clip=b", "data.clip.frames=3"],
                           "c") == ["seed=1", "data.clip.frames=3", "data/clip=c"]


def test_tune_without_training_clips_fails_cleanly(tmp_path):
    r = _console("torchmocap-tune", ["tune.train_clips=[]", f"hydra.run.dir={tmp_path / 'r'}"],
                 tmp_path)
    assert r.returncode == 2
    assert "tune.train_clips" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_tune_with_an_unknown_direction_fails_cleanly(tmp_path):
    """``tune.direction=sideways`` printed an error at the end of the run and exited 0; now it
    is refused before any clip is tracked."""
    r = _console("torchmocap-tune", ["tune.direction=sideways", "tracker=p", *TINY,
                                     f"hydra.run.dir={tmp_path / 'r'}"], tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "tune.direction: expected 'minimize' or 'maximize', got " \
        "'sideways'" in lines[0]
    assert not list((tmp_path / "r").rglob("metrics.json"))  # nothing was tracked
