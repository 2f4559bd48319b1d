"""Frames without usable evidence are uninformative, never a perfect score, and reported."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.geometry import matrix_to_quaternion
from torchmocap.ik import SensorManifold
from torchmocap.likelihoods import (
    AppearanceLikelihood,
    FrameEnergy,
    OrientationLikelihood,
    Poses,
    SilhouetteLikelihood,
    WeightedSum,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from oracle import capsule_masks  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk).float()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose((3,))
    th[1, sk.dof_index("l_elbow_flex")] = 1.0
    th[2, :2] += 50.0  # far out of every view
    masks = capsule_masks(body, rig, th[0])
    imgs = (torch.rand(4, 240, 320, 3, generator=torch.Generator().manual_seed(0)) * 255
            ).to(torch.uint8)
    return sk, body, rig, th, masks, imgs


def test_silhouettes_without_any_usable_view(scene):
    sk, body, rig, th, masks, _ = scene
    lik = SilhouetteLikelihood(body, rig)
    good = lik.prepare(Frame(index=0, time=0.0, silhouettes=masks))
    assert lik.evidence(good)
    assert lik.energy(Poses(th, sk), good)[0].item() < 0.01
    for frame in (Frame(index=0, time=0.0, silhouettes=masks,
                        view_dropped=torch.ones(4, dtype=torch.bool)),
                  Frame(index=0, time=0.0, silhouettes=torch.zeros_like(masks))):
        obs = lik.prepare(frame)
        assert not lik.evidence(obs)
        assert torch.equal(lik.energy(Poses(th, sk), obs), torch.ones(3))  # not 0 = perfect


def test_appearance_out_of_view_and_without_views(scene):
    sk, body, rig, th, masks, imgs = scene
    lik = AppearanceLikelihood(body, rig)
    obs = lik.prepare(Frame(index=0, time=0.0, images=imgs))
    v = lik.energy(Poses(th, sk), obs)
    assert v[2].item() == pytest.approx(0.25)  # seen by no view: worst, not perfect
    assert v[0].item() < 0.25
    one = lik.prepare(Frame(index=0, time=0.0, images=imgs,
                            view_dropped=torch.tensor([False, True, True, True])))
    assert not lik.evidence(one) and lik.evidence(obs)
    assert torch.allclose(lik.energy(Poses(th, sk), one), torch.full((3,), 0.25))


def test_orientation_without_valid_samples(scene):
    sk = scene[0]
    m = SensorManifold(sk)
    lik = OrientationLikelihood(m, power=1)
    q = matrix_to_quaternion(m.sensor_orientations(sk.zero_pose()))
    obs = lik.prepare(Frame(index=0, time=0.0, imu=q, imu_valid=torch.zeros(5, dtype=torch.bool)))
    assert not lik.evidence(obs)
    assert torch.allclose(lik.energy(Poses(sk.zero_pose((2,)), sk), obs),
                          torch.full((2,), math.pi))


def test_weighted_sum_and_bound_energy_name_the_missing_terms(scene):
    sk, body, rig, th, masks, imgs = scene
    lik = WeightedSum({"silhouette": SilhouetteLikelihood(body, rig),
                       "appearance": AppearanceLikelihood(body, rig)})
    frame = Frame(index=0, time=0.0, silhouettes=torch.zeros_like(masks), images=imgs)
    V = FrameEnergy(lik, lik.prepare(frame), sk)
    assert V.missing_evidence() == ["silhouette"]
    assert lik.evidence(lik.prepare(frame))
    both = Frame(index=0, time=0.0, silhouettes=masks, images=imgs,
                 view_dropped=torch.ones(4, dtype=torch.bool))
    assert FrameEnergy(lik, lik.prepare(both), sk).missing_evidence() == ["silhouette",
                                                                          "appearance"]
    assert not lik.evidence(lik.prepare(both))
