"""Silhouette, appearance and orientation likelihoods."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.geometry import so3_exp
from torchmocap.likelihoods.appearance import AppearanceLikelihood
from torchmocap.likelihoods.orientation import OrientationLikelihood, orientation_energy
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    prepare_silhouettes,
    silhouette_energy,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from oracle import capsule_masks  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_elbow_flex")] = 1.2
    th[sk.dof_index("r_hip_flex")] = 0.6
    th[sk.dof_index("l_shoulder_abd")] = 0.5
    masks = capsule_masks(body, rig, th)
    return sk, body, rig, th, masks


def test_hard_silhouette_zero_at_truth_and_grows(scene):
    sk, body, rig, th, masks = scene
    obs = prepare_silhouettes(masks, 200)
    lik = SilhouetteLikelihood(body, rig)
    assert lik.energy(th[None], obs).item() == pytest.approx(0.0, abs=1e-3)
    g = torch.Generator().manual_seed(0)
    energies = []
    for scale in (0.05, 0.15, 0.4):
        pert = th + scale * torch.randn(64, sk.num_dofs, generator=g)
        pert[:, :3] = th[:3]
        energies.append(lik.energy(pert, obs).mean().item())
    assert 0 < energies[0] < energies[1] < energies[2] <= 1
    assert torch.allclose(lik(th[None], obs), -2.0 * lik.energy(th[None], obs))


def test_both_directions_count(scene):
    sk, body, rig, th, masks = scene
    # an empty model region (mask twice as wide) penalises image->model; a shifted body both
    wide = masks | torch.roll(masks, 15, dims=2)
    e_wide = silhouette_energy(body.endpoints(sk(th[None])), body.radii, rig,
                               prepare_silhouettes(wide, 200))
    assert e_wide.item() > 0.05
    shifted = th.clone()
    shifted[:2] += 1.5
    e_far = silhouette_energy(body.endpoints(sk(shifted[None])), body.radii, rig,
                              prepare_silhouettes(masks, 200))
    assert e_far.item() > 0.8  # little overlap left in any view


def test_dropped_view_ignored(scene):
    sk, body, rig, th, masks = scene
    bad = masks.clone()
    bad[2] = torch.roll(bad[2], 40, dims=1)
    valid = torch.tensor([True, True, False, True])
    e = silhouette_energy(body.endpoints(sk(th[None])), body.radii, rig,
                          prepare_silhouettes(bad, 200, view_valid=valid))
    assert e.item() == pytest.approx(0.0, abs=1e-3)


def test_smooth_silhouette_differentiable_and_descends(scene):
    sk, body, rig, th, masks = scene
    obs = prepare_silhouettes(masks, 200)
    lik = SilhouetteLikelihood(body, rig, smooth=True)
    x = th.clone()
    x[sk.dof_index("l_elbow_flex")] = 0.6
    x = x[None].requires_grad_(True)
    e = lik.energy(x, obs)
    e.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # finite differences agree with autograd along the gradient direction
    d = -x.grad / x.grad.norm()
    h = 1e-3
    fd = (lik.energy(x.detach() + h * d, obs) - lik.energy(x.detach() - h * d, obs)) / (2 * h)
    assert fd.item() == pytest.approx(-x.grad.norm().item(), rel=0.1)
    assert fd.item() < 0  # a descent direction


def test_orientation_energy_closed_form():
    R = so3_exp(torch.tensor([[0.0, 0.0, 0.3], [0.1, 0.0, 0.0]]))
    measured = torch.eye(3).expand(2, 3, 3)
    offsets = torch.eye(3).expand(2, 3, 3)
    v = orientation_energy(R[None], offsets, measured)
    assert v.item() == pytest.approx((0.3**2 + 0.1**2) / 2, rel=1e-5)
    # the offset is applied on the right: R_TB R_BS vs R_TS
    off = so3_exp(torch.tensor([[0.0, 0.2, 0.0], [0.0, 0.0, 0.0]]))
    v = orientation_energy(torch.eye(3).expand(1, 2, 3, 3), off, off)
    assert v.item() == pytest.approx(0.0, abs=1e-10)
    with pytest.raises(ValueError, match="measured"):
        orientation_energy(R[None], offsets, torch.eye(3).expand(3, 3, 3))


def test_orientation_likelihood_module():
    sk = human31()
    lik = OrientationLikelihood(sk, ["l_elbow", "r_knee"], weight=3.0)
    th = sk.zero_pose((2,))
    th[1, sk.dof_index("l_elbow_flex")] = 0.5
    meas = sk(th[0]).rotations[[sk.joint_index("l_elbow"), sk.joint_index("r_knee")]]
    ll = lik(th, torch.eye(3).expand(2, 3, 3), meas)
    assert ll[0].item() == pytest.approx(0.0, abs=1e-10)
    assert ll[1].item() == pytest.approx(-3.0 * 0.5**2 / 2, rel=1e-4)


def test_appearance_prefers_the_true_pose(scene):
    sk, body, rig, th, masks = scene
    # colour images: body parts coloured by their x coordinate sign, background striped
    C, H, W = masks.shape
    imgs = torch.zeros(C, H, W, 3, dtype=torch.uint8)
    stripes = ((torch.arange(W) // 8) % 2 * 200).to(torch.uint8)
    imgs[..., 1] = stripes
    imgs[..., 0] = torch.where(masks, torch.tensor(230, dtype=torch.uint8),
                               torch.tensor(0, dtype=torch.uint8))
    imgs[..., 1] = torch.where(masks, torch.tensor(40, dtype=torch.uint8), imgs[..., 1])
    lik = AppearanceLikelihood(body, rig)
    e_true = lik.energy(th[None], imgs).item()
    far = th.clone()
    far[:2] += torch.tensor([0.3, -0.2])
    e_far = lik.energy(far[None], imgs).item()
    assert e_true < 0.02 < e_far
    with pytest.raises(ValueError, match="images"):
        lik.energy(th[None], imgs[..., 0])


def test_prepare_exceptions():
    with pytest.raises(ValueError, match="masks"):
        prepare_silhouettes(torch.zeros(4, 4))
    obs = prepare_silhouettes(torch.zeros(2, 5, 5))
    assert not obs.view_valid.any()


def test_gradient_of_hard_energy_not_needed_but_float64_ok(scene):
    sk, body, rig, th, masks = scene
    obs = prepare_silhouettes(masks, 100, dtype=torch.float64)
    e = silhouette_energy(body.endpoints(sk.double()(th.double()[None])), body.radii,
                          rig.double(), obs)
    sk.float()
    rig.float()
    assert e.dtype == torch.float64 and math.isfinite(e.item())
