"""SensorManifold: g / g^{-1} round trips, calibration (eq. 8), solution choice, errors."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.geometry import geodesic_angle, matrix_to_quaternion, random_rotation_matrix
from torchmocap.ik import PAPER_SENSORS, SensorManifold, SensorManifoldError
from torchmocap.skeleton import Skeleton, human31

F64 = torch.float64


def _random_poses(sk, n, gen, margin=0.05, dtype=F64):
    lo, hi = sk.lower.to(dtype).clone(), sk.upper.to(dtype).clone()
    lo = torch.where(torch.isinf(lo), torch.full_like(lo, -3.0), lo + margin)
    hi = torch.where(torch.isinf(hi), torch.full_like(hi, 3.0), hi - margin)
    return lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=dtype)


@pytest.fixture(scope="module")
def sk64():
    return human31().double()


@pytest.fixture(scope="module")
def manifold64(sk64):
    return SensorManifold(sk64).double()


class TestSensorManifold:
    def test_smoke(self, manifold64):
        m = manifold64
        assert m.num_active == 16 and m.num_sensors == 5  # paper: 31 DoF -> 16-dim manifold
        assert m.passive_joints == ["pelvis", "l_shoulder", "r_shoulder", "l_hip", "r_hip"]
        th = torch.zeros(3, 31, dtype=F64)
        sol = m.inverse(m(th), m.sensor_orientations(th))
        assert sol.theta.shape == (3, 31) and sol.residual.shape == (3, 5)

    def test_cardinality(self, manifold64):
        m = manifold64
        g = torch.Generator().manual_seed(0)
        th = _random_poses(m.skeleton, 6, g).reshape(2, 3, 31)
        S = m.sensor_orientations(th)  # (2, 3, 5, 3, 3)
        assert S.shape == (2, 3, 5, 3, 3)
        assert m.inverse(m(th), S).theta.shape == (2, 3, 31)
        # one shared sensor set for many particles
        xa = m(th).reshape(6, 16)
        sol = m.inverse(xa, S[0, 0])
        assert sol.theta.shape == (6, 31) and sol.within_limits.shape == (6, 5)
        # quaternion input
        sol_q = m.inverse(xa, matrix_to_quaternion(S[0, 0]))
        assert torch.allclose(sol_q.theta, sol.theta, atol=1e-12)

    def test_feature_roundtrip_within_limits(self, manifold64):
        """g^{-1}(g(theta), sensors(theta)) = theta; float64 residual << 1e-9 rad."""
        m = manifold64
        g = torch.Generator().manual_seed(1)
        th = _random_poses(m.skeleton, 5000, g)
        S = m.sensor_orientations(th)
        sol = m.inverse(m(th), S, reference=th)
        assert float(sol.residual.max()) < 1e-9
        assert float((sol.theta - th).abs().max()) < 1e-9
        assert bool(sol.within_limits.all())
        # without a reference: a (possibly different) exact solution with the same bone frames
        sol0 = m.inverse(m(th), S)
        assert float(sol0.residual.max()) < 1e-9
        ang = geodesic_angle(m.bone_orientations(sol0.theta), m.bone_orientations(th))
        assert float(ang.max()) < 1e-9
        assert torch.equal(m(sol0.theta), m(th))

    def test_feature_arbitrary_sensor_orientations(self, manifold64):
        """Any active coordinates and any sensor orientations are matched exactly (the passive
        joints of human31 have mutually orthogonal axes, so every rotation is reachable)."""
        m = manifold64
        g = torch.Generator().manual_seed(2)
        xa = m(_random_poses(m.skeleton, 4000, g))
        R = random_rotation_matrix((4000, 5), g, dtype=F64)
        sol = m.inverse(xa, R)
        assert float(sol.residual.max()) < 1e-9
        got = m.bone_orientations(sol.theta)  # independent check through the skeleton's FK
        assert float(geodesic_angle(got, R).max()) < 1e-9
        assert torch.equal(m(sol.theta), xa)

    def test_feature_noise_argument(self, manifold64):
        """inverse(x_a, R, noise=q) == inverse(x_a, R R(q)): fused GEMM path, per-particle
        sensors, matrix noise -- all agree."""
        from torchmocap.geometry import quaternion_to_matrix, random_quaternion

        m = manifold64
        g = torch.Generator().manual_seed(12)
        th = _random_poses(m.skeleton, 64, g)
        xa = m(th)
        R = random_rotation_matrix(5, g, dtype=F64)
        q = random_quaternion((64, 5), g, dtype=F64)
        ref = m.inverse(xa, R @ quaternion_to_matrix(q), reference=th)
        for sens, noise in ((R, q), (R.expand(64, 5, 3, 3), q), (R, quaternion_to_matrix(q))):
            sol = m.inverse(xa, sens, noise=noise, reference=th)
            assert torch.allclose(sol.theta, ref.theta, atol=1e-10)
            assert float(sol.residual.max()) < 1e-9
        with pytest.raises(ValueError, match="sensors"):
            m.inverse(xa, R, noise=q[:, :3])

    def test_feature_calibration(self, sk64):
        """Sensors with unknown mounting offsets: calibrate on frame 0 (eq. 8), then recover."""
        m = SensorManifold(sk64).double()
        g = torch.Generator().manual_seed(3)
        R_sb = random_rotation_matrix(5, g, dtype=F64)
        th = _random_poses(sk64, 50, g)
        R_tb = m.bone_orientations(th)
        R_ts = R_tb @ R_sb.transpose(-1, -2)  # what the sensors read
        m.calibrate(th[0], R_ts[0])
        assert torch.allclose(m.sensor_to_bone, R_sb, atol=1e-12)
        sol = m.inverse(m(th), R_ts, reference=th)
        assert float((sol.theta - th).abs().max()) < 1e-9
        assert torch.allclose(m.sensor_orientations(th), R_ts, atol=1e-12)
        # fused noise path with calibration offsets: identity noise changes nothing
        ident = torch.zeros(50, 5, 4, dtype=F64)
        ident[..., 0] = 1
        sol_n = m.inverse(m(th), R_ts[0], noise=ident, reference=th)
        sol_0 = m.inverse(m(th), R_ts[0], reference=th)
        assert torch.allclose(sol_n.theta, sol_0.theta, atol=1e-10)

    def test_feature_limits_then_reference(self, manifold64):
        m = manifold64
        sk = m.skeleton
        th = torch.zeros(31, dtype=F64)
        th[sk.joint_dofs("l_shoulder")] = torch.tensor([0.4, 0.3, 0.2], dtype=F64)
        S = m.sensor_orientations(th)
        i = m.passive_joints.index("l_shoulder")
        # reference = the other solution of the shoulder, which violates the int limit (+-pi-ish)
        other = torch.tensor([0.4 - math.pi, math.pi - 0.3, 0.2 - math.pi], dtype=F64)
        ref = th.clone()
        ref[sk.joint_dofs("l_shoulder")] = other
        sol = m.inverse(m(th), S, reference=ref)
        assert torch.allclose(sol.theta[sk.joint_dofs("l_shoulder")], th[sk.joint_dofs(
            "l_shoulder")], atol=1e-12)
        assert bool(sol.within_limits[i])
        # the root is unlimited: the solution closest to the reference wins
        th2 = th.clone()
        th2[sk.joint_dofs("pelvis")[3:]] = torch.tensor([0.5, 0.2, -0.1], dtype=F64)
        alt = torch.tensor([0.5 - math.pi, math.pi - 0.2, -0.1 + math.pi], dtype=F64)
        ref2 = th2.clone()
        ref2[sk.joint_dofs("pelvis")[3:]] = alt + 0.05
        sol2 = m.inverse(m(th2), m.sensor_orientations(th2), reference=ref2)
        assert torch.allclose(sol2.theta[sk.joint_dofs("pelvis")[3:]], alt, atol=1e-12)

    def test_feature_gimbal(self, manifold64):
        m = manifold64
        sk = m.skeleton
        th = torch.zeros(31, dtype=F64)
        th[sk.joint_dofs("l_hip")] = torch.tensor([0.3, math.pi / 2, 0.1], dtype=F64)
        ref = th.clone()
        sol = m.inverse(m(th), m.sensor_orientations(th), reference=ref)
        i = m.passive_joints.index("l_hip")
        assert bool(sol.gimbal[i])
        assert float(sol.residual.max()) < 1e-9
        assert torch.allclose(sol.theta, th, atol=1e-9)

    def test_feature_float32(self):
        m = SensorManifold(human31())
        g = torch.Generator().manual_seed(4)
        th = _random_poses(m.skeleton, 2000, g, dtype=torch.float32)
        sol = m.inverse(m(th), m.sensor_orientations(th), reference=th)
        assert sol.theta.dtype == torch.float32
        assert float(sol.residual.max()) < 1e-4
        assert float((sol.theta - th).abs().max()) < 1e-3

    def test_feature_non_orthogonal_axes_general_solver(self):
        spec = {"name": "skew", "joints": [
            {"name": "root", "parent": None, "offset": [0, 0, 1], "axes": [[0, 0, 1], [1, 0, 0],
                                                                         [0, 1, 0]]},
            {"name": "shoulder", "parent": "root", "offset": [0.2, 0, 0.3],
             "axes": [[1, 0, 0], [0, 0.6, 0.8], [0.0, 1.0, 0.0]]},
            {"name": "elbow", "parent": "shoulder", "offset": [0, 0, -0.3], "axes": [[1, 0, 0]]},
            {"name": "hand", "parent": "elbow", "offset": [0, 0, -0.3]},
        ]}
        sk = Skeleton.from_dict(spec).double()
        m = SensorManifold(sk, {"torso": "root", "forearm": "elbow"}).double()
        assert not m._orthogonal and m.passive_joints == ["root", "shoulder"]
        g = torch.Generator().manual_seed(5)
        th = (torch.rand(2000, sk.num_dofs, generator=g, dtype=F64) - 0.5) * 2.0
        sol = m.inverse(m(th), m.sensor_orientations(th), reference=th)
        # 1e-7, not 1e-9: the skeleton keeps its axis algebra (K, K^2) in float32, so with a
        # non-axis-aligned axis its float64 FK is itself only ~1e-8 from a rotation
        assert float(sol.residual.max()) < 1e-7
        assert float((sol.theta - th).abs().max()) < 1e-6
        # unreachable forearm orientations: least-squares answer with a reported residual
        R = random_rotation_matrix((2000, 2), g, dtype=F64)
        sol = m.inverse(m(th), R)
        ach = geodesic_angle(m.bone_orientations(sol.theta), R)
        assert torch.allclose(sol.residual, ach, atol=1e-7)
        assert float(sol.residual[:, 1].max()) > 1e-3  # some are unreachable
        assert float(sol.residual[:, 0].max()) < 1e-7  # the root is always reachable

    def test_feature_custom_placement(self, sk64):
        m = SensorManifold(sk64, {"chest": "spine", "l_upper_arm": "l_shoulder"}).double()
        assert m.passive_joints == ["spine", "l_shoulder"] and m.num_active == 25
        g = torch.Generator().manual_seed(6)
        th = _random_poses(sk64, 500, g)
        sol = m.inverse(m(th), m.sensor_orientations(th), reference=th)
        assert float((sol.theta - th).abs().max()) < 1e-9
        m2 = SensorManifold(sk64, {"back": "pelvis", "l_forearm": "l_elbow"},
                            passive={"l_forearm": "spine"}).double()
        th[:, sk64.joint_dofs("l_shoulder")] = 0.0  # spine passive: shoulder is active
        sol = m2.inverse(m2(th), m2.sensor_orientations(th), reference=th)
        assert float((sol.theta - th).abs().max()) < 1e-9

    def test_exception(self, sk64, manifold64):
        m = manifold64
        xa = torch.zeros(4, 16, dtype=F64)
        q = torch.zeros(4, 5, 4, dtype=F64)
        q[..., 0] = 1
        with pytest.raises(ValueError, match="sensors"):
            m.inverse(xa, q * 1.1)
        bad = q.clone()
        bad[0, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="sensors"):
            m.inverse(xa, bad)
        with pytest.raises(ValueError, match="sensors"):
            m.inverse(xa, q[:, :4])
        with pytest.raises(ValueError, match="sensors"):
            m.inverse(xa, torch.eye(3, dtype=F64).expand(4, 3, 3, 3))
        with pytest.raises(ValueError, match="x_a"):
            m.inverse(torch.zeros(4, 15, dtype=F64), q)
        with pytest.raises(ValueError, match="theta"):
            m(torch.zeros(4, 30))
        with pytest.raises(SensorManifoldError, match="unknown bone"):
            SensorManifold(sk64, {"back": "pelvis", "x": "tail"})
        with pytest.raises(SensorManifoldError, match="passive"):
            SensorManifold(sk64, PAPER_SENSORS, passive={"back": "l_knee"})
        with pytest.raises(SensorManifoldError, match="no free 3-DoF joint"):
            SensorManifold(sk64, {"upper": "l_shoulder", "fore": "l_elbow"})
        with pytest.raises(SensorManifoldError, match="same bone"):
            SensorManifold(sk64, {"a": "l_elbow", "b": "l_elbow"})

    @pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
    def test_exception_not_rotations(self, sk64, dtype):
        """2R, zero, reflections and skewed matrices are not sensor orientations; rotations
        with float-level rounding (products of float32 rotations) are."""
        m = SensorManifold(human31()).to(dtype)
        g = torch.Generator().manual_seed(21)
        th = _random_poses(m.skeleton, 4, g, dtype=dtype)
        R = m.sensor_orientations(th)  # (4, 5, 3, 3)
        xa = m(th)
        flip = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=dtype))
        skew = torch.eye(3, dtype=dtype)
        skew[0, 1] = 1e-2 if dtype == torch.float32 else 1e-4
        bad = {"2R": 2 * R[0, 0], "zero": torch.zeros(3, 3, dtype=dtype),
               "det -1": R[0, 0] @ flip, "skewed": R[0, 0] @ skew}
        for what, M in bad.items():
            S = R.clone()
            S[2, 3] = M
            with pytest.raises(ValueError, match=r"sensors: expected rotation matrices") as e:
                m.inverse(xa, S)
            assert "sensor 3" in str(e.value), what
            with pytest.raises(ValueError, match=r"sensors0: expected rotation matrices"):
                m.calibrate(th[2], S[2])
            with pytest.raises(ValueError, match=r"noise: expected rotation matrices"):
                m.inverse(xa, R, noise=S)
        # rounding-level deviations pass: a chain of 50 float products of rotations
        P = R[0].clone()
        for k in range(50):
            P = P @ R[k % 4]
        m.inverse(xa, P)
        m.calibrate(th[0], R[0])
        # quaternions: non-unit and non-finite, named
        q = matrix_to_quaternion(R[0])
        with pytest.raises(ValueError, match="sensors0: expected unit quaternions"):
            m.calibrate(th[0], 2 * q)
        nan = q.clone()
        nan[1, 2] = float("nan")
        with pytest.raises(ValueError, match="sensors0: expected finite"):
            m.calibrate(th[0], nan)
        inf = R[0].clone()
        inf[1, 2, 2] = float("inf")
        with pytest.raises(ValueError, match="sensors0: expected finite"):
            m.calibrate(th[0], inf)
        with pytest.raises(ValueError, match="noise: expected unit quaternions"):
            m.inverse(xa, R, noise=torch.zeros(4, 5, 4, dtype=dtype))

    def test_gradcheck(self, manifold64):
        m = manifold64
        g = torch.Generator().manual_seed(7)
        th = _random_poses(m.skeleton, 3, g, margin=0.3)
        S = m.sensor_orientations(th)
        xa = m(th).clone().requires_grad_()
        assert torch.autograd.gradcheck(
            lambda x: m.inverse(x, S, reference=th, compute_residual=False).theta, (xa,))
        # the passive angles do depend on the active ones (spine above shoulders, elbows below)
        out = m.inverse(xa, S, reference=th).theta
        grad = torch.autograd.grad(out[:, m.passive_index[1]].sum(), xa)[0]
        assert float(grad.abs().sum()) > 0

    @pytest.mark.slow
    def test_compiled_matches_eager(self):
        """torch.compile'd g^{-1} core (opt-in) gives the eager answer (compiles ~30 s)."""
        m = SensorManifold(human31())
        g = torch.Generator().manual_seed(13)
        th = _random_poses(m.skeleton, 64, g, dtype=torch.float32)
        q = torch.nn.functional.normalize(torch.randn(64, 5, 4, generator=g), dim=-1)
        S = m.sensor_orientations(th[0])
        ref = m.inverse(m(th), S, noise=q, reference=th)
        m.compile_inverse()
        got = m.inverse(m(th), S, noise=q, reference=th)
        assert torch.allclose(got.theta, ref.theta, atol=1e-5)
        assert torch.equal(got.within_limits, ref.within_limits)

    def test_module_device_dtype(self, sk64):
        m = SensorManifold(human31())
        assert m.sensor_to_bone.dtype == torch.float32
        m64 = m.double()
        assert m64.passive_axes.dtype == F64 and m64.sensor_to_bone.dtype == F64
