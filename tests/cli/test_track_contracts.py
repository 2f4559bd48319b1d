"""torchmocap-track's contracts: settings are validated before any loading, one live process per
run directory, resume from the documented relative checkpoint, a checkpoint of other data or
settings is refused, frames without evidence are reported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchmocap.cli.runs import RunLockError, acquire_lock, release_lock

EXE = str(Path(sys.executable).parent / "torchmocap-track")
SMALL = ["tracker=p", "tracker.num_particles=20", "tracker.inference.layers=2",
         "+data.scenario_overrides.image_size=[80,60]", "overlays=0", "progress=false"]


def _run(args, cwd, timeout=600):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout,
                          env=env, cwd=cwd)


def test_settings_are_validated_before_the_data_is_read(tmp_path):
    # the clip does not exist either: the settings error must come first
    r = _run(["tracker.num_particles=0", "data.clip.path=/nonexistent.bvh",
              f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert r.returncode == 2 and "num_particles" in r.stderr and "nonexistent" not in r.stderr
    r = _run(["seed=abc", f"hydra.run.dir={tmp_path / 'run2'}"], tmp_path)
    assert r.returncode == 2 and "seed" in r.stderr.splitlines()[-1]


def test_run_directory_lock(tmp_path):
    d = tmp_path / "run"
    lock = acquire_lock(d)
    assert lock.read_text() == str(os.getpid())
    acquire_lock(d)  # the same process may take it again
    # a live other process holds it: refused
    lock.write_text(str(os.getppid()))
    with pytest.raises(RunLockError, match="in use by process"):
        acquire_lock(d)
    # a dead process's lock is taken over
    lock.write_text("999999999")
    acquire_lock(d)
    release_lock(d)
    assert not lock.exists()


def test_a_second_run_into_a_busy_directory_is_refused(tmp_path):
    d = tmp_path / "run"
    first = subprocess.Popen([EXE, "data.clip.frames=6", *SMALL, f"hydra.run.dir={d}"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp_path,
                             env=dict(os.environ, OMP_NUM_THREADS="1"))
    try:
        for _ in range(200):  # wait until the first run holds the lock
            if (d / ".torchmocap.lock").exists():
                break
            time.sleep(0.05)
        r = _run(["tracker=g", "data.clip.frames=3", *SMALL, f"hydra.run.dir={d}"], tmp_path)
        assert r.returncode == 2 and "in use by process" in r.stderr
    finally:
        assert first.wait(timeout=600) == 0
    overrides = (d / ".hydra" / "overrides.yaml").read_text()
    assert "tracker=g" not in overrides  # the refused run wrote nothing there
    assert json.loads((d / "metrics.json").read_text())["tracker"] == "p"


@pytest.mark.slow
def test_resume_from_the_documented_checkpoint_and_refuse_other_data(tmp_path):
    """`checkpoint=state.pt` is relative to the working directory: running the same command
    again resumes; a checkpoint of another clip or of other settings is refused."""
    args = ["data.clip.frames=8", *SMALL, "checkpoint=state.pt", "checkpoint_every=2"]
    r = _run([*args, f"hydra.run.dir={tmp_path / 'a'}"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "state.pt").is_file()
    full = json.loads((tmp_path / "a" / "metrics.json").read_text())
    # the finished checkpoint resumes at its end: the same track, nothing recomputed
    r = _run([*args, f"hydra.run.dir={tmp_path / 'b'}"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    again = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert again["orientation_error_deg"] == full["orientation_error_deg"]
    for other in (["data.clip.start=0.4"], ["tracker.num_particles=21"]):
        r = _run([*args, *other, f"hydra.run.dir={tmp_path / 'c'}"], tmp_path)
        assert r.returncode == 2 and "checkpoint" in r.stderr and "fingerprint" in r.stderr
        assert not (tmp_path / "c" / "metrics.json").exists()


@pytest.mark.slow
def test_frames_without_evidence_are_counted(tmp_path):
    r = _run(["data.clip.frames=4", *SMALL, "+data.scenario_overrides.silhouettes.drop_view=1.0",
              "data.scenario=outdoor", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["frames_without_evidence"].get("silhouette", 0) >= 1
    assert "without usable evidence" in r.stderr
