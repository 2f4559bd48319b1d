"""torchmocap-track's contracts: settings are validated before any loading (as user errors that
name the setting, never a traceback), settings added with ``+`` that nothing reads are refused,
one live process per run directory, resume from the documented relative checkpoint, a checkpoint
of other data or settings is refused, frames without evidence are reported."""

from __future__ import annotations

import json
import os
import shutil
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
    # output settings (overlays) change what is written, not the track: resumed too
    r = _run([*args, "overlays=1", f"hydra.run.dir={tmp_path / 'd'}"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((tmp_path / "d" / "metrics.json").read_text())[
        "orientation_error_deg"] == full["orientation_error_deg"]
    assert list((tmp_path / "d").glob("overlay_*.png"))
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


def _compose(overrides):
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


@pytest.mark.parametrize("overrides, message", [
    (["tracker.num_particles=1000000000"], r"^num_particles: 1000000000 particles .* need at "
                                           r"least [\d.]+ TB, but"),
    (["tracker=p", "inference@tracker.inference=mixture"],
     r"MixtureInference takes gradients of the energy and needs the smooth silhouette term"),
    (["checkpoint=/nonexistent_dir/x/state.pt"],
     r"^checkpoint: the directory /nonexistent_dir/x does not exist"),
    (["checkpoint=state.pt", "checkpoint_every=0"], r"^checkpoint_every: expected an integer >= 1"),
    (["checkpoint=state.pt", "checkpoint_every=abc"], r"^checkpoint_every: .* got 'abc'"),
    (["seed=18446744073709551616"], r"^seed: expected an integer in \[-2\*\*63, 2\*\*64 - 1\]"),
])
def test_bad_settings_are_user_errors_before_any_loading(tmp_path, monkeypatch, overrides,
                                                         message):
    """Each once ended in a traceback (64 GB allocation, autograd error, a checkpoint directory
    found missing frames into the track, ZeroDivisionError, int('abc'), an overflow after the
    synthesis): now a user error (exit 2, one line) naming the setting, before the data (a
    missing clip here) is read."""
    from torchmocap.cli.runs import USER_ERRORS
    from torchmocap.cli.track import run

    monkeypatch.chdir(tmp_path)
    cfg = _compose(["data.clip.path=/nonexistent.bvh", *SMALL, *overrides])
    with pytest.raises(USER_ERRORS, match=message):
        run(cfg, tmp_path)


def test_asf_with_a_bvh_clip_is_refused(tmp_path, monkeypatch, shared_data):
    """``data.clip.asf`` is the skeleton of an AMC; with a BVH clip it was silently ignored."""
    from torchmocap.cli.track import run
    from torchmocap.data.synthetic.clips import DataConfigError

    shutil.copy(shared_data / "mocap" / "cmu" / "01.asf", tmp_path / "01.asf")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=r"data.clip.asf: only an .amc clip reads a separate "
                                         r"skeleton, data.clip.path is cmu_131_01_walk.bvh") as e:
        run(_compose([*SMALL, "data.clip.asf=01.asf"]), tmp_path)
    assert isinstance(e.value.__cause__, DataConfigError)


def test_console_absurd_frame_rate_is_refused_not_killed(tmp_path):
    """``data.clip.fps=1000000`` resampled the clip to millions of frames and was OOM-killed
    after 99 s without a message. Run under a 6 GB address-space limit (so that a regression
    fails here instead of exhausting the machine): a one-line error naming the setting."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (6 * 2**30, 6 * 2**30))

    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([EXE, "data.clip.fps=1000000", "overlays=0", "progress=false",
                        f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True,
                       timeout=600, env=env, cwd=tmp_path, preexec_fn=limit)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert "data.clip.fps: expected at most 1000 fps" in lines[0]


def test_console_added_setting_typo_is_refused(tmp_path):
    """``+overlay=5`` (for ``overlays``) was accepted and ignored, while ``+tracker.foo`` is
    refused by the tracker: both are errors now, naming the key."""
    r = _run([*SMALL, "+overlay=5", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "overlay: not a setting of torchmocap-track (did you mean overlays?)" in lines[0]
    assert json.loads((tmp_path / "run" / "failure.json").read_text())["type"] == "KeyError"
    r = _run([*SMALL, "+tracker.foo=1", f"hydra.run.dir={tmp_path / 'run2'}"], tmp_path)
    assert r.returncode == 2 and "foo" in r.stderr


def test_added_settings_of_components_and_groups_pass(tmp_path):
    """What ``+`` legitimately adds: a scenario key under the data source (which checks it),
    a config group (``+smoother@tracker.smoother``)."""
    from omegaconf import OmegaConf

    from torchmocap.cli.runs import check_added_settings

    class _Hydra:  # the two records check_added_settings reads
        def __init__(self, task, choices):
            self.overrides = OmegaConf.create({"task": task})
            self.runtime = OmegaConf.create({"choices": choices})

    cfg = _compose(["+data.scenario_overrides.image_size=[80,60]",
                    "+smoother@tracker.smoother=kalman", "+video.fps=3"])
    import hydra.core.hydra_config as hc

    ok = _Hydra(["+data.scenario_overrides.image_size=[80,60]",
                 "+smoother@tracker.smoother=kalman"], {"smoother@tracker.smoother": "kalman"})
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hc.HydraConfig, "initialized", staticmethod(lambda: True))
        mp.setattr(hc.HydraConfig, "get", staticmethod(lambda: ok))
        check_added_settings(cfg, "torchmocap-track")
        bad = _Hydra(["+video.fps=3"], {})
        mp.setattr(hc.HydraConfig, "get", staticmethod(lambda: bad))
        with pytest.raises(KeyError, match=r"video.fps: not a setting .*did you mean "
                                           r"video.max_fps\?"):
            check_added_settings(cfg, "torchmocap-track")


def test_warnings_are_one_line_each_and_recorded(tmp_path, capsys):
    """A loader's or tracker's warning is printed as one ``torchmocap-track: warning:`` line
    when it happens and kept in metrics.json (a sweep's stderr is easily lost); the summary
    printed without truth leaves out the input digests."""
    import re

    from torchmocap.cli.outputs import print_summary
    from torchmocap.cli.track import run
    from torchmocap.data.synthetic.clips import bundled_clip_path

    text = re.sub(r"(OFFSET )([^\n]*)", lambda m: m.group(1) + " ".join(
        repr(float(v) * 0.7) for v in m.group(2).split()), bundled_clip_path().read_text())
    (tmp_path / "child.bvh").write_text(text)  # a child's size: plausible, but worth a word
    (tmp_path / "run").mkdir()
    m = run(_compose([*SMALL, "data.clip.frames=3", f"data.clip.path={tmp_path / 'child.bvh'}",
                      "glb.enabled=false"]), tmp_path / "run")
    err = capsys.readouterr().err
    line = [x for x in err.splitlines() if "child's size" in x]
    assert len(line) == 1 and line[0].startswith("torchmocap-track: warning: ")
    assert any("child's size" in w for w in m["warnings"])
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["warnings"] == \
        m["warnings"]
    print_summary({"tracker": "x", "inputs": {"/a": "0"}, "warnings": []})
    assert "inputs" not in capsys.readouterr().out
