"""The depth-order cue of the 2D-joint likelihood: which joints the capsule body hides, the
binary energy, its place in the Gauss-Newton derivatives, and that it separates mirror-image
interpretations the reprojection residuals tie on."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.body import CapsuleBody, rays_blocked_by_capsules
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import FrameEnergy, Joints2DLikelihood, Poses
from torchmocap.likelihoods.joints2d import occlusion_energy, predicted_hidden
from torchmocap.proposals import kinematic_jumps
from torchmocap.skeleton import human31

#: every joint but the hands: human31 has no wrist DoF, so a flipped forearm cannot keep the hand
#: on its ray and arm jumps would not be zero-residual mirror images
NO_HANDS = [j for j in human31().joint_names if not j.endswith("_hand")]


@pytest.fixture(scope="module")
def mono():
    sk = human31().double()
    rig = make_ring_rig(1, radius=4.5, height=1.5, image_size=(640, 480), fov_deg=55.0)
    return sk, rig, CapsuleBody(sk).double()


def _detections(sk, rig, body, th, hidden_conf=0.3, seen_conf=0.9):
    """Exact projections; the hidden joints (by the capsule body) get a low confidence."""
    pos = sk(th[None]).positions
    pix = rig.project(pos[0])[0]  # (C, J, 2)
    hid = predicted_hidden(pos, torch.arange(sk.num_joints), body, rig)[0]  # (C, J)
    conf = torch.where(hid, hidden_conf, seen_conf).to(pix)
    return torch.cat([pix, conf[..., None]], -1), hid


def _random_pose(sk, g):
    th = sk.zero_pose()
    th[6:] = 0.7 * torch.randn(sk.num_dofs - 6, generator=g, dtype=th.dtype)
    th[5] = 6.28 * float(torch.rand(1, generator=g))
    return sk.clamp(th[None])[0]


def test_feature_energy_is_residual_plus_disagreements(mono):
    sk, rig, body = mono
    g = torch.Generator().manual_seed(1)
    th = torch.stack([_random_pose(sk, g) for _ in range(6)])
    obs, _ = _detections(sk, rig, body, th[0])
    frame = Frame(index=0, time=0.0, joints2d=obs)
    plain = Joints2DLikelihood(rig, skeleton=sk, scale_px=2.0)
    cue = Joints2DLikelihood(rig, skeleton=sk, scale_px=2.0, occlusion="capsules", body=body,
                             occlusion_error=0.2)
    o0, o1 = plain.prepare(frame), cue.prepare(frame)
    v0 = FrameEnergy(plain, o0, sk)(th)
    v1 = FrameEnergy(cue, o1, sk)(th)
    pos = sk(th).positions
    wrong = (predicted_hidden(pos, o1.joints, body, rig) != o1.hidden[None]) \
        & rig.project(pos)[2]
    want = v0 + wrong.sum((-1, -2)).to(v0) * math.log(0.8 / 0.2)
    assert torch.allclose(v1, want)
    assert float(v1[0] - v0[0]) == 0.0 and bool((wrong.sum((-1, -2))[1:] > 0).any())
    # Gauss-Newton: the same energy, the residual's gradient and Hessian (the cue is
    # piecewise constant)
    e0, g0, h0 = plain.gauss_newton(Poses(th, sk), o0)
    e1, g1, h1 = cue.gauss_newton(Poses(th, sk), o1)
    assert torch.allclose(e1, v1) and torch.allclose(e0, v0)
    assert torch.equal(g0, g1) and torch.equal(h0, h1)


def test_feature_mirror_interpretations_are_separated(mono):
    """Every kinematic jump of an arm reprojects onto the same pixels (the residual energies
    tie); when a jump changes which joints the body hides, the cue makes it worse than the
    true pose by at least one disagreement."""
    sk, rig, body = mono
    c = rig.camera_centers()[0]
    g = torch.Generator().manual_seed(0)
    separated = 0
    for _ in range(12):
        th = _random_pose(sk, g)
        jumps = kinematic_jumps(sk, th, ["l_arm", "r_arm"], c)
        if jumps.kept < 2:
            continue
        obs, hid = _detections(sk, rig, body, th)
        frame = Frame(index=0, time=0.0, joints2d=obs)
        plain = Joints2DLikelihood(rig, skeleton=sk, scale_px=2.0, joints=NO_HANDS)
        cue = Joints2DLikelihood(rig, skeleton=sk, scale_px=2.0, joints=NO_HANDS,
                                 occlusion="capsules", body=body)
        v0 = FrameEnergy(plain, plain.prepare(frame), sk)(jumps.theta)
        v1 = FrameEnergy(cue, cue.prepare(frame), sk)(jumps.theta)
        assert float(v0.max()) < 1e-9  # every jump is a zero-residual mirror image
        idx = torch.tensor([sk.joint_index(j) for j in NO_HANDS])
        hj = predicted_hidden(sk(jumps.theta).positions, idx, body, rig)[:, 0]  # (N, J')
        differs = (hj != hid[0, idx][None]).any(-1)
        assert float(v1[0]) < 1e-9
        assert bool((v1[differs] >= math.log(9.0) - 1e-9).all())
        assert bool((v1[~differs] < 1e-9).all())
        separated += int(differs.sum())
    assert separated > 0  # the property was exercised


def test_feature_ignore_mask_of_the_ray_test():
    ep = torch.tensor([[[[0.0, -1.0, -1.0], [0.0, -1.0, 1.0]]]])  # (P=1, B=1, 2, 3)
    radii = torch.tensor([0.2])
    o = torch.tensor([[0.0, -4.0, 0.0]])
    pts = torch.zeros(1, 2, 3)
    assert rays_blocked_by_capsules(o, pts, ep, radii).tolist() == [[[True, True]]]
    ign = torch.tensor([[True], [False]])
    assert rays_blocked_by_capsules(o, pts, ep, radii, ignore=ign).tolist() == [[[False, True]]]
    with pytest.raises(ValueError, match="ignore"):
        rays_blocked_by_capsules(o, pts, ep, radii, ignore=torch.ones(3, 1, dtype=torch.bool))


def test_feature_preset_builds_with_the_runtime_body(mono):
    sk, rig, body = mono
    cfg = tracker_config("kjs", ["likelihood@tracker.likelihood=joints2d_occlusion"])
    tracker = build_tracker(cfg, Runtime(skeleton=sk, body=body, rig=rig), seed=0)
    term = tracker.likelihood.terms["joints2d"]
    assert term.occlusion == "capsules" and term.body is body


def test_exception(mono):
    sk, rig, body = mono
    with pytest.raises(ValueError, match="occlusion"):
        Joints2DLikelihood(rig, skeleton=sk, occlusion="mesh", body=body)
    with pytest.raises(ValueError, match="body"):
        Joints2DLikelihood(rig, skeleton=sk, occlusion="capsules")
    for bad in (0.0, 0.5, 2):
        with pytest.raises(ValueError, match="occlusion_error"):
            Joints2DLikelihood(rig, skeleton=sk, occlusion="capsules", body=body,
                               occlusion_error=bad)
    with pytest.raises(ValueError, match="occluded_below"):
        Joints2DLikelihood(rig, skeleton=sk, occlusion="capsules", body=body,
                           occluded_below=0.0)
    obs, _ = _detections(sk, rig, body, sk.zero_pose())
    plain = Joints2DLikelihood(rig, skeleton=sk).prepare(Frame(index=0, time=0.0,
                                                               joints2d=obs))
    with pytest.raises(ValueError, match="hidden"):
        occlusion_energy(sk(sk.zero_pose((1,))).positions, plain, rig, body)
