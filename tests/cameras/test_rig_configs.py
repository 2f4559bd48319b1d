"""The torchmocap/conf/rig Hydra options compose and instantiate into the advertised rigs."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from torchmocap.cameras import CameraRig

CONF = Path(__file__).resolve().parents[2] / "torchmocap" / "conf"
F64 = torch.float64


def _load(name, overrides=()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=None, overrides=[f"+rig={name}", *overrides])
    return instantiate(cfg.rig)


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF / "rig").glob("*.yaml")))
def test_smoke_every_rig_option(name):
    rig = _load(name)
    single = name in ("mono1", "stereo1")
    assert isinstance(rig, CameraRig) and rig.num_cameras == (1 if single else 4)
    # a standing 1.8 m person at the origin is seen whole by every camera
    body = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.8], [0.4, 0.3, 1.0]], dtype=F64)
    assert bool(rig.project(body)[2].all())


def test_feature_ring4():
    rig = _load("ring4")
    c = rig.camera_centers()
    torch.testing.assert_close(c[:, :2].norm(dim=-1), torch.full((4,), 4.0, dtype=F64))
    torch.testing.assert_close(c[:, 2], torch.full((4,), 2.5, dtype=F64))
    assert rig.image_size.tolist() == [[320, 240]] * 4
    big = _load("ring4", ["rig.image_size=[1280,720]"])
    assert big.image_size[0].tolist() == [1280, 720]
    assert big.K[0, 0, 0].item() == pytest.approx(640 / (3**0.5 / 3))
