"""experiments/hauberg2011/report.py turns a sweep's metrics.json files into its tables: means
and seed spreads, ESS and time ratios to the angular prior, missing runs listed."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _write(d: Path, err: float, ess: float, t: float, rej: float | None = None) -> None:
    d.mkdir(parents=True)
    m = {"marker_error_mm": {"mean": err}, "mpjpe_mm": {"mean": 2 * err}, "ess_mean": ess,
         "seconds_per_frame": t, "proposal_mean": {}}
    if rej is not None:
        m["proposal_mean"]["rejections_per_sample"] = rej
    (d / "metrics.json").write_text(json.dumps(m))


def test_importance_table_and_ratios(tmp_path, load_script):
    rep = load_script("hauberg2011/report.py")
    runs = tmp_path / "runs"
    errs = {"hauberg_angular": [30.0, 32.0, 34.0], "hauberg_depth": [20.0, 21.0, 25.0]}
    for t, es in errs.items():
        for s, e in enumerate(es):
            ess = 2.0 if t == "hauberg_angular" else 6.0
            time = 0.2 if t == "hauberg_angular" else 0.22
            _write(runs / "swim" / t / "n50" / f"seed{s}", e, ess + s, time)
    out = tmp_path / "out"
    assert rep.main(["importance", "--runs", str(runs), "--out", str(out)]) == 0
    md = (out / "importance.md").read_text()
    sd = statistics.stdev(errs["hauberg_depth"])
    assert f"| depth-driven (eq. 14) | 50 | 22.0 ± {sd:.1f} |" in md
    assert "| ×2.33 |" in md and "| ×1.10 |" in md  # ESS 7 / 3, time 0.22 / 0.2
    assert (out / "importance.png").stat().st_size > 1000
    assert "Missing runs (90)" in md and "swim/hauberg_angular/n25/seed0" in md
    assert "grab high" not in md  # a clip without runs has no section


def test_rejection_counts_and_no_runs(tmp_path, load_script):
    rep = load_script("hauberg2011/report.py")
    runs = tmp_path / "runs"
    for s in range(3):
        _write(runs / "swim" / "hauberg_rejection" / "n25" / f"seed{s}", 40.0, 1.0, 2.0,
               rej=6000.0 + 100 * s)
    out = tmp_path / "out"
    assert rep.main(["rejection", "--runs", str(runs), "--out", str(out)]) == 0
    md = (out / "rejection.md").read_text()
    assert "| rejection-sampled (eq. 4) | 25 | 40.0 ± 0.0 |" in md
    assert "6100 ± 100" in md
    assert rep.main(["rejection", "--runs", str(tmp_path / "empty"), "--out", str(out)]) == 2


@pytest.mark.parametrize("sweep", ["importance", "rejection"])
def test_the_report_names_every_run_of_its_experiment_config(sweep, load_script):
    """The report reads exactly the cells the experiment config sweeps."""
    import yaml

    rep = load_script("hauberg2011/report.py")
    cfg = yaml.safe_load((ROOT / "conf" / "experiment" / "hauberg2011" / f"{sweep}.yaml")
                         .read_text())["hydra"]["sweeper"]["params"]
    spec = rep.SWEEPS[sweep]
    assert spec["clips"] == str(cfg["data/clip"]).split(",")
    assert list(spec["trackers"]) == str(cfg["tracker"]).split(",")
    assert spec["particles"] == [int(n) for n in str(cfg["tracker.num_particles"]).split(",")]
    assert rep.SEEDS == [int(s) for s in str(cfg["seed"]).split(",")]


def _write_frame(d: Path, views: list[float], offset=None) -> None:
    d.mkdir(parents=True)
    m = {"silhouette_iou": {"per_view": views, "mean": sum(views) / len(views)},
         "body_fit": {}}
    if offset is not None:
        m["body_fit"]["offsets"] = {"head_top": offset}
    (d / "metrics.json").write_text(json.dumps(m))


def test_bodytrack_table_per_view_and_seed_spread(tmp_path, load_script):
    rep = load_script("hauberg2011/report.py")
    runs = tmp_path / "runs"
    hull = [[0.8, 0.7, 0.7, 0.6], [0.7, 0.7, 0.6, 0.6], [0.9, 0.8, 0.7, 0.6]]
    for s, v in enumerate(hull):
        _write_frame(runs / "real_frame_hull" / f"seed{s}", v, offset=[0.01 * s, 0.0, 0.08])
    _write_frame(runs / "real_frame" / "seed0", [0.6, 0.6, 0.5, 0.5])
    out = tmp_path / "out"
    assert rep.main(["bodytrack", "--runs", str(runs), "--out", str(out)]) == 0
    md = (out / "bodytrack.md").read_text()
    means = [sum(v) / 4 for v in hull]  # 0.7, 0.65, 0.75
    row = next(line for line in md.splitlines() if "(`real_frame_hull`)" in line)
    assert "| 0.800 | 0.733 | 0.667 | 0.600 |" in row  # per view, over the seeds
    assert f"| 0.700 ± {statistics.stdev(means):.3f} | 0.650 – 0.750 |" in row
    assert "| (1.0, 0.0, 8.0) |" in row  # mean head offset in cm
    assert "| 0.550 ± 0.000 |" in md and "| – |" in md  # real_frame: one seed, no offset
    assert "Missing runs (5)" in md and "real_frame_hull_centred/seed0" in md
    assert (out / "bodytrack.png").stat().st_size > 1000
    assert not list(out.glob("*tmp*"))
    assert rep.main(["bodytrack", "--runs", str(tmp_path / "none"), "--out", str(out)]) == 2


def test_bodytrack_report_reads_its_experiment_config(load_script):
    import yaml

    rep = load_script("hauberg2011/report.py")
    text = (ROOT / "conf" / "experiment" / "hauberg2011" / "bodytrack.yaml").read_text()
    cfg = yaml.safe_load(text)["hydra"]["sweeper"]["params"]
    assert set(str(cfg["tracker"]).split(",")) < set(rep.BODYTRACK)
    assert "tracker.name=real_frame_hull_centred" in text  # the ablation's command
    assert rep.SEEDS == [int(s) for s in str(cfg["seed"]).split(",")]
