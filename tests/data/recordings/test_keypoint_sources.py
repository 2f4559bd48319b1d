"""The keypoint-source registry: sources by name or by their config file, settings checked,
a user's source through one class and one YAML file."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.recordings import keypoint_sources, load_recording
from torchmocap.data.recordings.keypoints import (
    KEYPOINT_SETTINGS,
    build_keypoint_source,
    keypoint_settings,
)
from torchmocap.data.recordings.keypoints.openpose import OpenPoseJson


@pytest.fixture(scope="module")
def p2s(shared_data):
    return shared_data / "multiview" / "pose2sim_balancing"


class TestRegistry:
    def test_smoke(self):
        assert "openpose" in keypoint_sources()
        s = keypoint_settings({"source": "openpose"})
        assert s == {**KEYPOINT_SETTINGS, "source": "openpose", "folder": "auto"}
        src = build_keypoint_source("openpose", {**s, "folder": "raw"})
        assert isinstance(src, OpenPoseJson) and src.folder == "raw" and src.name == "openpose"

    @pytest.mark.parametrize("given, match", [
        ({"source": "nope"}, r"unknown source 'nope'; expected one of \['auto', 'none', "
                             r"'mediapipe', 'openpose'"),
        ({"source": 3}, r"data\.keypoints\.source: expected a source name"),
        ({"source": "none", "folder": "raw"}, r"unknown setting\(s\) \['folder'\]"),
        ({"source": "openpose", "shift": 1}, r"unknown setting\(s\) \['shift'\]; expected "
                                             r"\['folder', 'format', 'min_confidence', "
                                             r"'source'\]"),
        ({"min_confidence": 2}, r"data\.keypoints\.min_confidence: expected a number in"),
    ])
    def test_exception(self, given, match):
        with pytest.raises(ValueError, match=match):
            keypoint_settings(given)

    def test_exception_config_files(self, tmp_path):
        bad = tmp_path / "bad.yaml"
        bad.write_text("folder: raw\n")
        with pytest.raises(ValueError, match=r"bad\.yaml: expected a mapping with a _target_"):
            keypoint_settings({"source": str(bad)})
        bad.write_text("_target_: torchmocap.nowhere.Source\n")
        with pytest.raises(ValueError, match=r"cannot import the _target_ "
                                             r"'torchmocap\.nowhere\.Source'"):
            build_keypoint_source(str(bad), keypoint_settings({"source": str(bad)}))
        bad.write_text("_target_: torchmocap.cameras.CameraRig\n")
        with pytest.raises(ValueError, match="is not a KeypointSource class"):
            build_keypoint_source(str(bad), keypoint_settings({"source": str(bad)}))
        with pytest.raises(ValueError, match=r"data\.keypoints\.source: .*missing\.yaml: "
                                             r"cannot read"):
            keypoint_settings({"source": str(tmp_path / "missing.yaml")})


@pytest.mark.filterwarnings("ignore:.*codec.s crop")
def test_feature_a_users_source_is_one_class_and_one_config(tmp_path, p2s, monkeypatch):
    """A source outside the package (tests/plugins) enters through its YAML alone; its
    detections are what the loader tracks (here OpenPose's moved by 8 px)."""
    from pathlib import Path

    plugins = Path(__file__).resolve().parents[2] / "plugins"
    monkeypatch.syspath_prepend(str(plugins))
    cfg = tmp_path / "shifted.yaml"
    cfg.write_text("_target_: user_components.ShiftedOpenPose\nshift: 0.0\nfolder: auto\n")
    kw = dict(cameras=["cam01", "cam03"], stop=2, scale=0.5, masks="none",
              subject={"frames": 2})
    ref = load_recording(p2s, **kw)
    moved = load_recording(p2s, keypoints={"source": str(cfg), "shift": 8.0}, **kw)
    assert moved.meta.keypoint_source == "shifted" and moved.meta.keypoint_report["shift"] == 8
    seen = ref.joints2d[..., 2] > 0
    assert torch.equal(seen, moved.joints2d[..., 2] > 0) and int(seen.sum()) > 40
    # scaled images: 8 px of the full-size images are 4 px here
    torch.testing.assert_close(moved.joints2d[..., :2][seen], ref.joints2d[..., :2][seen] + 4.0)
