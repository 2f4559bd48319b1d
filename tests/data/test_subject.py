"""Subject fitting on real motion capture."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.subject import fit_subject
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
