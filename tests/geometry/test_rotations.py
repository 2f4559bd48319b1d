"""SO(3) maps, quaternions, twists: closed forms, round trips, branches and gradients."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from torchmocap.geometry import (
    axis_angle_rotation,
    axis_angle_to_quaternion,
    geodesic_angle,
    hat,
    make_transform,
    matrix_to_quaternion,
    quaternion_angle,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_slerp,
    quaternion_to_axis_angle,
    quaternion_to_matrix,
    random_quaternion,
    random_rotation_matrix,
    revolute_twist,
    se3_exp,
    so3_exp,
    so3_log,
    transform_points,
    vee,
)


def _tol(dtype):
    return 2e-5 if dtype == torch.float32 else 1e-10


def _rotvecs(n, gen, max_angle=math.pi, dtype=torch.float64):
    x = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    ax = torch.nn.functional.normalize(x, dim=-1)
    ang = torch.rand(n, 1, generator=gen, dtype=torch.float64) * max_angle
    return (ax * ang).to(dtype)


class TestSO3:
    def test_smoke(self, dtype, device):
        w = torch.zeros(4, 3, dtype=dtype, device=device)
        R = so3_exp(w)
        assert R.shape == (4, 3, 3) and R.dtype == dtype and R.device == device
        assert torch.equal(R, torch.eye(3, dtype=dtype, device=device).expand(4, 3, 3))

    def test_cardinality(self, dtype):
        w = torch.randn(2, 5, 3, dtype=dtype)
        assert so3_exp(w).shape == (2, 5, 3, 3)
        assert so3_log(so3_exp(w)).shape == (2, 5, 3)

    def test_feature_vs_scipy(self):
        gen = torch.Generator().manual_seed(0)
        w = _rotvecs(500, gen)
        R = so3_exp(w)
        ref = torch.from_numpy(Rotation.from_rotvec(w.numpy()).as_matrix())
        assert (R - ref).abs().max() < 1e-12

    @pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.5, math.pi - 1e-3,
                                       math.pi - 1e-6])
    def test_exp_log_round_trip_branches(self, angle):
        axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64),
                                             dim=0)
        w = axis * angle
        R = so3_exp(w)
        ref = torch.from_numpy(Rotation.from_rotvec(w.numpy()).as_matrix())
        assert (R - ref).abs().max() < 1e-14
        w2 = so3_log(R)
        assert (w2 - w).abs().max() < 1e-9 * max(1.0, 1 / max(math.pi - angle, 1e-3) * 1e-3)
        assert torch.isfinite(w2).all()

    def test_log_near_pi_float32(self):
        gen = torch.Generator().manual_seed(1)
        ax = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen), dim=-1)
        w = ax * (math.pi - 1e-4)
        R = so3_exp(w)
        back = so3_exp(so3_log(R))
        assert (back - R).abs().max() < 1e-4

    def test_gradcheck(self):
        gen = torch.Generator().manual_seed(2)
        w = _rotvecs(6, gen, max_angle=3.0).requires_grad_(True)
        assert torch.autograd.gradcheck(so3_exp, (w,))
        w0 = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(so3_exp, (w0,))
        wl = _rotvecs(6, gen, max_angle=3.0).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: so3_log(so3_exp(x)), (wl,))

    def test_gradient_finite_at_zero(self):
        w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
        (so3_exp(w) * torch.arange(9.0, dtype=torch.float64).reshape(3, 3)).sum().backward()
        assert torch.isfinite(w.grad).all()
        # d/dw of sum(M * exp(w^)) at 0 equals vee(M - M^T) up to sign convention: hat is linear
        M = torch.arange(9.0, dtype=torch.float64).reshape(3, 3)
        expected = torch.stack([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
        assert torch.allclose(w.grad, expected)

    def test_hat_vee(self, dtype):
        w = torch.randn(7, 3, dtype=dtype)
        v = torch.randn(7, 3, dtype=dtype)
        assert torch.allclose(hat(w) @ v[..., None], torch.cross(w, v, dim=-1)[..., None],
                              atol=_tol(dtype))
        assert torch.allclose(vee(hat(w)), w)

    def test_axis_angle_rotation_matches_exp(self, dtype):
        gen = torch.Generator().manual_seed(3)
        w = _rotvecs(50, gen, dtype=dtype)
        ang = w.norm(dim=-1)
        R = axis_angle_rotation(w / ang[:, None], ang)
        assert torch.allclose(R, so3_exp(w), atol=_tol(dtype))

    def test_geodesic_angle(self, dtype):
        gen = torch.Generator().manual_seed(4)
        w = _rotvecs(200, gen, dtype=torch.float64)
        R1 = random_rotation_matrix(200, gen, dtype=torch.float64)
        R2 = R1 @ so3_exp(w)
        a = geodesic_angle(R1.to(dtype), R2.to(dtype))
        assert torch.allclose(a.double(), w.norm(dim=-1), atol=1e-5 if dtype == torch.float32
                              else 1e-10)

    def test_exception(self):
        with pytest.raises(ValueError, match="w: expected shape"):
            so3_exp(torch.zeros(4, 4))
        with pytest.raises(ValueError, match="R: expected shape"):
            so3_log(torch.zeros(3, 4))
        with pytest.raises(TypeError, match="w: expected a torch.Tensor"):
            so3_exp([0.0, 0.0, 0.0])


class TestQuaternion:
    def test_multiply_matches_matrices(self, dtype):
        gen = torch.Generator().manual_seed(5)
        q1 = random_quaternion(100, gen, dtype=dtype)
        q2 = random_quaternion(100, gen, dtype=dtype)
        lhs = quaternion_to_matrix(quaternion_multiply(q1, q2))
        rhs = quaternion_to_matrix(q1) @ quaternion_to_matrix(q2)
        assert torch.allclose(lhs, rhs, atol=_tol(dtype) * 5)

    def test_wxyz_convention_vs_scipy(self):
        gen = torch.Generator().manual_seed(6)
        q = random_quaternion(100, gen, dtype=torch.float64)
        ref = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scipy is x, y, z, w
        assert torch.allclose(quaternion_to_matrix(q), torch.from_numpy(ref), atol=1e-12)

    def test_matrix_round_trip_near_pi(self, dtype):
        gen = torch.Generator().manual_seed(7)
        ax = torch.nn.functional.normalize(torch.randn(3000, 3, generator=gen, dtype=torch.float64),
                                           dim=-1)
        for ang in (math.pi, math.pi - 1e-5, 1e-7, 2.0):
            R = so3_exp(ax * ang)
            q = matrix_to_quaternion(R.to(dtype))
            assert (q[:, 0] >= 0).all()
            assert (q.norm(dim=-1) - 1).abs().max() < _tol(dtype)
            back = quaternion_to_matrix(q).double()
            assert (back - R).abs().max() < (2e-6 if dtype == torch.float32 else 1e-12)

    def test_conjugate_is_inverse(self, dtype):
        q = random_quaternion(20, torch.Generator().manual_seed(8), dtype=dtype)
        e = quaternion_multiply(q, quaternion_conjugate(q))
        assert torch.allclose(e, torch.tensor([1.0, 0, 0, 0], dtype=dtype).expand(20, 4),
                              atol=_tol(dtype))

    def test_axis_angle_round_trip(self):
        gen = torch.Generator().manual_seed(9)
        w = _rotvecs(500, gen, max_angle=math.pi - 1e-3)
        w = torch.cat([w, torch.zeros(1, 3, dtype=torch.float64),
                       torch.tensor([[1e-9, 0, 0]], dtype=torch.float64)])
        q = axis_angle_to_quaternion(w)
        assert torch.allclose(quaternion_to_matrix(q), so3_exp(w), atol=1e-12)
        assert torch.allclose(quaternion_to_axis_angle(q), w, atol=1e-12)

    def test_angle_atan2_accuracy(self):
        # float32: atan2 form accurate at tiny angles where arccos of the dot product fails
        q1 = torch.tensor([[1.0, 0, 0, 0]])
        small = 1e-3  # radians
        q2 = axis_angle_to_quaternion(torch.tensor([[small, 0.0, 0.0]]))
        d = quaternion_angle(q1, q2)
        assert abs(d.item() - small) < 1e-7
        naive = 2 * torch.arccos((q1 * q2).sum(-1).abs().clamp(max=1))
        assert abs(naive.item() - small) > 1e-5  # the printed form is visibly off in float32
        # sign invariance (q and -q are one rotation)
        assert torch.allclose(quaternion_angle(q1, -q2), d)

    def test_angle_gradcheck(self):
        gen = torch.Generator().manual_seed(10)
        q1 = random_quaternion(4, gen, dtype=torch.float64).requires_grad_(True)
        q2 = random_quaternion(4, gen, dtype=torch.float64).requires_grad_(True)
        assert torch.autograd.gradcheck(quaternion_angle, (q1, q2))

    def test_slerp(self, dtype):
        gen = torch.Generator().manual_seed(11)
        w = _rotvecs(50, gen, max_angle=2.5, dtype=torch.float64)
        q0 = random_quaternion(50, gen, dtype=torch.float64)
        q1 = quaternion_multiply(q0, axis_angle_to_quaternion(w))
        for t in (0.0, 0.25, 0.5, 1.0):
            qt = quaternion_slerp(q0.to(dtype), q1.to(dtype), t)
            ref = quaternion_multiply(q0, axis_angle_to_quaternion(w * t))
            assert quaternion_angle(qt.double(), ref).max() < (1e-5 if dtype == torch.float32
                                                                 else 1e-10)
        # shorter arc with the sign flipped, and identical inputs
        qt = quaternion_slerp(q0, -q1, 0.5)
        assert quaternion_angle(qt, quaternion_multiply(q0, axis_angle_to_quaternion(w / 2))
                                ).max() < 1e-10
        assert torch.allclose(quaternion_slerp(q0, q0, 0.3), q0)

    def test_random_uniform_and_seeded(self):
        a = random_quaternion(20000, torch.Generator().manual_seed(3), dtype=torch.float64)
        b = random_quaternion(20000, torch.Generator().manual_seed(3), dtype=torch.float64)
        assert torch.equal(a, b)
        # Haar measure: rotation angle density (1 - cos t)/pi => E[t] = pi/2 + 2/pi
        ang = 2 * torch.atan2(a[:, 1:].norm(dim=-1), a[:, 0].abs())
        assert abs(ang.mean().item() - (math.pi / 2 + 2 / math.pi)) < 0.02
        R = random_rotation_matrix((3, 4), torch.Generator().manual_seed(1))
        assert R.shape == (3, 4, 3, 3)
        assert torch.allclose(torch.linalg.det(R), torch.ones(3, 4), atol=1e-5)


class TestTwist:
    def test_revolute_twist_rotates_about_point(self):
        gen = torch.Generator().manual_seed(12)
        axis = torch.nn.functional.normalize(torch.randn(10, 3, generator=gen,
                                                         dtype=torch.float64), dim=-1)
        point = torch.randn(10, 3, generator=gen, dtype=torch.float64)
        theta = torch.rand(10, 1, generator=gen, dtype=torch.float64) * 3
        T = se3_exp(revolute_twist(axis, point) * theta)
        # a point on the axis is fixed; any point rotates about the axis through `point`
        assert torch.allclose(transform_points(T, point + 0.7 * axis), point + 0.7 * axis,
                              atol=1e-12)
        x = torch.randn(10, 3, generator=gen, dtype=torch.float64)
        expected = point + (so3_exp(axis * theta) @ (x - point)[..., None])[..., 0]
        assert torch.allclose(transform_points(T, x), expected, atol=1e-12)

    def test_vs_matrix_exponential(self):
        gen = torch.Generator().manual_seed(13)
        xi = torch.randn(20, 6, generator=gen, dtype=torch.float64)
        X = torch.zeros(20, 4, 4, dtype=torch.float64)
        X[:, :3, :3] = hat(xi[:, 3:])
        X[:, :3, 3] = xi[:, :3]
        assert torch.allclose(se3_exp(xi), torch.linalg.matrix_exp(X), atol=1e-9)
        small = torch.zeros(2, 6, dtype=torch.float64)
        small[:, :3] = 1.0
        assert torch.allclose(se3_exp(small)[:, :3, 3], small[:, :3])

    def test_gradcheck(self):
        xi = torch.randn(3, 6, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(se3_exp, (xi,))

    def test_make_transform(self):
        R = random_rotation_matrix(5, torch.Generator().manual_seed(0), dtype=torch.float64)
        t = torch.randn(5, 3, dtype=torch.float64)
        T = make_transform(R, t)
        assert T.shape == (5, 4, 4)
        assert torch.equal(T[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(5, 4))


def test_geodesic_angle_gradient_finite_at_zero():
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone().requires_grad_(True)
    geodesic_angle(R, torch.eye(3, dtype=torch.float64).expand(2, 3, 3)).sum().backward()
    assert torch.isfinite(R.grad).all()
