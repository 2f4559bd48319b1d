"""experiments/smoothing/report.py: the filtered-vs-smoothed table from the runs' metrics.json
(seed means, clip means, relative change) and a run without a smoother named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


def _write(path: Path, filt: float, smooth: float, smoother=True, markers=False) -> None:
    path.mkdir(parents=True)
    m = {k: {"mean": smooth} for k in ("orientation_error_deg", "mpjpe_mm",
                                        "mpjpe_root_relative_mm")
         + (("marker_error_mm",) if markers else ())}
    if smoother:
        m["filtered"] = {k: filt for k in m}
        m["smoother"] = {"name": "kalman", "measurement_std_deg_median": 2.0,
                         "acceleration_std_deg_median": 1.0, "clamped": 0}
    (path / "metrics.json").write_text(json.dumps(m))


def test_table_means_and_changes(tmp_path, load_script):
    rep = load_script("smoothing/report.py")
    runs = tmp_path / "runs"
    for c, base in (("walk", 40.0), ("jump", 60.0)):
        for s in (0, 1):
            _write(runs / "studio" / c / "p" / f"seed{s}", base + 2 * s, base + 2 * s - 4)
    assert rep.main(["--runs", str(runs), "--out", str(tmp_path / "out")]) == 0
    md = (tmp_path / "out" / "kalman.md").read_text()
    assert (tmp_path / "out" / "kalman.png").stat().st_size > 0
    assert "| studio | `p` | walk | 41.0 → 37.0 (-10 %)" in md
    assert "| studio | `p` | jump | 61.0 → 57.0 (-7 %)" in md
    # the clip mean of the seed means: (41 + 61) / 2 -> (37 + 57) / 2
    assert "| studio | `p` | mean | **51.0 → 47.0 (-8 %)**" in md
    assert not list((tmp_path / "out").glob("*tmp*"))


def test_marker_error_column_when_every_run_has_it(tmp_path, load_script):
    rep = load_script("smoothing/report.py")
    runs = tmp_path / "runs"
    _write(runs / "stereo" / "boxing" / "hauberg_depth" / "seed0", 50.0, 45.0, markers=True)
    assert rep.main(["--runs", str(runs), "--out", str(tmp_path / "out"),
                     "--name", "hauberg"]) == 0
    md = (tmp_path / "out" / "hauberg.md").read_text()
    assert "marker error, eq. 16 (mm)" in md
    assert md.count("50.0 → 45.0 (-10 %)") == 2 * 4  # per clip and mean, four measures
    _write(runs / "stereo" / "boxing" / "hauberg_depth" / "seed1", 50.0, 45.0)
    assert rep.main(["--runs", str(runs), "--out", str(tmp_path / "out"),
                     "--name", "mixed"]) == 0
    assert "marker error" not in (tmp_path / "out" / "mixed.md").read_text()


def test_runs_without_a_smoother_are_named(tmp_path, load_script, capsys):
    rep = load_script("smoothing/report.py")
    runs = tmp_path / "runs"
    _write(runs / "studio" / "walk" / "p" / "seed0", 40.0, 40.0, smoother=False)
    assert rep.main(["--runs", str(runs), "--out", str(tmp_path / "out")]) == 2
    assert "not a smoothed run" in capsys.readouterr().err
    assert rep.main(["--runs", str(tmp_path / "none"), "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out" / "kalman.md").exists()


@pytest.mark.parametrize("a, b, text", [(40.0, 36.0, "-10 %"), (0.0, 1.0, "–")])
def test_relative_change(load_script, a, b, text):
    assert load_script("smoothing/report.py")._pct(a, b) == text


def test_moving_average_peer_keeps_ramps_and_unwraps(load_script):
    import math

    import torch

    va = load_script("smoothing/variants.py")
    ramp = torch.linspace(2.5, 4.0, 12, dtype=torch.float64)[:, None]
    wrapped = torch.remainder(ramp + math.pi, 2 * math.pi) - math.pi
    out = va.moving_average(wrapped)
    # a linear ramp is kept away from the padded ends, across the +-pi seam
    assert torch.allclose(out[2:-2], ramp[2:-2], atol=1e-12)
    assert out[0] == wrapped[0]
