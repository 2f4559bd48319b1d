"""experiments/learned_real: the camera-consistency table on the trimmed pose2sim recording (a
camera in the fit is matched better than one outside it), the synthetic-to-real ranking of the
image terms and the mask noise model held out camera by camera there, and the report's tables
from given scores (means, the change, the offsets with their anatomical points)."""

from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def report(load_script):
    return load_script("learned_real/report.py")


@pytest.mark.slow
def test_consistency_on_the_trimmed_recording(load_script, shared_data, tmp_path):
    cons = load_script("learned_real/consistency.py")
    rec = shared_data / "multiview" / "pose2sim_balancing"
    assert cons.main(["--recording", str(rec), "--scale", "0.25", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "consistency.json").read_text())
    assert len(rows) == 11  # 6 pairs, 4 triples, all four
    inside = [v["median_px"] for r in rows for v in r["views"].values() if v["in_fit"]]
    outside = [v["median_px"] for r in rows for v in r["views"].values() if not v["in_fit"]]
    assert sum(inside) / len(inside) < sum(outside) / len(outside)
    assert all(0 < x < 200 for x in inside + outside)
    text = (tmp_path / "consistency.md").read_text()
    assert text.count("\n| cam") == 11 and "**" in text


def _row(median, secs):
    return {"median_px": median, "mean_px": median + 1, "pck_05": 0.8, "pck_10": 1.0,
            "bone_cv_mean": 1.0, "jitter": 50.0, "seconds_per_frame": secs}


def test_table_means_and_change(report):
    rows = {"cam01": {"hand": _row(30.0, 0.1), "learned": _row(24.0, 0.11)},
            "cam02": {"hand": _row(10.0, 0.1), "learned": _row(8.0, 0.13)}}
    scores = {"hand_set": {"test": {"median_px": 30.0}}, "learned": {"test": {"median_px": 25.0}}}
    train = {c: {"seconds_training": 12.0, "scores": scores} for c in rows}
    text, mean = report.table(rows, train)
    assert mean["hand"]["median_px"] == 20.0 and mean["learned"]["median_px"] == 16.0
    assert "median -20.0 %" in text and "time per frame × 1.20" in text
    assert text.count("| cam01 |") == 2 and "| **mean** | learned | 16.0 |" in text


def test_offsets_table_names_the_anatomical_points(report):
    kp = {"LHip": {"joint": "l_hip", "frame": "pelvis", "offset_cm": [3.0, 0.0, 3.5],
                   "change_cm": [1.0, 0.0, 0.5], "change_norm_cm": 1.12, "scale_factor": 1.0}}
    shipped = {"parameters": {"keypoints": kp}}
    train = {"cam01": {"parameters": {"keypoints": {"LHip": {"change_norm_cm": 2.0}}}}}
    text = report.offsets_table(shipped, train)
    assert "| LHip | left greater trochanter region | pelvis | 2.0, 0.0, 3.0 | 3.0, 0.0, 3.5 | " \
           "+1.0, +0.0, +0.5 | 2.0 |" in text
    assert set(report.ANATOMY) == set(report.KEYPOINTS)


@pytest.mark.slow
def test_synthetic_to_real_on_the_trimmed_recording(load_script, shared_data, tmp_path):
    """Every term scores every camera; on the real masks the hand-crafted silhouette cost
    orders the perturbed poses by their error (a positive rank correlation)."""
    s2r = load_script("learned_real/synthetic_to_real.py")
    rec = shared_data / "multiview" / "pose2sim_balancing"
    assert s2r.main(["--recording", str(rec), "--scale", "0.25", "--mask-cache",
                     str(tmp_path / "masks"), "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "synthetic_to_real.json").read_text())
    assert set(out) == {"cam01", "cam02", "cam03", "cam04"}
    for r in out.values():
        assert set(r) == {"silhouette", "learned", "combined"}
        assert all(0.0 <= v["reference_lowest"] <= 1.0 for v in r.values())
    assert min(r["silhouette"]["spearman"] for r in out.values()) > 0.5


@pytest.mark.slow
def test_silhouette_noise_on_the_trimmed_recording(load_script, shared_data, tmp_path):
    """The mask noise model fitted to three views scores the fourth: every camera held out
    once, rates in [0, 0.5), the learned model's held-out NLL per pixel finite."""
    sn = load_script("learned_real/silhouette_noise.py")
    rec = shared_data / "multiview" / "pose2sim_balancing"
    assert sn.main(["--recording", str(rec), "--scale", "0.25", "--train-frames", "6",
                    "--mask-cache", str(tmp_path / "masks"), "--out", str(tmp_path)]) == 0
    out = json.loads((tmp_path / "silhouette_noise.json").read_text())
    assert set(out) == {"cam01", "cam02", "cam03", "cam04"}
    for cam, r in out.items():
        assert cam not in r["learned"] and len(r["learned"]) == 3
        for v in r["learned"].values():
            assert 0 <= v["false_positive"] < 0.5 and 0 <= v["false_negative"] < 0.5
            assert v["width_px"] > 0
        assert 0 < r["heldout_nll_per_pixel"]["learned"] < 1
