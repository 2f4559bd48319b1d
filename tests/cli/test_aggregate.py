"""torchmocap-aggregate: on a fabricated multirun directory the table's mean ± std equal
numpy's over the seeds of each group of swept overrides; fixed overrides, failed jobs, nested
and Hydra-less job directories; plots; typed errors naming the argument; the console script."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from torchmocap.cli.aggregate import (
    SweepAggregateError,
    aggregate,
    aggregate_sweep,
    find_jobs,
    main,
    metric_value,
)

EXE = str(Path(sys.executable).parent / "torchmocap-aggregate")
TRACKERS, PARTICLES, SEEDS = ("p", "gs"), (25, 100, 400), (0, 1, 2)


def _job(root: Path, name: str, overrides: list[str] | None, metrics: dict) -> Path:
    d = root / name
    d.mkdir(parents=True)
    if overrides is not None:
        (d / ".hydra").mkdir()
        (d / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (d / "metrics.json").write_text(json.dumps(metrics))
    return d


@pytest.fixture
def sweep(tmp_path):
    """A multirun directory: trackers x particle counts x seeds, one job without MPJPE, and
    one failed job; returns the directory and the values per (tracker, particles)."""
    rng = np.random.default_rng(0)
    root = tmp_path / "multirun"
    values: dict[tuple, dict[str, list]] = {}
    i = 0
    for t in TRACKERS:
        for n in PARTICLES:
            for s in SEEDS:
                ori, mp, sec = rng.uniform(5, 40), rng.uniform(50, 200), rng.uniform(0.1, 2)
                m = {"tracker": t, "seed": s, "seconds_per_frame": sec,
                     "orientation_error_deg": {"mean": ori, "std": 1.0},
                     "mpjpe_mm": {"mean": mp}, "frames": 3}
                if (t, n, s) == ("gs", 400, 2):
                    del m["mpjpe_mm"]
                v = values.setdefault((t, str(n)), {"ori": [], "mp": [], "sec": []})
                v["ori"].append(ori)
                v["sec"].append(sec)
                if "mpjpe_mm" in m:
                    v["mp"].append(mp)
                _job(root, f"{i}_n={n},s={s},t={t}",
                     [f"tracker={t}", f"tracker.num_particles={n}", f"seed={s}",
                      "data.clip.frames=3", "+data.scenario_overrides.image_size=[80,60]"], m)
                i += 1
    bad = root / f"{i}_broken"
    bad.mkdir()
    (bad / "failure.json").write_text(json.dumps({"error": "boom"}))
    return root, values


def _rows(csv_path: Path) -> list[dict]:
    return list(csv.DictReader(io.StringIO(csv_path.read_text())))


class TestAggregate:
    def test_feature_mean_std_equal_numpy(self, sweep, tmp_path):
        root, values = sweep
        res = aggregate_sweep(root, tmp_path / "out")
        rows = _rows(res["csv"])
        assert len(rows) == len(TRACKERS) * len(PARTICLES)
        for r in rows:
            v = values[(r["tracker"], r["tracker.num_particles"])]
            for key, name in (("ori", "orientation_error_deg.mean"), ("mp", "mpjpe_mm.mean"),
                              ("sec", "seconds_per_frame")):
                assert float(r[f"{name}_mean"]) == pytest.approx(np.mean(v[key]), rel=1e-12)
                assert float(r[f"{name}_std"]) == pytest.approx(np.std(v[key]), rel=1e-9,
                                                                abs=1e-12)
                assert int(r[f"{name}_n"]) == len(v[key])
            assert r["jobs"] == "3" and r["seed"] == "0;1;2"
        # ordered by the swept values (numbers numerically)
        assert [(r["tracker"], int(r["tracker.num_particles"])) for r in rows] == sorted(
            [(t, n) for t in TRACKERS for n in PARTICLES])

    def test_cardinality_columns_fixed_and_failed(self, sweep):
        root, _ = sweep
        jobs, failed = find_jobs(root)
        assert len(jobs) == 18 and [p.name for p in failed] == ["18_broken"]
        table = aggregate(jobs, failed=failed)
        assert table.columns == ["tracker", "tracker.num_particles"]
        assert table.fixed == {"data.clip.frames": "3",
                               "data.scenario_overrides.image_size": "[80,60]"}
        assert table.metrics == ["orientation_error_deg.mean", "mpjpe_mm.mean",
                                 "seconds_per_frame"]  # the defaults that some job has

    def test_markdown_and_plots(self, sweep):
        root, values = sweep
        res = aggregate_sweep(root)
        md = res["markdown"].read_text()
        assert res["markdown"].parent == root and "1 failed" in md
        assert "`data.clip.frames=3`" in md
        lines = [ln for ln in md.splitlines() if ln.startswith("| gs | 400 |")]
        assert len(lines) == 1 and "(2)" in lines[0]  # two of three jobs report MPJPE
        mean = np.mean(values[("p", "25")]["ori"])
        assert f"{mean:.4g} ±" in md
        assert len(res["plots"]) == 3
        for p in res["plots"]:
            with Image.open(p) as im:
                assert im.format == "PNG" and im.size[0] > 100
        assert not [p for p in root.iterdir() if p.name.startswith(".aggregate")]

    def test_metric_option(self, sweep, tmp_path):
        root, values = sweep
        res = aggregate_sweep(root, tmp_path, metrics=["orientation_error_deg.std"],
                              plots=False)
        rows = _rows(res["csv"])
        assert [k for k in rows[0] if k.endswith("_mean")] == ["orientation_error_deg.std_mean"]
        assert all(float(r["orientation_error_deg.std_mean"]) == 1.0 for r in rows)
        assert res["plots"] == []

    def test_over_option_pools_another_setting(self, sweep, tmp_path):
        root, values = sweep
        res = aggregate_sweep(root, tmp_path, over=["seed", "tracker.num_particles"],
                              plots=False)
        rows = _rows(res["csv"])
        assert [r["tracker"] for r in rows] == ["gs", "p"]
        for r in rows:
            pooled = sum((values[(r["tracker"], str(n))]["ori"] for n in PARTICLES), [])
            assert float(r["orientation_error_deg.mean_mean"]) == pytest.approx(np.mean(pooled))
            assert r["jobs"] == "9"

    def test_nested_parts_and_hydraless_runs(self, tmp_path):
        # a torchmocap-tune trial: the job's overrides, one metrics.json per clip below it
        root = tmp_path / "tune"
        for i, w in enumerate((0.5, 2.0)):
            job = _job(root, str(i), [f"tracker.likelihood.weights.orientation={w}"], {})
            (job / "metrics.json").unlink()
            for clip, v in (("boxing", 10 + w), ("salsa", 20 + w)):
                _job(job, clip, None, {"orientation_error_deg": {"mean": v}, "seed": 0})
        rows = _rows(aggregate_sweep(root, plots=False)["csv"])
        assert [(r["tracker.likelihood.weights.orientation"], r["part"]) for r in rows] == [
            ("0.5", "boxing"), ("0.5", "salsa"), ("2.0", "boxing"), ("2.0", "salsa")]
        # committed runs keep only metrics.json: named by their path without the seed part
        root = tmp_path / "fig"
        for clip in ("walking", "kicking"):
            for s in (0, 1):
                _job(root, f"{clip}/gs/seed{s}", None,
                     {"orientation_error_deg": {"mean": 10.0 * s + len(clip)}, "seed": s})
        rows = _rows(aggregate_sweep(root, plots=False)["csv"])
        assert [(r["run"], r["jobs"], r["seed"]) for r in rows] == [
            ("kicking/gs", "2", "0;1"), ("walking/gs", "2", "0;1")]
        assert float(rows[1]["orientation_error_deg.mean_mean"]) == 12.0
        assert float(rows[1]["orientation_error_deg.mean_std"]) == 5.0

    def test_metric_value(self):
        m = {"a": {"b": 2, "c": True, "d": [1]}, "e": 1.5}
        assert metric_value(m, "a.b") == 2.0 and metric_value(m, "e") == 1.5
        assert metric_value(m, "a.c") is None and metric_value(m, "a.d") is None
        assert metric_value(m, "a.x") is None and metric_value(m, "e.f") is None

    def test_exception(self, tmp_path, sweep):
        with pytest.raises(SweepAggregateError, match="multirun_dir.*does not exist"):
            aggregate_sweep(tmp_path / "nope")
        (tmp_path / "file").write_text("x")
        with pytest.raises(SweepAggregateError, match="multirun_dir.*not a directory"):
            aggregate_sweep(tmp_path / "file")
        (tmp_path / "empty").mkdir()
        with pytest.raises(SweepAggregateError, match="multirun_dir: no job"):
            aggregate_sweep(tmp_path / "empty")
        only_failed = tmp_path / "failed" / "0_x"
        only_failed.mkdir(parents=True)
        (only_failed / "failure.json").write_text("{}")
        with pytest.raises(SweepAggregateError, match="multirun_dir: no job.*1 failed"):
            aggregate_sweep(tmp_path / "failed")
        root, _ = sweep
        with pytest.raises(SweepAggregateError, match="metric: 'nope'.*available:.*mpjpe"):
            aggregate_sweep(root, tmp_path / "o", metrics=["nope"])
        with pytest.raises(SweepAggregateError, match="over"):
            aggregate_sweep(root, tmp_path / "o", over="seed")
        broken = tmp_path / "broken" / "0"
        broken.mkdir(parents=True)
        (broken / "metrics.json").write_text("{not json")
        with pytest.raises(SweepAggregateError, match="multirun_dir: unreadable"):
            aggregate_sweep(tmp_path / "broken")
        assert issubclass(SweepAggregateError, ValueError)


class TestConsole:
    def test_main(self, sweep, tmp_path, capsys):
        root, _ = sweep
        assert main([str(root), "--out", str(tmp_path / "o"), "--no-plots"]) == 0
        out = capsys.readouterr()
        assert out.out.startswith("# Sweep multirun") and "| p | 25 | 3 |" in out.out
        assert main([str(tmp_path / "nope")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("torchmocap-aggregate: error: multirun_dir:")
        (tmp_path / "a_file").write_text("x")  # was '[Errno 17] File exists'
        assert main([str(root), "--out", str(tmp_path / "a_file"), "--no-plots"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"torchmocap-aggregate: error: --out: cannot write the tables into "
                       f"{tmp_path / 'a_file'} (a file, not a directory)"]

    def test_console_script(self, sweep, tmp_path):
        root, _ = sweep
        env = dict(os.environ, OMP_NUM_THREADS="1")
        r = subprocess.run([EXE, str(root), "--metric", "seconds_per_frame", "--no-plots"],
                           capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 0, r.stderr
        assert (root / "aggregate.csv").is_file() and "seconds_per_frame" in r.stdout
        r = subprocess.run([EXE, str(tmp_path / "empty_dir_that_is_missing")],
                           capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 2 and "multirun_dir" in r.stderr
