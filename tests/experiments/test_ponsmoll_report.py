"""experiments/ponsmoll2010/report.py: the body-fit table (outdoor and studio) from the runs'
metrics.json — pooled cells, the all-activity means, the fit's IoU and head offset, and a
missing run named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _metrics(ori: float, mpjpe: float, fit: dict | None = None) -> dict:
    m = {"orientation_error_deg": {"mean": ori, "std": 1.0, "per_bone": {"l_hip": ori},
                                   "per_bone_frame": {"l_hip": [ori, ori]}},
         "mpjpe_root_relative_mm": {"mean": mpjpe}, "seconds_per_frame": 1.0, "frames": 2}
    if fit is not None:
        m["body_fit"] = fit
    return m


def _write(path: Path, m: dict) -> None:
    path.mkdir(parents=True)
    (path / "metrics.json").write_text(json.dumps(m))


def test_body_fit_table(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path)
    trackers = [m for m, _ in rep.BODY_FIT]
    for k, a in enumerate(rep.ACTIVITIES):
        for j, t in enumerate(trackers):
            for s in rep.SEEDS:
                fit = None if j == 0 else {"iou_before": 0.4, "iou_after": 0.5,
                                           "offsets": {"head_top": [0.0, -0.05, 0.0]}}
                _write(tmp_path / "fig8" / a / t / f"seed{s}",
                       _metrics(10.0 + j + s, 50.0 + 10 * j + k, fit))
    for d, _, seeds in rep.STUDIO:
        for t, _ in rep.STUDIO_FIT:
            for s in seeds:
                _write(tmp_path / "studio" / d / t / f"seed{s}", _metrics(8.0 + s, 30.0))
    md = rep.body_fit()
    walking = next(line for line in md.splitlines() if line.startswith("| walking |"))
    cells = walking.split(" | ")
    assert len(cells) == 1 + len(trackers)
    # seeds 0-2 of the default: 10, 11, 12 -> mean 11, spread 1, pooled std sqrt(1 + 2/3)
    assert cells[1] == "11.0 ± 1.3 (±1.0); 50.0 mm"
    assert cells[2].startswith("12.0 ± 1.3 (±1.0); 60.0 mm; IoU 0.40 → 0.50, head 5.0 cm")
    assert "| **all** | **11.0°; 52.5 mm** | **12.0°; 62.5 mm** |" in md
    assert "(`body_fit.hull_filter=true`)" in md
    demo = next(line for line in md.splitlines() if line.startswith("| demo walk"))
    assert demo.count("8.0° (30.0 mm) / 9.0° (30.0 mm) / 10.0° (30.0 mm)") == len(rep.STUDIO_FIT)
    # a missing run is named
    missing = tmp_path / "fig8" / "dancing" / trackers[-1] / "seed1" / "metrics.json"
    missing.unlink()
    with pytest.raises(SystemExit, match="dancing/p_prior_refined_head/seed1"):
        rep.body_fit()


def _run(ori_by_bone_frame: dict, seconds: float = 1.0, below: float | None = None) -> dict:
    """metrics.json of one run from its per-bone, per-frame errors (population std, as the
    tracker's summary)."""
    import numpy as np

    a = np.array(list(ori_by_bone_frame.values()), dtype=float)  # (bones, frames)
    m = {"orientation_error_deg": {
        "mean": float(a.mean()), "std": float(a.std()),
        "per_bone": {b: float(np.mean(v)) for b, v in ori_by_bone_frame.items()},
        "per_bone_frame": {b: list(map(float, v)) for b, v in ori_by_bone_frame.items()}},
        "seconds_per_frame": seconds, "frames": a.shape[1] + 1,
        "mpjpe_root_relative_mm": {"mean": 40.0}}
    if below is not None:
        m["estimate_energy_below_truth"] = below
    return m


def test_combine_pools_frames_bones_and_seeds_like_one_sample(load_script):
    import numpy as np

    rep = load_script("ponsmoll2010/report.py")
    rng = np.random.default_rng(0)
    seeds = [{b: rng.normal(10 + 3 * s, 2 + s, 20) for b in ("l_hip", "r_hip")}
             for s in range(3)]
    r = rep.combine([_run(x) for x in seeds])
    every = np.concatenate([np.concatenate(list(x.values())) for x in seeds])
    assert r["ori_mean"] == pytest.approx(every.mean(), rel=1e-12)
    assert r["ori_std"] == pytest.approx(every.std(), rel=1e-12)
    per_seed = [np.concatenate(list(x.values())).mean() for x in seeds]
    assert r["seed_spread"] == pytest.approx(np.std(per_seed, ddof=1), rel=1e-12)
    assert r["ori_per_bone_frame"]["l_hip"][3] == pytest.approx(
        np.mean([x["l_hip"][3] for x in seeds]))


def _tree(root: Path, parts, m: dict) -> None:
    _write(root.joinpath(*parts), m)


def test_fig8_table_and_plot(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(rep, "RESULTS", tmp_path / "results")
    (tmp_path / "results").mkdir()
    for k, a in enumerate(rep.ACTIVITIES):
        for j, m in enumerate(rep.METHODS):
            for s in rep.SEEDS:
                v = 10.0 + j + k + s  # seed means j + k + 10, 11, 12
                _tree(tmp_path / "runs", ("fig8", a, m, f"seed{s}"),
                      _run({"l_hip": [v] * 4, "r_hip": [v] * 4}, seconds=0.5 + j))
    md = rep.fig8()
    assert (tmp_path / "results" / "fig8.png").stat().st_size > 0
    walking = next(x for x in md.splitlines() if x.startswith("| walking (4 frames) |"))
    # method 0 on activity 0: seeds 10, 11, 12 -> 11.0, pooled std sqrt(2/3), spread 1
    assert walking.split(" | ")[1] == "11.0 ± 0.8 (±1.0)"
    # P (method 5) over the six activities: 11 + 5 + mean(0..5) = 18.5
    p = rep.METHODS.index("p")
    allrow = next(x for x in md.splitlines() if x.startswith("| **all** |")).split(" | ")
    assert allrow[1 + p].startswith(f"**{11 + p + 2.5:.1f} ± ")
    secs = next(x for x in md.splitlines() if x.startswith("| s / frame")).split(" | ")
    assert secs[1 + p].strip(" |") == f"{0.5 + p:.2f}"
    assert "**10.78 ± 8.5**" in md
    missing = tmp_path / "runs" / "fig8" / "kicking" / "ls" / "seed2" / "metrics.json"
    missing.unlink()
    with pytest.raises(SystemExit, match="kicking/ls/seed2"):
        rep.fig8()


def test_fig10_rows_appear_once_their_three_sweeps_exist(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(rep, "RESULTS", tmp_path / "results")
    (tmp_path / "results").mkdir()

    def sweep(t, hip):
        for s in rep.SEEDS:
            _tree(tmp_path / "runs", ("fig10", t, f"seed{s}"),
                  _run({"l_hip": [hip] * 3, "r_hip": [2 * hip] * 3}))

    for t, hip in (("p_nonoise", 20.0), ("p_gaussian", 12.0), ("p", 6.0)):
        sweep(t, hip)
    sweep("p_fidelity_nonoise", 9.0)
    sweep("p_fidelity", 5.0)  # the Gaussian fidelity sweep is missing: no fidelity rows
    md = rep.fig10()
    assert "| vMF, κ = 1000 (`p`) | 6.0 | 9.0 ± 3.0 (±0.0) | 7.3 |" in md
    assert "fidelity options" not in md
    sweep("p_fidelity_gaussian", 7.0)
    md = rep.fig10()
    assert "| Gaussian, fidelity options (`p_fidelity_gaussian`) | 7.0 |" in md
    assert md.count("| 26.8 |") == 2  # the paper's no-noise number beside both no-noise rows
    assert (tmp_path / "results" / "fig10.png").stat().st_size > 0


def test_control_reports_the_energy_below_truth_fraction(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path / "runs")
    conds = ["capsules_clean_fitted", "capsules_clean", "skinned_clean", "skinned_outdoor"]
    for i, c in enumerate(conds):
        for a in ("walking", "jumping", "basketball"):
            for s in rep.SEEDS:
                _tree(tmp_path / "runs", ("control", c, a, f"seed{s}"),
                      _run({"l_hip": [2.0 + i] * 3}, below=0.1 * s + 0.1 * i))
    md = rep.control()
    row = next(x for x in md.splitlines() if "`skinned_outdoor`" in x)
    # seed fractions 0.3, 0.4, 0.5 -> 0.40; error 5.0 with no spread
    assert row.count("5.0 ± 0.0 (±0.0) [0.40]") == 3


def test_long_first_and_last_five_seconds(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(rep, "RESULTS", tmp_path / "results")
    (tmp_path / "results").mkdir()
    with pytest.raises(SystemExit, match="no clip has runs of every tracker"):
        rep.long()
    curve = [10.0] * 125 + [15.0] * 250 + [20.0] * 125  # 20 s at 25 fps
    for m in rep.LONG_METHODS:
        for s in rep.SEEDS:
            _tree(tmp_path / "runs", ("long", "boxing_long", m, f"seed{s}"),
                  _run({"l_hip": curve, "r_hip": curve}, seconds=2.0))
    md = rep.long()
    row = next(x for x in md.splitlines() if x.startswith("| boxing (CMU21 box-1) | LS"))
    assert row.endswith("| 10.0 | 20.0 | 2.00 |")
    assert "jumping jacks" not in md  # a clip without runs is left out
    assert (tmp_path / "results" / "long.png").stat().st_size > 0


def test_main_writes_tables_atomically(tmp_path, load_script, monkeypatch):
    rep = load_script("ponsmoll2010/report.py")
    monkeypatch.setattr(rep, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(rep, "RESULTS", tmp_path / "results")

    def broken():
        raise RuntimeError("boom")

    monkeypatch.setitem(rep.FIGURES, "control", broken)
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "control.md").write_text("old\n")
    monkeypatch.setattr("sys.argv", ["report.py", "control"])
    with pytest.raises(RuntimeError):
        rep.main()
    assert (tmp_path / "results" / "control.md").read_text() == "old\n"
    monkeypatch.setitem(rep.FIGURES, "control", lambda: "| new |")
    rep.main()
    assert (tmp_path / "results" / "control.md").read_text() == "| new |\n"
    assert not list((tmp_path / "results").glob("*tmp*"))
