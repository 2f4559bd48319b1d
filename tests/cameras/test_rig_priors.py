"""Priors of a rig refinement: the stated default widths in the refined parameters' units,
None for no prior, clear errors naming the setting."""

from __future__ import annotations

import math

import pytest

from torchmocap.cameras import RefinementError, RigParametrization, RigPriors, make_ring_rig


class TestRigPriors:
    def test_smoke(self):
        p = RigPriors()
        assert (p.rotation_deg, p.translation_m, p.focal_percent, p.principal_point_px,
                p.distortion, p.time_offset_frames) == (5.0, 0.25, 5.0, 20.0, 0.05, 2.0)
        assert RigPriors.from_dict(p.to_dict()) == p

    def test_feature_widths_in_parameter_units(self):
        par = RigParametrization(make_ring_rig(2), ("rotation", "translation", "focal",
                                                    "principal_point", "distortion",
                                                    "time_offset"))
        w = RigPriors().widths(par)[:12].tolist()
        want = [math.radians(5)] * 3 + [0.25] * 3 + [math.log(1.05)] + [20.0] * 2 + \
            [0.05] * 2 + [2.0]
        assert w == pytest.approx(want)
        w = RigPriors(focal_percent=None).widths(par)
        assert math.isinf(float(w[6])) and math.isfinite(float(w[5]))

    def test_exception(self):
        for field in ("rotation_deg", "translation_m", "focal_percent", "principal_point_px",
                      "distortion", "time_offset_frames"):
            for bad in (0.0, -1.0, float("inf"), True, "2"):
                with pytest.raises(RefinementError, match=f"priors.{field}"):
                    RigPriors(**{field: bad})
        with pytest.raises(RefinementError, match=r"unknown setting\(s\) \['focal'\]"):
            RigPriors.from_dict({"focal": 3.0})
        with pytest.raises(RefinementError, match="priors: expected a RigPriors"):
            RigPriors.from_dict(3.0)
        with pytest.raises(RefinementError, match="priors.time_offset_frames"):
            RigPriors(time_offset_frames=12.0).check_time(10)
        RigPriors(time_offset_frames=2.0).check_time(10)
