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
