"""experiments/real_multiview/calibration_refinement.py on the trimmed pose2sim recording: a
refinement on some frames lowers the held-out error on the others, and the tables and JSON are
written."""

from __future__ import annotations

import json

import pytest

pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")


def test_calibration_refinement_script(load_script, shared_data, tmp_path):
    script = load_script("real_multiview/calibration_refinement.py")
    rec = shared_data / "multiview" / "pose2sim_balancing"
    assert script.main(["--recording", str(rec), "--splits", "0:6/6:10",
                        "--groups", "rotation,translation", "--groups",
                        "rotation,translation,focal", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "calibration_refinement.json").read_text())
    assert [r["groups"] for r in data["runs"]] == [["rotation", "translation"],
                                                    ["rotation", "translation", "focal"]]
    for run in data["runs"]:
        assert run["mean_after"] < run["mean_before"]
        assert len(run["report"]["cameras"]) == 4
    text = (tmp_path / "calibration_refinement.md").read_text()
    assert "| given calibration |" in text and "## Summary" in text
