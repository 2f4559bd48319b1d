"""``MaskSettings``: the dict form round-trips; bad keys and values are errors naming the key."""

from __future__ import annotations

import pytest

from torchmocap.data.recordings.masks import MaskError, MaskSettings


class TestMaskSettings:
    def test_smoke(self):
        s = MaskSettings.from_dict(None)
        assert s == MaskSettings() and s.min_views is None and s.bounds is None

    def test_feature_round_trip(self):
        s = MaskSettings.from_dict({"scale": 0.5, "min_views": 3, "threshold": 5,
                                    "bounds": [[-1, 1], [-1, 1], [0, 2]]})
        assert s.scale == 0.5 and s.min_views == 3 and s.threshold == 5
        assert s.bounds == ((-1.0, 1.0), (-1.0, 1.0), (0.0, 2.0))
        assert MaskSettings.from_dict(s.to_dict()) == s
        assert MaskSettings.from_dict(s) is s

    def test_feature_omegaconf(self):
        from omegaconf import OmegaConf

        cfg = OmegaConf.create({"scale": 0.5, "fill_holes": False})
        assert MaskSettings.from_dict(cfg) == MaskSettings(scale=0.5, fill_holes=False)

    @pytest.mark.parametrize("key, value", [
        ("scale", 0), ("scale", 1.5), ("scale", float("nan")), ("scale", True), ("scale", "0.5"),
        ("median_frames", 0), ("median_frames", 2.5), ("threshold", -1.0),
        ("threshold", float("inf")), ("shadow_min", 1.5), ("highlight_max", 0.9),
        ("open_size", -0.1), ("min_area", 2.0), ("min_views", 0), ("min_views", 2.0),
        ("voxel_size", 0.0), ("fill_holes", 1), ("multiview", "yes"), ("min_noise", 300),
        ("bounds", [[0, 1], [0, 1]]), ("bounds", [[1, 0], [0, 1], [0, 1]]),
        ("bounds", [["a", 1], [0, 1], [0, 1]]), ("max_plate_motion", 0.9),
    ])
    def test_exception(self, key, value):
        with pytest.raises(MaskError, match=rf"^data\.masks\.{key}: expected"):
            MaskSettings.from_dict({key: value}, prefix="data.masks")

    def test_exception_unknown_key(self):
        with pytest.raises(MaskError, match=r"masks: unknown setting\(s\) \['tresh'\]; expected "
                                            r"some of \[.*'threshold'"):
            MaskSettings.from_dict({"tresh": 1})
        with pytest.raises(MaskError, match="masks: expected a mapping"):
            MaskSettings.from_dict(3)

    def test_exception_constructor(self):
        with pytest.raises(MaskError, match=r"masks\.scale"):
            MaskSettings(scale=-1.0)
