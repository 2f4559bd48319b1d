"""Subject fitting on real motion capture."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.geometry import geodesic_angle
from torchmocap.io import load_motion


@pytest.fixture(scope="module")
def walk():
    """3 s of the bundled CMU 131_01 walk (3dsMax-style BVH) at 25 fps."""
    from torchmocap.io import bundled_clip_path

    return load_motion(bundled_clip_path()).resample(25).slice(0, 75)


@pytest.fixture(scope="module")
def walk_subject(walk):
    return fit_subject(walk)


def test_walk_fits_within_two_centimetres(walk_subject):
    s = walk_subject
    assert s.family == "cmu_max"
    assert s.theta.shape == (75, 31)
    assert s.residual.mean() < 0.02
    assert s.residual.max() < 0.04
    assert s.skeleton.within_limits(s.theta, tol=1e-6).all()


def test_fitted_pose_reproduces_ground_truth(walk_subject):
    s = walk_subject
    kin = s.skeleton(s.theta)
    err = (kin.positions - s.positions).norm(dim=-1).mean(-1)
    assert torch.allclose(err, s.residual, atol=1e-9)
    j = [s.skeleton.joint_index(b) for b in s.mapped_bones]
    assert {"l_elbow", "r_knee", "pelvis", "l_shoulder"} <= set(s.mapped_bones)
    ang = geodesic_angle(kin.rotations[:, j], s.rotations[:, j])
    assert ang.mean() < 0.15  # ~8.6 degrees: source bone frames vs the 31-DoF model
    assert torch.allclose(ang.mean(1), s.rotation_residual, atol=1e-6)


def test_bone_lengths_match_source_and_are_symmetric(walk_subject):
    s = walk_subject
    L = s.skeleton.bone_lengths()
    P = s.positions
    j = s.skeleton.joint_index
    thigh = 0.5 * ((P[:, j("l_knee")] - P[:, j("l_hip")]).norm(dim=-1).median()
                   + (P[:, j("r_knee")] - P[:, j("r_hip")]).norm(dim=-1).median())
    assert abs(L["l_knee"] - float(thigh)) < 1e-6
    assert abs(L["l_knee"] - L["r_knee"]) < 1e-9
    off = s.skeleton.offsets
    assert torch.allclose(off[j("l_shoulder")][1:], off[j("r_shoulder")][1:])
    assert torch.allclose(off[j("l_shoulder")][0], -off[j("r_shoulder")][0])


@pytest.mark.parametrize("rel, kw", [
    ("cmu/01_01.amc", {"asf": "cmu/01.asf"}),
    ("hdm05/HDM_bk_hopBothLegs1hops_017_120.amc", {"asf": "hdm05/HDM_bk.asf"}),
    ("cmu/60_12_scaled.bvh", {}),
    ("cmu/cmu21_kick.bvh", {}),
])
def test_other_families_fit(shared_data, rel, kw):
    kw = {k: shared_data / "mocap" / v for k, v in kw.items()}
    clip = load_motion(shared_data / "mocap" / rel, **kw).resample(25).slice(0, 20)
    s = fit_subject(clip)
    assert s.residual.mean() < 0.03, rel


def test_unmapped_skeleton_rejected(walk):
    import dataclasses

    from torchmocap.io import SkeletonMapError

    odd = dataclasses.replace(walk, joint_names=[f"bone{i}" for i in range(walk.num_joints)],
                              skeleton_family=None)
    with pytest.raises(SkeletonMapError, match="l_knee"):
        fit_subject(odd)


def test_continuation_repairs_a_wrong_minimum_on_real_motion(shared_data):
    # HDM05 bd arm rotation at 25 fps: from the standing template, frames 12-14 (arms swinging
    # overhead) land in wrong minima (0.02-0.05 m mean joint distance, 10 mm elsewhere); their
    # neighbours' solutions lead to the right ones
    hdm = shared_data / "mocap" / "hdm05"
    clip = load_motion(hdm / "HDM_bd_rotateArmsBothBackward1Reps_001_120.amc",
                       asf=hdm / "HDM_bd.asf").resample(25)
    s = fit_subject(clip)
    assert clip.num_frames >= 16
    assert s.residual.max() < 0.015, s.residual
    kin = s.skeleton(s.theta)  # the reported residual is that of the returned poses
    err = (kin.positions - s.positions).norm(dim=-1).mean(-1)
    assert torch.allclose(err, s.residual, atol=1e-9)
    assert s.skeleton.within_limits(s.theta, tol=1e-6).all()


class _Fit:
    def __init__(self, theta, pe, re=None):
        self.theta, self.position_error, self.rotation_error = theta, pe, re


def _toy_refit(target):
    """A 1-D 'fit' with two minima per frame: the right one at ``target[t]`` (error 0) and a
    wrong one at ``target[t] + 10`` (error 0.05); a start lands in the nearer one."""
    def refit(theta0, frames):
        right = target[frames][:, None]
        wrong = right + 10.0
        near_right = (theta0 - right).abs() <= (theta0 - wrong).abs()
        theta = torch.where(near_right, right, wrong)
        pe = torch.where(near_right, 0.0, 0.05).to(theta0.dtype).expand(-1, 2).clone()
        return _Fit(theta, pe)
    return refit


def test_continue_in_time_toy_two_minima():
    from torchmocap.data.subjects.mocap import _continue_in_time

    T = 12
    target = torch.arange(T, dtype=torch.float64) * 0.5  # smooth motion
    start = target.clone()[:, None]
    start[3:9] += 10.0  # a wrong stretch of six frames
    pe = torch.zeros(T, 2, dtype=torch.float64)
    pe[3:9] = 0.05
    calls = []
    refit = _toy_refit(target)

    def counting(theta0, frames):
        calls.append(frames.clone())
        return refit(theta0, frames)

    theta, perr, _, passes, changed = _continue_in_time(_Fit(start, pe), counting, 0.0)
    assert torch.equal(theta[:, 0], target) and float(perr.abs().max()) == 0.0
    assert changed == 6
    # pass 1 tries every frame from both neighbours; the repair then advances one frame per
    # pass from each end of the stretch (3 + 1 more passes), trying only the new frontier
    assert calls[0].numel() == 2 * (T - 1)
    assert passes <= 5 and all(c.numel() <= 4 for c in calls[1:])
    # nothing to repair: one pass, nothing changed
    theta2, _, _, passes2, changed2 = _continue_in_time(
        _Fit(target.clone()[:, None], torch.zeros(T, 2, dtype=torch.float64)), refit, 0.0)
    assert (passes2, changed2) == (1, 0) and torch.equal(theta2[:, 0], target)


def test_continue_in_time_min_gain():
    from torchmocap.data.subjects.mocap import _continue_in_time

    T = 6
    target = torch.zeros(T, dtype=torch.float64)
    start = target.clone()[:, None]
    start[2] += 10.0
    pe = torch.zeros(T, 2, dtype=torch.float64)
    pe[2] = 0.05
    # a gain of 0.05 m RMS is taken at min_gain 0.002 m, refused at 0.1 m
    th, _, _, _, changed = _continue_in_time(_Fit(start, pe), _toy_refit(target), 0.0)
    assert changed == 1 and float(th[2, 0]) == 0.0
    th, _, _, _, changed = _continue_in_time(_Fit(start, pe), _toy_refit(target), 0.0,
                                             min_gain=0.1)
    assert changed == 0 and float(th[2, 0]) == 10.0
