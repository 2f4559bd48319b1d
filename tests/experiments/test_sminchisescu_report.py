"""experiments/sminchisescu2003/report.py: the tracking table from the runs' metrics.json (seed
means and spreads, smoothed beside filtered, a chain's intermediate stage, missing runs named)."""

from __future__ import annotations

import json
from pathlib import Path


def _write(path: Path, mpjpe: float, root: float, ori: float, chain=None) -> None:
    path.mkdir(parents=True)
    m = {"mpjpe_mm": {"mean": mpjpe, "per_frame": [mpjpe - 1, mpjpe + 1]},
         "mpjpe_root_relative_mm": {"mean": root},
         "orientation_error_deg": {"mean": ori, "per_frame": [ori, ori]},
         "seconds_per_frame": 0.2, "frames": 3, "num_particles": 200}
    if chain is not None:  # a viterbi_kalman run: the filter's errors and the Viterbi stage's
        m["filtered"] = {"mpjpe_mm": mpjpe + 20, "mpjpe_root_relative_mm": root + 10,
                         "orientation_error_deg": ori + 2}
        m["smoother"] = {"name": "viterbi+kalman", "stages": [
            {"name": "viterbi", "errors": {"mpjpe_root_relative_mm": chain[0],
                                           "orientation_error_deg": chain[1],
                                           "mpjpe_mm": mpjpe + 5}},
            {"name": "kalman", "errors": {"mpjpe_root_relative_mm": root,
                                          "orientation_error_deg": ori, "mpjpe_mm": mpjpe}}]}
    (path / "metrics.json").write_text(json.dumps(m))


def test_chain_runs_get_the_first_stage_beside_the_last(tmp_path, load_script):
    rep = load_script("sminchisescu2003/report.py")
    runs = tmp_path / "runs"
    for s, (root, vit) in enumerate(((50.0, 56.0), (54.0, 60.0))):
        _write(runs / "dance_cmu21" / "kjs" / f"seed{s}", 100.0 + s, root, 20.0 + s,
               chain=(vit, 22.0 + s))
        _write(runs / "dance_cmu21" / "css" / f"seed{s}", 90.0, 45.0, 25.0, chain=(49.0, 26.0))
    out = tmp_path / "out"
    assert rep.main(["--runs", str(runs), "--out", str(out), "--clips", "dance_cmu21",
                     "--trackers", "kjs,css,ss", "--seeds", "0,1"]) == 0
    md = (out / "tracking.md").read_text()
    assert (out / "tracking.png").stat().st_size > 0
    head = next(line for line in md.splitlines() if line.startswith("| clip"))
    assert "root-aligned after viterbi (mm)" in head and "after kalman" not in head
    kjs = next(line for line in md.splitlines() if "| KJS + CSS |" in line)
    cells = [c.strip() for c in kjs.strip("|").split("|")]
    cols = [c.strip() for c in head.strip("|").split("|")]
    row = dict(zip(cols, cells))
    # seed means with the sample standard deviation of the per-seed means
    assert row["MPJPE, smoothed (mm)"] == "100.5 ± 0.7"
    assert row["MPJPE, filtered (mm)"] == "120.5 ± 0.7"
    assert row["root-aligned, smoothed (mm)"] == "52.0 ± 2.8"
    assert row["root-aligned after viterbi (mm)"] == "58.0 ± 2.8"
    assert row["orientation error after viterbi (deg)"] == "22.50 ± 0.71"
    assert row["seeds"] == "2"
    assert "Missing runs (2): dance_cmu21/ss/seed0, dance_cmu21/ss/seed1" in md
