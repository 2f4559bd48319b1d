"""Every experiment config of the repository's conf/experiment runs (a few frames, tiny budget),
and its report script reads the runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
EXE = str(Path(sys.executable).parent / "torchmocap-track")
EXPERIMENTS = sorted(p.relative_to(ROOT / "conf" / "experiment").with_suffix("").as_posix()
                     for p in (ROOT / "conf" / "experiment").rglob("*.yaml"))


def _vendored_clip(clip: str, data: Path) -> list[str]:
    """Overrides reading a clip config's ``../shared/data/...`` files from the trimmed copies
    in ``data`` (tests/data_files), from their first frame (the copies are short)."""
    if not clip:
        return []
    cfg = yaml.safe_load((ROOT / "conf" / "data" / "clip" / f"{clip}.yaml").read_text())
    out = []
    for key in ("path", "asf"):
        v = cfg.get(key)
        if v and "shared/data/" in v:
            p = data / v.split("shared/data/", 1)[1]
            assert p.is_file(), p
            out.append(f"data.clip.{key}={p}")
    return out + ["data.clip.start=0.0"] if out else out


def test_experiment_configs_exist():
    assert {"ponsmoll2010/fig8", "ponsmoll2010/fig9a", "ponsmoll2010/fig10",
            "ponsmoll2010/control"} <= set(EXPERIMENTS)


@pytest.mark.slow
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_config_runs_for_three_frames(name, tmp_path, shared_data):
    from torchmocap.assembly import tracker_config

    spec = yaml.safe_load((ROOT / "conf" / "experiment" / f"{name}.yaml").read_text())
    params = spec["hydra"]["sweeper"]["params"]
    # one seed, one clip, one scenario (every scenario runs in some experiment's other choices)
    one = ("seed", "data/clip", "data.scenario")
    narrow = [f"{k}={str(v).split(',')[0]}" for k, v in params.items() if k in one]
    narrow += _vendored_clip(str(params.get("data/clip", "")).split(",")[0], shared_data)
    if str(params.get("data", "")) == "bodytrack":  # the real frame: no clip, one frame
        root = shared_data / "multiview" / "bodytrack_sequenceB_1"
        data = ["data=bodytrack", f"data.path={root}", "data.scale=0.5",
                "++tracker.inference.rounds=1"]
        frames = 1
    else:
        data = ["data.clip.frames=3", "++data.scenario_overrides.image_size=[80,60]"]
        frames = 3
    sweep = tmp_path / "sweep"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    trackers = str(params.get("tracker", "p")).split(",")
    n_jobs = 1  # per tracker (the budget below replaces a particle-count sweep)
    for k, v in params.items():
        if k not in (*one, "tracker", "tracker.num_particles"):
            n_jobs *= len(str(v).split(","))
    groups: dict[tuple[str, ...], list[str]] = {}
    for t in trackers:  # a tiny budget: annealing layers or descent steps
        kind = tracker_config(t).inference._target_.rsplit(".", 1)[-1]
        budget = {"LocalInference": ("tracker.inference.iterations=2",),
                  "SIRInference": ("tracker.num_particles=12",)}.get(
            kind, ("tracker.num_particles=12", "tracker.inference.layers=2"))
        groups.setdefault(budget, []).append(t)
    # one sweep per budget: its trackers share a process; "++" because the sweep's base config
    # (the default tracker) may lack a key that every job of the group has
    for budget, ts in groups.items():
        budget = tuple(f"++{b}" for b in budget)
        r = subprocess.run([EXE, "-m", f"+experiment={name}", *narrow, f"tracker={','.join(ts)}",
                            *data, *budget, f"sequence_cache={tmp_path / 'cache'}",
                            f"hydra.sweep.dir={sweep}"],
                           capture_output=True, text=True, timeout=900, env=env, cwd=ROOT)
        assert r.returncode == 0, (ts, r.stderr[-3000:])
    metrics = list(sweep.rglob("metrics.json"))
    assert len(metrics) == n_jobs * len(trackers)
    small = {tracker_config(t).name for b, ts in groups.items() for t in ts
             if "tracker.num_particles=12" in b}
    for m in metrics:
        m = json.loads(m.read_text())
        assert m["frames"] == frames
        if m["tracker"] in small:  # the budget reached every job of its sweep
            assert m["num_particles"] == 12, m["tracker"]
    if name.startswith("smoothing/"):  # the smoothing report reads these runs
        r = subprocess.run([sys.executable, str(ROOT / "experiments" / "smoothing" / "report.py"),
                            "--runs", str(sweep), "--out", str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
        assert r.returncode == 0, r.stderr[-3000:]
        md = (tmp_path / "out" / "kalman.md").read_text()
        assert all(f"`{tracker_config(t).name}` | mean |" in md for t in trackers), md
    if name == "smoothing/kalman":  # so does the fixed-lag table
        r = subprocess.run([sys.executable, str(ROOT / "experiments" / "smoothing" / "lag.py"),
                            "--runs", str(sweep), "--out", str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
        assert r.returncode == 0, r.stderr[-3000:]
        md = (tmp_path / "out" / "lag.md").read_text()
        assert "| filtered | lag 0 | lag 1 | lag 2 | lag 5 | whole clip |" in md, md
        assert all(f"| `{tracker_config(t).name}` | {n_jobs} |" in md for t in trackers), md
        assert (tmp_path / "out" / "lag.png").stat().st_size > 0
    if frames == 1:  # the real frame's report reads these runs
        r = subprocess.run([sys.executable, str(ROOT / "experiments" / "hauberg2011" / "report.py"),
                            "bodytrack", "--runs", str(sweep), "--out", str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
        assert r.returncode == 0, r.stderr[-3000:]
        md = (tmp_path / "out" / "bodytrack.md").read_text()
        assert all(f"(`{t}`)" in md for t in trackers)
