"""Fitting capsule radii to silhouettes: recovers a known scale, improves the IoU, checkpoints."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.filters.body_fit import SilhouetteBodyFit
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parents[1] / "likelihoods"))
from oracle import capsule_masks  # noqa: E402


def test_recovers_thicker_limbs():
    sk = human31()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_shoulder_abd")] = 0.8
    th[sk.dof_index("r_elbow_flex")] = 1.0
    truth = CapsuleBody(sk).float()
    names = truth.bone_names
    scale = torch.tensor([1.5 if ("elbow" in n or "wrist" in n) else 1.0 for n in names])
    truth.radii.mul_(scale)
    masks = capsule_masks(truth, rig, th)
    body = CapsuleBody(sk).float()
    fit = SilhouetteBodyFit(body, rig, iterations=60, stride=2)
    info = fit(th, Frame(index=0, time=0.0, silhouettes=masks))
    assert info["iou_after"] > info["iou_before"] + 0.01
    assert info["iou_after"] > 0.98
    assert info["scales"]["elbow"] == pytest.approx(1.5, rel=0.1)  # upper arms
    assert info["scales"]["wrist"] == pytest.approx(1.5, rel=0.1)  # forearms
    assert info["scales"]["knee"] == pytest.approx(1.0, rel=0.1)  # thighs unchanged
    arm = [i for i, n in enumerate(names) if "elbow" in n]
    assert torch.allclose(body.radii[arm], truth.radii[arm], rtol=0.12)  # changed in place
    with pytest.raises(ValueError, match="min_scale"):
        SilhouetteBodyFit(body, rig, min_scale=1.5)
    with pytest.raises(ValueError, match="silhouettes"):
        fit(th, Frame(index=0, time=0.0))
