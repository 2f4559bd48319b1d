"""The refinement report: per camera every change with its standard deviation (None for what
was not refined), JSON-serialisable, in a markdown table with one row per camera; the focal
length / distance correlation is reported."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchmocap.cameras import bundle_adjust, refinement_report, report_markdown

from .calibration_scenes import FPS, make_scene


@pytest.fixture(scope="module")
def result():
    sc = make_scene(11, T=20, K=15, offsets=(0.0, 0.4, -0.2, 0.1))
    return sc, bundle_adjust(sc.detections, sc.perturbed, ("rotation", "translation", "focal",
                                                           "principal_point", "time_offset"),
                             fps=FPS)


class TestRefinementReport:
    def test_smoke(self, result):
        _, res = result
        rep = refinement_report(res)
        assert json.loads(json.dumps(rep)) == rep
        assert [c["name"] for c in rep["cameras"]] == res.rig.names
        assert rep["solver"]["iterations"] == res.iterations
        assert rep["settings"]["groups"] == ["rotation", "translation", "focal",
                                             "principal_point", "time_offset"]
        assert res.report() == rep
        corr = res.correlation().reshape(4, 13, 4, 13)
        refined = ~torch.isnan(res.std)
        diag = torch.stack([corr[c, v, c, v] for c in range(4) for v in range(13)]).reshape(4, 13)
        torch.testing.assert_close(diag[refined], torch.ones_like(diag[refined]))

    def test_feature_values(self, result):
        sc, res = result
        rep = refinement_report(res)
        for c, e in enumerate(rep["cameras"]):
            want = math.degrees(float(res.values[c, 0:3].norm()))
            assert e["rotation_change_deg"] == pytest.approx(want, abs=1e-3)
            assert e["centre_change_mm"] == pytest.approx(
                1000 * float(res.values[c, 3:6].norm()), abs=0.01)
            assert e["focal_change_percent"] == pytest.approx(
                100 * (float(res.rig.K[c, 0, 0] / sc.perturbed.K[c, 0, 0]) - 1), abs=1e-3)
            assert e["principal_point_change_px"] == pytest.approx(
                (res.rig.K[c, :2, 2] - sc.perturbed.K[c, :2, 2]).tolist(), abs=1e-3)
            assert e["time_offset_frames"] == pytest.approx(float(res.time_offsets[c]), abs=1e-4)
            for key in ("rotation_change_std_deg", "centre_change_std_mm", "depth_std_mm",
                        "focal_std_percent", "time_offset_std_frames"):
                assert e[key] > 0, key
            assert all(s > 0 for s in e["principal_point_std_px"])
            assert -1 <= e["focal_depth_correlation"] <= 1
            assert e["residual_median_px_after"] < e["residual_median_px_before"]
            assert "k1_change" not in e  # distortion not refined
            # rotation about the camera's axes: same size as in world axes
            assert float(torch.tensor(e["rotation_camera_axes_deg"]).norm()) == pytest.approx(
                e["rotation_change_deg"], rel=1e-3)

    def test_feature_not_refined_is_none(self):
        sc = make_scene(12, T=8, K=12)
        rep = bundle_adjust(sc.detections, sc.perturbed, ("rotation",)).report()
        e = rep["cameras"][0]
        assert e["centre_change_mm"] is None and e["focal_change_percent"] is None
        assert e["time_offset_frames"] is None and e["principal_point_change_px"] is None
        assert e["rotation_change_deg"] > 0

    def test_feature_markdown(self, result):
        _, res = result
        text = report_markdown(refinement_report(res))
        rows = [ln for ln in text.splitlines() if ln.startswith("| ")]
        assert len(rows) == 1 + 4  # header and one row per camera
        assert rows[1].startswith(f"| {res.rig.names[0]} |") and " ± " in rows[1]
        assert "iterations, converged: True" in text
        assert res.markdown() == text
