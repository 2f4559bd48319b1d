"""torchmocap-track on recordings the checks refuse or report (a view where nobody was
detected, millimetres in a metres file, too few views), a run directory that cannot be
written, and sweeps over presets (a setting every swept preset has but the default lacks; an
unknown preset named before any job runs)."""

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

from torchmocap.cli.runs import sweep_overrides
from torchmocap.cli.track import run

EXE = str(Path(sys.executable).parent / "torchmocap-track")
pytestmark = pytest.mark.filterwarnings("ignore:.*codec's crop")


def _compose(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        return compose(config_name="track", overrides=overrides)


def _console(args, cwd, timeout=600):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([EXE, *args], capture_output=True, text=True, cwd=cwd, env=env,
                          timeout=timeout)


@pytest.fixture
def recording(tmp_path, shared_data):
    root = tmp_path / "rec"
    shutil.copytree(shared_data / "multiview" / "pose2sim_balancing", root,
                    ignore=shutil.ignore_patterns("pose2sim_output"))
    return root


def _tiny(root, tmp_path, *extra):
    return ["data=recording", f"data.path={root}", "data.stop=3", "data.scale=0.25",
            f"data.mask_cache={tmp_path / 'masks'}", "tracker=real_keypoints",
            "tracker.num_particles=20", "tracker.inference.layers=2", "overlays=0",
            "glb.enabled=false", "progress=false", "threads=1", *extra]


def test_nobody_in_a_tracked_view(recording, tmp_path):
    """Every cam02 file has ``people: []`` and cam03 is held out: the run finishes, cam02's
    scores say there was nothing to compare, the warning names it; the views' agreement is in
    metrics.json."""
    for kind in ("pose-associated", "pose"):
        for p in (recording / kind / "cam02_json").glob("*.json"):
            p.write_text(json.dumps({"version": 1.3, "people": []}))
    out = tmp_path / "run"
    out.mkdir()
    m = run(_compose(_tiny(recording, tmp_path, "evaluation.heldout_camera=cam03")), out)
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["tracked_views"]["cam02"]["median_px"] is None
    assert saved["tracked_views"]["cam02"]["num_compared"] == 0
    assert saved["tracked_views"]["cam01"]["median_px"] > 0
    assert any(w.startswith("cam02: nobody detected") for w in saved["warnings"])
    vc = saved["view_consistency"]
    assert vc["views"]["cam02"]["status"] == "no detections"
    assert vc["consistent_views"] == ["cam01", "cam03", "cam04"] and m["frames"] == 3


def test_millimetres_refused_before_tracking(recording, tmp_path):
    import re

    toml = recording / "calibration" / "Calib.toml"
    toml.write_text(re.sub(r"translation = \[([^\]]*)\]", lambda m: "translation = [ " + ", ".join(
        repr(1000 * float(v)) for v in m.group(1).split(",")) + "]", toml.read_text()))
    r = _console(_tiny(recording, tmp_path, "hydra.run.dir=run"), tmp_path)
    assert r.returncode == 2
    errors = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and "data.unit" in errors[0] and "data.unit=mm" in errors[0]
    assert "Traceback" not in r.stderr and not (tmp_path / "run" / "tracked.bvh").exists()


def test_one_tracked_view_refused_first(recording, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    with pytest.raises(ValueError, match=r"data\.cameras: the tracker sees 1 view \(cam02\)"):
        run(_compose(_tiny(recording, tmp_path, "data.cameras=[cam02]")), out)


def test_unwritable_run_directory(tmp_path):
    (tmp_path / "a_file").write_text("")
    r = _console(["hydra.run.dir=a_file/run", "data.clip.frames=2"], tmp_path, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("torchmocap: error: hydra.run.dir: cannot "
                                                   "write the directory a_file/run")


def test_sweep_overrides():
    args = ["-m", "tracker=p,g", "tracker.inference.layers=3", "data.cameras=[cam01,cam03]",
            "+x=1", "hydra.sweep.dir=/s", "seed=0,1", "noise@tracker.proposal.noise=vmf"]
    assert sweep_overrides(args) == [
        "-m", "tracker=p,g", "tracker.inference.layers=choice(3)",
        "data.cameras=choice([cam01,cam03])", "+x=1", "hydra.sweep.dir=/s", "seed=0,1",
        "noise@tracker.proposal.noise=vmf"]
    # no group swept, or no multirun: unchanged
    assert sweep_overrides(["-m", "seed=0,1", "tracker.inference.layers=3"]) == \
        ["-m", "seed=0,1", "tracker.inference.layers=3"]
    assert sweep_overrides(["tracker=p", "tracker.inference.layers=3"]) == \
        ["tracker=p", "tracker.inference.layers=3"]


@pytest.mark.slow
def test_sweep_over_presets_with_their_setting(tmp_path):
    """``-m tracker=p,g tracker.inference.layers=2``: both presets have annealing layers,
    the default (LS) has none; each job runs with the setting."""
    sweep = tmp_path / "sweep"
    r = _console(["-m", "tracker=p,g", "tracker.inference.layers=2",
                  "tracker.num_particles=10", "data.clip.frames=3",
                  "+data.scenario_overrides.image_size=[80,60]", "overlays=0",
                  "glb.enabled=false", "progress=false", "threads=1",
                  f"hydra.sweep.dir={sweep}"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    runs = {json.loads(p.read_text())["tracker"]: json.loads(p.read_text())
            for p in sweep.glob("*/metrics.json")}
    assert set(runs) == {"p", "g"} and {m["layers"] for m in runs.values()} == {2}
    # a key a swept preset lacks is still that job's error (LS has no layers)
    r = _console(["-m", "tracker=ls,p", "tracker.inference.layers=2",
                  "tracker.num_particles=10", "data.clip.frames=3",
                  "+data.scenario_overrides.image_size=[80,60]", "overlays=0",
                  "glb.enabled=false", "progress=false", "threads=1",
                  f"hydra.sweep.dir={tmp_path / 'sweep2'}"], tmp_path)
    assert r.returncode != 0 and "layers" in r.stderr


def test_sweep_with_an_unknown_preset(tmp_path):
    sweep = tmp_path / "sweep"
    r = _console(["-m", "tracker=p,nope", "tracker.inference.layers=2",
                  f"hydra.sweep.dir={sweep}"], tmp_path, timeout=120)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "tracker=p,nope: no tracker option nope" in lines[0]
    assert "real_keypoints" in lines[0] and not list(sweep.glob("*/metrics.json"))
