"""The monocular rig option ``mono1`` and the ``monocular`` scenario that uses it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from torchmocap.cameras import CameraRig
from torchmocap.data.synthetic import load_scenario
from torchmocap.data.synthetic.scenario import build_rig

CONF = Path(__file__).resolve().parents[2] / "torchmocap" / "conf"
F64 = torch.float64


def test_feature_mono1():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=None, overrides=["+rig=mono1"])
    rig = instantiate(cfg.rig)
    assert isinstance(rig, CameraRig) and rig.num_cameras == 1
    assert rig.image_size.tolist() == [[320, 240]]
    c = rig.camera_centers()[0]
    torch.testing.assert_close(c, torch.tensor([0.0, -4.5, 1.5], dtype=F64), atol=1e-9,
                               rtol=0)
    # a standing 1.8 m person at the origin (facing -y, the camera) is seen whole, and so is
    # a person a metre to the side
    body = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.8], [0.4, 0.3, 1.0], [1.0, 0.0, 0.0],
                         [-1.0, 0.0, 1.8]], dtype=F64)
    assert bool(rig.project(body)[2].all())
    assert torch.equal(build_rig("mono1").K, rig.K)


def test_feature_monocular_scenario():
    sc = load_scenario("monocular")
    assert sc.rig == "mono1" and sc.image_size == [320, 240]
    assert sc.joints2d.enabled and sc.silhouettes.enabled
    assert not (sc.imu.enabled or sc.images.enabled or sc.depth.enabled)
    assert sc.joints2d.pixel_noise > 0 and sc.joints2d.outlier_prob > 0 \
        and sc.joints2d.miss_prob > 0
    assert build_rig(sc.rig, sc.image_size).num_cameras == 1


@pytest.mark.parametrize("size", [[640, 480], [80, 60]])
def test_feature_monocular_rig_rescales(size):
    rig = build_rig("mono1", size)
    assert rig.image_size.tolist() == [size]
