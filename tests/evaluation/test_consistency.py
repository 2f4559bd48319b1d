"""Bone-length constancy and jitter in closed form: a rigid motion has a bone CV of 0, known
length sequences give their CV, a constant acceleration gives that jitter, missing frames are
left out; a track's joints are rigid and its mapped keypoints' limb segments are not; and on
Pose2Sim's own triangulation of the real recording (its TRC)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchmocap.evaluation import LIMB_KEYPOINTS, bone_length_cv, jitter, track_consistency
from torchmocap.geometry import axis_angle_rotation

F64 = torch.float64


def _rigid_motion(T=20, J=6, seed=0):
    """A fixed point set moved by a rotation and translation that change every frame."""
    g = torch.Generator().manual_seed(seed)
    body = torch.randn(J, 3, generator=g, dtype=F64) * 0.3
    axes = torch.nn.functional.normalize(torch.randn(T, 3, generator=g, dtype=F64), dim=-1)
    R = axis_angle_rotation(axes, torch.linspace(0.0, 2.0, T, dtype=F64))
    t = torch.randn(T, 1, 3, generator=g, dtype=F64)
    return body @ R.transpose(-1, -2) + t


class TestBoneLengthCV:
    def test_feature_rigid_motion_is_zero(self):
        x = _rigid_motion()
        cv = bone_length_cv(x, [(0, 1), (1, 2), (3, 5)])
        assert cv.cv_percent.abs().max() < 1e-10 and cv.mean_percent < 1e-10
        torch.testing.assert_close(cv.mean_length, (x[0, [0, 1, 3]] - x[0, [1, 2, 5]]).norm(
            dim=-1))

    def test_feature_known_lengths(self):
        """Lengths 1 +- d alternating: mean 1, population std d, CV 100 d %; a second bone of
        constant length has CV 0; the mean is over bones."""
        T, d = 10, 0.05
        x = torch.zeros(T, 3, 3, dtype=F64)
        x[:, 1, 0] = 1.0 + d * torch.tensor([(-1.0) ** t for t in range(T)], dtype=F64)
        x[:, 2, 1] = 0.5
        cv = bone_length_cv(x, [("a", "b"), ("a", "c")], joint_names=["a", "b", "c"])
        torch.testing.assert_close(cv.cv_percent, torch.tensor([100 * d, 0.0], dtype=F64))
        assert cv.mean_percent == pytest.approx(50 * d)
        assert cv.frames.tolist() == [T, T]

    def test_feature_missing_frames(self):
        x = _rigid_motion(T=8, J=3)
        x[2, 1] = float("nan")
        x[5, 1, 0] += 10.0  # an outlier frame does count
        cv = bone_length_cv(x, [(0, 1), (0, 2)])
        assert cv.frames.tolist() == [7, 8]
        assert float(cv.cv_percent[0]) > 50 and float(cv.cv_percent[1]) < 1e-10
        gone = x.clone()
        gone[:, 2] = float("nan")
        cv2 = bone_length_cv(gone, [(0, 1), (0, 2)])
        assert math.isnan(float(cv2.cv_percent[1])) and cv2.mean_percent == pytest.approx(
            float(cv.cv_percent[0]))

    def test_exception(self):
        x = torch.zeros(4, 3, 3)
        with pytest.raises(ValueError, match="positions"):
            bone_length_cv(x[0], [(0, 1)])
        with pytest.raises(ValueError, match="bones: expected at least one"):
            bone_length_cv(x, [])
        with pytest.raises(ValueError, match="out of range"):
            bone_length_cv(x, [(0, 3)])
        with pytest.raises(ValueError, match="unknown joint 'd'"):
            bone_length_cv(x, [("a", "d")], joint_names=["a", "b", "c"])


class TestJitter:
    def test_feature_constant_acceleration(self):
        """x(t) = x0 + v t + a t^2 / 2 sampled at fps: the second difference times fps^2 is
        |a| exactly, for every joint and frame."""
        fps, T = 60.0, 30
        t = torch.arange(T, dtype=F64)[:, None, None] / fps
        a = torch.tensor([[0.0, 3.0, 4.0], [1.0, 0.0, 0.0]], dtype=F64)  # |a| = 5 and 1
        v = torch.tensor([[0.5, -1.0, 0.0], [0.0, 2.0, 1.0]], dtype=F64)
        x = 0.3 + v * t + 0.5 * a * t ** 2
        j = jitter(x, fps)
        torch.testing.assert_close(j.per_joint, torch.tensor([5.0, 1.0], dtype=F64))
        torch.testing.assert_close(j.per_frame, torch.full((T - 2,), 3.0, dtype=F64))
        assert j.mean == pytest.approx(3.0)
        # a constant velocity (or a rest) has no jitter
        assert jitter(0.3 + v * t, fps).mean == pytest.approx(0.0, abs=1e-9)

    def test_feature_missing_frames(self):
        fps = 30.0
        t = torch.arange(6, dtype=F64)[:, None, None] / fps
        x = (0.5 * 2.0 * t ** 2).expand(6, 2, 3).clone()  # |a| = 2 sqrt(3)
        x[3, 0] = float("nan")  # spoils the triples centred at frames 2, 3, 4 for joint 0
        j = jitter(x, fps)
        torch.testing.assert_close(j.per_joint, torch.full((2,), 2 * math.sqrt(3), dtype=F64))
        assert j.per_frame.shape == (4,)

    def test_exception(self):
        with pytest.raises(ValueError, match="at least 3 frames"):
            jitter(torch.zeros(2, 4, 3), 30.0)
        with pytest.raises(ValueError, match="fps"):
            jitter(torch.zeros(5, 4, 3), 0.0)
        with pytest.raises(ValueError, match="positions"):
            jitter(torch.zeros(5, 4), 30.0)


class TestTrackConsistency:
    def test_feature(self):
        """A skeleton's track: the joints' bones are rigid (CV 0 up to rounding); the mapped
        keypoints' limb segments are not where a keypoint rides on the parent's bone (a hip on
        the pelvis, the knee on the femur: bending the hip changes their distance), and a
        track at constant velocity has no jitter, one with a kick has."""
        from torchmocap.skeleton import human31

        sk = human31().double()
        T = 6
        theta = sk.zero_pose((T,), dtype=F64)
        theta[:, 0] = 0.1 * torch.arange(T, dtype=F64)  # constant velocity
        theta[:, sk.dof_index("l_hip_flex")] = 0.2 * torch.arange(T, dtype=F64)
        joints = track_consistency(sk, theta, 30.0)
        assert joints["points"] == "joints"
        assert joints["bone_length_cv_percent"]["mean"] < 1e-6
        assert len(joints["bone_length_cv_percent"]["per_bone"]) == len(sk.joint_names) - 1
        kp = track_consistency(sk, theta, 30.0, "body_25b")
        cv = kp["bone_length_cv_percent"]["per_bone"]
        assert kp["points"] == "keypoints" and set(cv) == {f"{a}-{b}" for a, b in LIMB_KEYPOINTS}
        assert cv["LHip-LKnee"] > 0.1 and cv["RHip-RKnee"] < 1e-6 and cv["LKnee-LAnkle"] < 1e-6
        assert kp["jitter_m_s2"]["per_point"]["RAnkle"] < 1e-6  # moves at constant velocity
        assert kp["jitter_m_s2"]["per_point"]["LAnkle"] > 1.0  # the hip's rotation accelerates
        kick = theta.clone()
        kick[3, 0] += 0.05
        assert track_consistency(sk, kick, 30.0)["jitter_m_s2"]["mean"] > 10.0
        json.dumps(kp)


def test_real_recording(shared_data):
    """Pose2Sim's own 4-view triangulation of pose2sim_balancing (its TRC, the first 10
    frames): the limb bones' lengths vary by 1.2-3.7 % (mean 2.4 %; REFERENCE §11: 3.8-10.1 %
    over all 100 frames, which include the kick), and the keypoints jitter by 77 m/s^2 on
    average at 60 fps (19-251 m/s^2 per keypoint): per-frame triangulation is not smooth."""
    from torchmocap.io import read_trc

    trc = read_trc(shared_data / "multiview" / "pose2sim_balancing" / "pose2sim_output"
                   / "S00_P00_T01_BalancingTrial_0-100.trc")
    x = trc.z_up()
    limbs = [("RHip", "RKnee"), ("RKnee", "RAnkle"), ("LHip", "LKnee"), ("LKnee", "LAnkle"),
             ("RShoulder", "RElbow"), ("RElbow", "RWrist"), ("LShoulder", "LElbow"),
             ("LElbow", "LWrist")]
    cv = bone_length_cv(x, limbs, joint_names=trc.marker_names)
    assert 1.0 < cv.mean_percent < 5.0, cv.cv_percent
    assert bool(((cv.mean_length > 0.2) & (cv.mean_length < 0.5)).all())
    j = jitter(x, trc.rate)
    assert 30.0 < j.mean < 150.0, j.mean
