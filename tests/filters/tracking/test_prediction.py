"""Tests for torchmocap.filters.tracking.prediction (AR(3) pose prediction, SO(3) composition)."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from torchmocap.filters.optim.rotations import (
    RotationGroup,
    angles_from_matrix,
    skeleton_rotation_groups,
)
from torchmocap.filters.tracking.prediction import predict_ar3
from torchmocap.geometry import axis_angle_rotation, geodesic_angle, so3_exp, so3_log

F64 = torch.float64


def _axes_to_matrix(axes: torch.Tensor):
    """Euler-type angles through three arbitrary unit axes: rot(a1,t1) rot(a2,t2) rot(a3,t3)."""

    def to_matrix(t: torch.Tensor) -> torch.Tensor:
        out = None
        for j in range(3):
            r = axis_angle_rotation(axes[j].to(t).expand(*t.shape[:-1], 3), t[..., j])
            out = r if out is None else out @ r
        return out

    return to_matrix


ZYX = _axes_to_matrix(torch.tensor([[0.0, 0, 1], [0, 1, 0], [1, 0, 0]], dtype=F64))


class TestScalarModes:
    def test_constant_acceleration_exact_on_quadratics(self):
        """Exact for every polynomial of degree ≤ 2, batched over leading dims."""
        g = torch.Generator().manual_seed(0)
        c = torch.randn(4, 3, 5, generator=g, dtype=F64)  # (batch, coeff, D)
        t = torch.arange(6, dtype=F64)
        traj = c[:, None, 0] + c[:, None, 1] * t[:, None] + c[:, None, 2] * t[:, None] ** 2
        pred = predict_ar3(traj[:, :5], "constant_acceleration")
        assert pred.shape == (4, 5)
        assert torch.allclose(pred, traj[:, 5], atol=1e-10)
        # ... and not for a cubic (so the test can fail)
        cubic = t**3
        assert abs(float(predict_ar3(cubic[:5, None])) - 125.0) > 1

    def test_uses_last_three(self):
        h = torch.tensor([[100.0], [0.0], [1.0], [4.0]])
        assert predict_ar3(h).item() == pytest.approx(9.0)

    def test_damped(self):
        h = torch.tensor([[0.0, 0.0], [1.0, 2.0], [3.0, 3.0]], dtype=F64)
        lam1, lam2 = 0.7, 0.2
        d1, d2 = h[2] - h[1], h[1] - h[0]
        expect = h[2] + lam1 * d1 + lam2 * (d1 - d2)
        assert torch.allclose(predict_ar3(h, "damped", damping=(lam1, lam2)), expect)
        # (1, 1) is constant acceleration, (1, 0) constant velocity
        assert torch.allclose(predict_ar3(h, "damped", damping=(1.0, 1.0)), predict_ar3(h))
        lin = torch.tensor([[1.0], [3.0], [5.0]], dtype=F64)
        assert predict_ar3(lin, "damped", damping=(1.0, 0.0)).item() == pytest.approx(7.0)

    def test_limits(self):
        h = torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 0.1], [2.0, -2.0, 0.2]])
        out = predict_ar3(h, lower=torch.tensor([-1.0, -1.0, -1.0]), upper=2.5)
        assert torch.allclose(out, torch.tensor([2.5, -1.0, 0.3]))

    def test_exception(self):
        with pytest.raises(ValueError, match="history.*T >= 3"):
            predict_ar3(torch.zeros(2, 4))
        with pytest.raises(ValueError, match="history"):
            predict_ar3(torch.zeros(4))
        with pytest.raises(TypeError, match="history"):
            predict_ar3(torch.zeros(3, 4, dtype=torch.int64))
        with pytest.raises(ValueError, match="history.*finite"):
            predict_ar3(torch.full((3, 2), float("nan")))
        with pytest.raises(ValueError, match="mode"):
            predict_ar3(torch.zeros(3, 2), "cubic")
        with pytest.raises(ValueError, match="mode"):
            predict_ar3(torch.zeros(3, 2), "least_squares")
        with pytest.raises(ValueError, match="rotation_groups"):
            predict_ar3(torch.zeros(3, 4), rotation_groups=[(1, 2, 9)])
        with pytest.raises(ValueError, match="rotation_groups"):
            predict_ar3(torch.zeros(3, 6), rotation_groups=[(0, 1, 2), (2, 3, 4)])
        with pytest.raises(ValueError, match="indices"):
            RotationGroup((0, 0, 1))
        with pytest.raises(ValueError, match="upper"):
            predict_ar3(torch.zeros(3, 2), upper=torch.zeros(3))


class TestRotations:
    @pytest.mark.parametrize("mode", ["constant_acceleration", "damped"])
    def test_rotation_vector_across_wrap(self, mode):
        """Constant-rate rotation whose rotation vector wraps at π: SO(3) composition predicts
        exactly; extrapolating the numbers fails."""
        axis = torch.tensor([0.3, -0.5, 0.8], dtype=F64)
        axis = axis / axis.norm()
        angles = torch.tensor([2.7, 2.95, 3.2, 3.45], dtype=F64)  # 3.2 wraps to 3.2 − 2π
        rv = so3_log(so3_exp(angles[:, None] * axis))  # as a tracker would store them
        assert float(rv[2] @ axis) < 0  # the wrap happened in the history
        hist = torch.cat([torch.zeros(3, 2, dtype=F64), rv[:3]], dim=1)  # D = 5, group 2..4
        truth = so3_exp(angles[3] * axis)
        damping = (1.0, 0.4)
        pred = predict_ar3(hist, mode, damping=damping, rotation_groups=[(2, 3, 4)])
        assert float(geodesic_angle(so3_exp(pred[2:]), truth)) < 1e-9
        assert float(pred[2:].norm()) <= math.pi + 1e-9
        naive = predict_ar3(hist, mode, damping=damping)
        if mode == "damped":
            assert float(geodesic_angle(so3_exp(naive[2:]), truth)) > 1.0
        else:
            # integer coefficients turn the 2π jump into 3·2π along the same axis: the same
            # rotation by accident, but a vector of norm ≈ 15 rad that any limit would clamp
            assert float(naive[2:].norm()) > 4 * math.pi
        # body-frame composition also exact for a constant-rate rotation about a moving axis
        r0 = so3_exp(torch.tensor([0.4, 1.0, -2.0], dtype=F64))
        omega = torch.tensor([0.5, -0.9, 0.7], dtype=F64)
        rs = r0 @ so3_exp(torch.arange(4, dtype=F64)[:, None] * omega)
        pred = predict_ar3(so3_log(rs[:3]), rotation_groups=[(0, 1, 2)])
        assert float(geodesic_angle(so3_exp(pred), rs[3])) < 1e-9

    @pytest.mark.parametrize("mode", ["constant_acceleration", "damped"])
    def test_euler_angles_across_wrap(self, mode):
        """Root rotation as ZYX angles (wrapped to (−π, π] like a BVH): composed on SO(3) via a
        to_matrix callback, predicted exactly (constant rate) where angle extrapolation fails."""
        omega = torch.tensor([0.05, 0.02, 0.45], dtype=F64)  # mostly yaw, fast
        r0 = Rotation.from_euler("ZYX", [2.4, 0.2, -0.1]).as_matrix()
        rs = torch.tensor(r0) @ so3_exp(torch.arange(4, dtype=F64)[:, None] * omega)
        eul = torch.tensor(Rotation.from_matrix(rs.numpy()).as_euler("ZYX"))
        assert torch.allclose(ZYX(eul), rs, atol=1e-12)
        yaw = eul[:, 0]
        assert bool((yaw[1:] - yaw[:-1]).abs().max() > math.pi)  # wrap inside the window
        hist = torch.cat([torch.randn(4, 3, dtype=F64), eul], dim=1)[:3]
        group = RotationGroup((3, 4, 5), to_matrix=ZYX)
        damping = (1.0, 0.4)  # any λ with λ1 = 1 is exact at constant rate
        pred = predict_ar3(hist, mode, damping=damping, rotation_groups=[group])
        assert float(geodesic_angle(ZYX(pred[3:]), rs[3])) < 1e-8
        # continuous angles: nearest to the last ones, not re-wrapped
        assert float((pred[3:] - hist[-1, 3:]).abs().max()) < 1.0
        naive = predict_ar3(hist, mode, damping=damping)
        if mode == "damped":
            assert float(geodesic_angle(ZYX(naive[3:]), rs[3])) > 0.5
        else:  # the 2π jump is tripled (same yaw by accident), the rest is not exact
            assert float(naive[3].abs()) > 2 * math.pi
            assert float(geodesic_angle(ZYX(naive[3:]), rs[3])) > 1e-2

    def test_from_matrix_callback(self):
        """A user-supplied inverse (here scipy's wrapped ZYX) is used and gets the reference."""
        calls = []

        def from_m(R, ref):
            calls.append(ref.shape)
            return torch.tensor(Rotation.from_matrix(R.numpy()).as_euler("ZYX"))

        omega = torch.tensor([0.1, 0.0, 0.3], dtype=F64)
        rs = so3_exp(torch.arange(4, dtype=F64)[:, None] * omega)
        eul = torch.tensor(Rotation.from_matrix(rs.numpy()).as_euler("ZYX"))
        group = RotationGroup((0, 1, 2), to_matrix=ZYX, from_matrix=from_m)
        pred = predict_ar3(eul[:3], rotation_groups=[group])
        assert calls == [(3,)]
        assert float(geodesic_angle(ZYX(pred), rs[3])) < 1e-9

    def test_batched_particles(self):
        """(P, 3, D) histories of particles, each its own rotation."""
        g = torch.Generator().manual_seed(6)
        r0 = so3_exp(torch.randn(50, 3, generator=g, dtype=F64))
        om = 0.3 * torch.randn(50, 3, generator=g, dtype=F64)
        rs = r0[:, None] @ so3_exp(torch.arange(4, dtype=F64)[None, :, None] * om[:, None])
        hist = so3_log(rs[:, :3])
        pred = predict_ar3(hist, rotation_groups=[(0, 1, 2)])
        assert pred.shape == (50, 3)
        assert float(geodesic_angle(so3_exp(pred), rs[:, 3]).max()) < 1e-8

    def test_angles_from_matrix(self):
        """Generic inverse for non-orthogonal axes: exact rotation; the generating angles when
        the reference is close (away from gimbal lock)."""
        axes = torch.nn.functional.normalize(
            torch.tensor([[0.0, 0.2, 1.0], [0.3, 1.0, 0.0], [1.0, 0.0, 0.1]], dtype=F64), dim=-1
        )
        tm = _axes_to_matrix(axes)
        g = torch.Generator().manual_seed(7)
        th = (torch.rand(500, 3, generator=g, dtype=F64) * 2 - 1) * 3
        ref = th + 0.05 * torch.randn(500, 3, generator=g, dtype=F64)
        out = angles_from_matrix(tm, tm(th), ref)
        assert float(geodesic_angle(tm(out), tm(th)).max()) < 1e-9
        # world axes of the joint; singular value → 0 at gimbal lock
        r1 = axis_angle_rotation(axes[0].expand(500, 3), th[:, 0])
        r2 = axis_angle_rotation(axes[1].expand(500, 3), th[:, 1])
        w = torch.stack([axes[0].expand(500, 3), r1 @ axes[1], (r1 @ r2) @ axes[2]], -1)
        ok = torch.linalg.svdvals(w)[:, -1] > 0.1
        assert int(ok.sum()) > 400
        assert torch.allclose(out[ok], th[ok], atol=1e-8)
        # winding: reference near 2π + θ gives 2π + θ
        out2 = angles_from_matrix(tm, tm(th[:5]), th[:5] + 2 * math.pi)
        assert torch.allclose(out2, th[:5] + 2 * math.pi, atol=1e-8)
        with pytest.raises(ValueError, match="reference"):
            angles_from_matrix(tm, tm(th), th[:4])
        with pytest.raises(ValueError, match="R"):
            angles_from_matrix(tm, th, th)

class TestSkeleton:
    def test_root_group_human31(self):
        """Root rotation of human31 (3 angles through its root axes), constant-rate yaw that
        wraps past ±π: composed prediction matches the FK root rotation."""
        skeleton_mod = pytest.importorskip("torchmocap.skeleton")
        sk = skeleton_mod.human31().to(dtype=F64)
        (group,) = skeleton_rotation_groups(sk)
        assert group.indices == (3, 4, 5)
        g = torch.Generator().manual_seed(9)
        theta = torch.zeros(4, sk.num_dofs, dtype=F64)
        omega = torch.tensor([0.02, -0.03, 0.5], dtype=F64)
        r0 = so3_exp(torch.tensor([0.1, 0.05, 2.9], dtype=F64))
        rs = r0 @ so3_exp(torch.arange(4, dtype=F64)[:, None] * omega)
        ref = torch.zeros(3, dtype=F64)
        for t in range(4):  # angles wrapped into (−π, π] as a BVH reader would give them
            ang = angles_from_matrix(group.to_matrix, rs[t], ref)
            ang = torch.remainder(ang + math.pi, 2 * math.pi) - math.pi
            theta[t, 3:6] = ang
            ref = ang
        assert float((theta[1:, 3] - theta[:-1, 3]).abs().max()) > math.pi  # yaw wrapped
        theta[:, 6:] = 0.01 * torch.randn(4, sk.num_dofs - 6, generator=g, dtype=F64)
        root_rot = sk(theta).rotations[:, 0]
        assert torch.allclose(root_rot, rs, atol=1e-9)
        pred = predict_ar3(theta[:3], rotation_groups=[group], lower=sk.lower, upper=sk.upper)
        got = sk(pred[None]).rotations[0, 0]
        assert float(geodesic_angle(got, rs[3])) < 1e-8
        naive = predict_ar3(theta[:3], "damped", damping=(1.0, 0.3))
        assert float(geodesic_angle(sk(naive[None]).rotations[0, 0], rs[3])) > 0.1

    def test_from_axes(self):
        group = RotationGroup.from_axes((0, 1, 2), [[0, 0, 2.0], [0, 1, 0], [1, 0, 0]])
        t = torch.tensor([0.3, -0.2, 1.1], dtype=F64)
        assert torch.allclose(group.matrix(t), ZYX(t))
        with pytest.raises(ValueError, match="axes"):
            RotationGroup.from_axes((0, 1, 2), [[0, 0, 0.0], [0, 1, 0], [1, 0, 0]])
        with pytest.raises(ValueError, match="axes"):
            RotationGroup.from_axes((0, 1, 2), [[0, 0, 1.0], [0, 1, 0]])

    def test_exception(self):
        skeleton_mod = pytest.importorskip("torchmocap.skeleton")
        sk = skeleton_mod.human31()
        with pytest.raises(ValueError, match="joints.*l_elbow"):
            skeleton_rotation_groups(sk, ["l_elbow"])
        groups = skeleton_rotation_groups(sk, ["pelvis", "l_hip"])
        assert groups[1].indices == tuple(sk.joint_dofs("l_hip"))


def test_float32_rotation_group():
    """float32 history: composed prediction accurate to float32 precision (the Gauss–Newton
    inverse runs in float64 internally)."""
    omega = torch.tensor([0.05, 0.02, 0.45], dtype=F64)
    r0 = torch.tensor(Rotation.from_euler("ZYX", [2.4, 0.2, -0.1]).as_matrix())
    rs = r0 @ so3_exp(torch.arange(4, dtype=F64)[:, None] * omega)
    eul = torch.tensor(Rotation.from_matrix(rs.numpy()).as_euler("ZYX")).float()
    group = RotationGroup.from_axes((0, 1, 2), [[0, 0, 1.0], [0, 1, 0], [1, 0, 0]])
    pred = predict_ar3(eul[:3], rotation_groups=[group])
    assert pred.dtype == torch.float32
    assert float(geodesic_angle(ZYX(pred.double()), rs[3])) < 1e-5


class TestPosePredictor:
    """The tracker's predictor module: AR(3) with the root on SO(3) from three estimates, half a
    velocity step from two, the estimate itself from one; always inside the joint limits."""

    def test_feature_history_lengths(self):
        from torchmocap.filters import PosePredictor
        from torchmocap.skeleton import human31

        sk = human31()
        p = PosePredictor(sk, damping=(0.8, 0.3))
        e = sk.dof_index("l_elbow_flex")
        h = sk.zero_pose((3,))
        h[:, e] = torch.tensor([0.2, 0.4, 0.7])
        # damped: x1 + 0.8 (x1 - x2) + 0.3 ((x1 - x2) - (x2 - x3))
        assert p(h)[e].item() == pytest.approx(0.7 + 0.8 * 0.3 + 0.3 * (0.3 - 0.2), abs=1e-5)
        assert p(h[1:])[e].item() == pytest.approx(0.7 + 0.5 * 0.3, abs=1e-6)
        assert torch.equal(p(h[2:]), h[2])
        assert PosePredictor(sk, "constant_position")(h)[e].item() == pytest.approx(0.7)
        ca = PosePredictor(sk, "constant_acceleration")(h)[e].item()
        assert ca == pytest.approx(3 * 0.7 - 3 * 0.4 + 0.2, abs=1e-5)
        h[:, e] = torch.tensor([2.0, 2.4, 2.6])  # extrapolates past the 150 deg elbow limit
        assert p(h)[e].item() == pytest.approx(float(sk.upper[e]))

    def test_feature_root_heading_across_the_seam(self):
        from torchmocap.filters import PosePredictor
        from torchmocap.skeleton import human31

        sk = human31()
        rz = sk.dof_index("pelvis_rz")
        h = sk.zero_pose((3,))
        h[:, rz] = torch.tensor([3.0, 3.1, 3.2])  # constant rate through +pi
        out = PosePredictor(sk, "constant_acceleration")(h)[rz].item()
        d = math.remainder(out - 3.3, 2 * math.pi)
        assert abs(d) < 1e-4

    def test_exception(self):
        from torchmocap.filters import PosePredictor
        from torchmocap.skeleton import human31

        sk = human31()
        with pytest.raises(ValueError, match="mode"):
            PosePredictor(sk, "least_squares")
        with pytest.raises(ValueError, match="damping"):
            PosePredictor(sk, damping=(1.0,))
        with pytest.raises(ValueError, match="history"):
            PosePredictor(sk)(torch.zeros(3, 5))
