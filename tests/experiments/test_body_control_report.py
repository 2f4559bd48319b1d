"""experiments/body/control.py reads the control runs and writes the table and plot."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _module():
    spec = importlib.util.spec_from_file_location("body_control",
                                                  ROOT / "experiments" / "body" / "control.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _metrics(mp, ori, spf, fit=None):
    m = {"frames": 30, "mpjpe_mm": {"mean": mp}, "orientation_error_deg": {"mean": ori},
         "seconds_per_frame": spf}
    if fit is not None:
        m["body_fit"] = fit
    return m


def test_report_rows_and_summary(tmp_path):
    mod = _module()
    runs = tmp_path / "runs"
    for data, body in mod.BODIES:
        for i, clip in enumerate(mod.CLIPS):
            for tr, _ in mod.TRACKERS:
                d = runs / data / body / clip / tr
                d.mkdir(parents=True)
                fit = None if tr == "default" else {
                    "iou_before": 0.8, "iou_after": 0.85, "seconds": 5.0,
                    "height_error_m": None if body == "makehuman" else 0.001 * (i + 1)}
                mp = 30.0 if tr == "default" else 18.0 + i
                (d / "metrics.json").write_text(json.dumps(_metrics(mp, 6.0, 0.6, fit)))
    text = mod.report(runs, tmp_path / "out")
    assert (tmp_path / "out" / "control.png").stat().st_size > 1000
    assert "| child | jumping | 30.0 → **19.0** | 6.00 → 6.00 | +0.20 |" in text
    assert "MPJPE 30.0 → 19.0 mm" in text  # the mean of 18, 19, 20 over the five bodies
    assert "height error over every Anny run: max 0.30 cm" in text
    assert (tmp_path / "out" / "control.md").read_text() == text
