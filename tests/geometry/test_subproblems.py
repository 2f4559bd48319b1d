"""Tests of the Paden–Kahan subproblems and the 3-axis decomposition (REFERENCE §3 recipes)."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.geometry import axis_angle_rotation, random_rotation_matrix
from torchmocap.geometry.subproblems import (
    rotate_about_axis,
    subproblem1,
    subproblem2,
    three_axis_decomposition,
    three_axis_rotation,
)

F64 = torch.float64


def _unit(n, gen, dtype=F64):
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=dtype), dim=-1)


def _wrap(a):
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class TestSubproblem1:
    def test_smoke(self):
        k = torch.tensor([0.0, 0.0, 1.0])
        r = subproblem1(k, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
        assert r.theta.item() == pytest.approx(math.pi / 2, abs=1e-6)
        assert bool(r.exact) and not bool(r.degenerate)

    def test_feature_forward_problems(self):
        g = torch.Generator().manual_seed(1)
        n = 20000
        k, p = _unit(n, g), torch.randn(n, 3, generator=g, dtype=F64)
        th = (torch.rand(n, generator=g, dtype=F64) * 2 - 1) * math.pi
        q = rotate_about_axis(k, th, p)
        r = subproblem1(k, p, q)
        assert bool(r.exact.all())
        assert float(r.residual.max()) < 1e-12
        ok = ~r.degenerate
        assert float(_wrap(r.theta - th)[ok].abs().max()) < 1e-8

    def test_feature_least_squares_is_minimum(self):
        g = torch.Generator().manual_seed(2)
        n = 500
        k, p, q = _unit(n, g), torch.randn(n, 3, generator=g, dtype=F64), torch.randn(
            n, 3, generator=g, dtype=F64)
        r = subproblem1(k, p, q)
        assert not bool(r.exact.any())
        for d in (1e-6, -1e-6):
            other = (rotate_about_axis(k, r.theta + d, p) - q).norm(dim=-1)
            assert bool((other >= r.residual - 1e-14).all())

    def test_feature_degenerate(self):
        k = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        r = subproblem1(k, torch.tensor([0.0, 0.0, 2.0], dtype=F64),
                        torch.tensor([0.0, 0.0, 2.0], dtype=F64))
        assert bool(r.degenerate) and float(r.theta) == 0.0 and bool(r.exact)

    def test_exception(self):
        with pytest.raises(ValueError, match="p"):
            subproblem1(torch.zeros(3), torch.zeros(4), torch.zeros(3))

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(3)
        k = _unit(4, g)
        p = torch.randn(4, 3, generator=g, dtype=F64, requires_grad=True)
        q = torch.randn(4, 3, generator=g, dtype=F64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda a, b: subproblem1(k, a, b).theta, (p, q))


class TestSubproblem2:
    def test_feature_forward_problems_orthogonal_and_random_axes(self):
        g = torch.Generator().manual_seed(4)
        n = 100000
        w1, w2, p = _unit(n, g), _unit(n, g), torch.randn(n, 3, generator=g, dtype=F64)
        t = (torch.rand(n, 2, generator=g, dtype=F64) * 2 - 1) * math.pi
        q = rotate_about_axis(w1, t[:, 0], rotate_about_axis(w2, t[:, 1], p))
        r = subproblem2(w1, w2, p, q)
        assert bool(r.exact.all())
        assert float(r.residual.max()) < 1e-9 * max(1.0, float(p.norm(dim=-1).max()))
        # the generating angles are among the two solutions (away from degenerate cases)
        err = (_wrap(r.theta1 - t[:, :1]).abs() + _wrap(r.theta2 - t[:, 1:]).abs()).min(-1).values
        ok = ~r.degenerate & (r.theta1[:, 0] - r.theta1[:, 1]).abs().gt(1e-3)
        assert float(err[ok].max()) < 1e-6

    def test_feature_least_squares_is_local_minimum(self):
        g = torch.Generator().manual_seed(5)
        n = 2000
        w1, w2 = _unit(n, g), _unit(n, g)
        p, q = torch.randn(n, 3, generator=g, dtype=F64), torch.randn(n, 3, generator=g, dtype=F64)
        r = subproblem2(w1, w2, p, q)
        ls = ~r.exact
        assert int(ls.sum()) > 100  # mostly unreachable: different norms / missing circles
        t1, t2 = r.theta1[:, 0], r.theta2[:, 0]

        def res(a, b):
            return (rotate_about_axis(w1, a, rotate_about_axis(w2, b, p)) - q).norm(dim=-1)

        base = res(t1, t2)
        for d1, d2 in ((1e-5, 0), (-1e-5, 0), (0, 1e-5), (0, -1e-5), (1e-5, 1e-5), (1e-5, -1e-5)):
            assert bool((res(t1 + d1, t2 + d2)[ls] >= base[ls] - 1e-12).all())
        # and it is the global optimum: compare with a dense grid on a few problems
        grid = torch.linspace(-math.pi, math.pi, 721, dtype=F64)
        A, B = torch.meshgrid(grid, grid, indexing="ij")
        for i in torch.nonzero(ls)[:5, 0].tolist():
            x = rotate_about_axis(w1[i], A, rotate_about_axis(w2[i], B, p[i].expand(*A.shape, 3)))
            best = (x - q[i]).norm(dim=-1).min()
            assert float(base[i]) <= float(best) + 1e-9

    def test_feature_parallel_axes(self):
        w = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
        w2 = torch.tensor([1e-10, 0.0, 1.0], dtype=F64)
        w2 = w2 / w2.norm()
        p = torch.tensor([1.0, 0.0, 0.3], dtype=F64)
        q = rotate_about_axis(w, torch.tensor(0.7, dtype=F64), p)
        r = subproblem2(w, w2, p, q)
        assert bool(r.parallel) and bool(r.exact)
        assert torch.isfinite(r.theta1).all() and float(r.residual.max()) < 1e-9
        r = subproblem2(w, -w, p, q)
        assert bool(r.parallel) and float(r.residual.max()) < 1e-12

    def test_feature_degenerate_p_on_axis(self):
        ex, ey, ez = torch.eye(3, dtype=F64)
        q = rotate_about_axis(ez, torch.tensor(0.4, dtype=F64), ey)
        r = subproblem2(ez, ey, ey, q)  # p on w2: t2 free
        assert bool(r.degenerate) and float(r.residual.max()) < 1e-12

    def test_cardinality(self):
        w1 = torch.tensor([0.0, 0.0, 1.0]).expand(5, 7, 3)
        r = subproblem2(w1, torch.tensor([0.0, 1.0, 0.0]), torch.randn(5, 7, 3), torch.randn(7, 3))
        assert r.theta1.shape == (5, 7, 2) and r.exact.shape == (5, 7)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(6)
        ez, ey = torch.tensor([0.0, 0, 1], dtype=F64), torch.tensor([0.0, 1, 0], dtype=F64)
        p = torch.tensor([[1.0, 0.2, 0.1], [0.3, 0.5, 0.8]], dtype=F64)
        t = torch.rand(2, 2, generator=g, dtype=F64)
        q = rotate_about_axis(ez, t[:, 0], rotate_about_axis(ey, t[:, 1], p)).requires_grad_()
        assert torch.autograd.gradcheck(lambda x: subproblem2(ez, ey, p, x).theta1, (q,))


class TestThreeAxis:
    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    def test_feature_orthogonal_axes_all_reachable(self, dtype):
        g = torch.Generator().manual_seed(7)
        n = 100000 if dtype == F64 else 20000
        R = random_rotation_matrix(n, g, dtype=dtype)
        ex, ey, ez = torch.eye(3, dtype=dtype)
        r = three_axis_decomposition(R, ez, ey, ex)
        assert bool(r.exact.all())
        tol = 1e-10 if dtype == F64 else 2e-3
        assert float(r.residual.max()) < tol
        if dtype == F64:
            assert float(r.residual.max()) < 1e-12

    def test_feature_generating_angles_recovered(self):
        g = torch.Generator().manual_seed(8)
        n = 50000
        w = torch.nn.functional.normalize(torch.randn(n, 3, 3, generator=g, dtype=F64), dim=-1)
        ang = (torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1) * math.pi
        R = three_axis_rotation(w, ang)
        r = three_axis_decomposition(R, w[:, 0], w[:, 1], w[:, 2])
        assert bool(r.exact.all()) and float(r.residual.max()) < 1e-9
        err = _wrap(r.angles - ang[:, None]).abs().amax(-1).min(-1).values
        ok = ~r.gimbal & (r.angles[:, 0] - r.angles[:, 1]).abs().amax(-1).gt(1e-4)
        assert float(err[ok].max()) < 1e-6

    def test_feature_unreachable_flagged(self):
        g = torch.Generator().manual_seed(9)
        n = 20000
        w = torch.nn.functional.normalize(torch.randn(n, 3, 3, generator=g, dtype=F64), dim=-1)
        R = random_rotation_matrix(n, g, dtype=F64)
        r = three_axis_decomposition(R, w[:, 0], w[:, 1], w[:, 2])
        frac = 1 - r.exact.double().mean().item()
        assert 0.30 < frac < 0.46  # REFERENCE: ~38% of random R unreachable with random axes
        assert bool((r.residual[~r.exact] > 1e-7).all())  # tol 1e-9 on gamma^2
        assert float(r.residual[r.exact].max()) < 1e-8
        assert torch.isfinite(r.angles).all()

    def test_feature_gimbal_lock(self):
        ex, ey, ez = torch.eye(3, dtype=F64)
        # rot(z, a) rot(y, pi/2) rot(x, b): R x = rot(z,a) rot(y,pi/2) x = -z  -> gimbal
        R = three_axis_rotation(torch.stack([ez, ey, ex]),
                                torch.tensor([0.3, math.pi / 2, -0.5], dtype=F64))
        r = three_axis_decomposition(R, ez, ey, ex)
        assert bool(r.gimbal) and bool(r.exact)
        assert float(r.residual.max()) < 1e-8
        assert float(r.angles[0, 0]) == 0.0
        r = three_axis_decomposition(R, ez, ey, ex, default_theta1=torch.tensor(0.3, dtype=F64))
        assert float(r.residual.max()) < 1e-8
        assert torch.allclose(r.angles[0], torch.tensor([0.3, math.pi / 2, -0.5], dtype=F64))

    def test_cardinality(self):
        ex, ey, ez = torch.eye(3)
        R = axis_angle_rotation(ex.expand(4, 5, 3), torch.rand(4, 5))
        r = three_axis_decomposition(R, ez, ey, ex)
        assert r.angles.shape == (4, 5, 2, 3) and r.residual.shape == (4, 5, 2)
        assert r.gimbal.shape == (4, 5)

    def test_exception(self):
        with pytest.raises(ValueError, match="R"):
            three_axis_decomposition(torch.eye(4), *torch.eye(3))

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(10)
        ex, ey, ez = torch.eye(3, dtype=F64)
        ang = (torch.rand(3, 3, generator=g, dtype=F64) - 0.5)
        w = torch.stack([ez, ey, ex])

        def f(a):
            return three_axis_decomposition(three_axis_rotation(w, a), ez, ey, ex).angles

        assert torch.autograd.gradcheck(f, (ang.requires_grad_(),))


class TestOrthogonalThreeAxis:
    AXES = [
        [[0, 0, 1], [1, 0, 0], [0, 1, 0]],
        [[-1, 0, 0], [0, -1, 0], [0, 0, -1]],
        [[-1, 0, 0], [0, 1, 0], [0, 0, 1]],
    ]

    @pytest.mark.parametrize("axes", AXES)
    def test_feature_matches_general_solver(self, axes):
        from torchmocap.geometry.subproblems import orthogonal_three_axis_decomposition

        g = torch.Generator().manual_seed(11)
        ax = torch.tensor(axes, dtype=F64)
        R = random_rotation_matrix(50000, g, dtype=F64)
        ang, gimbal = orthogonal_three_axis_decomposition(R, ax)
        rec = three_axis_rotation(ax.expand(50000, 2, 3, 3), ang)
        assert float((rec - R[:, None]).abs().max()) < 1e-12
        gen = three_axis_decomposition(R, ax[0], ax[1], ax[2]).angles
        # same solution set (order may differ)
        d = _wrap(ang[:, :, None] - gen[:, None]).abs().amax(-1)  # (N, 2, 2)
        same = torch.minimum(d[:, 0, 0] + d[:, 1, 1], d[:, 0, 1] + d[:, 1, 0])
        assert float(same.max()) < 1e-8
        assert not bool(gimbal.any())

    def test_feature_gimbal_exact(self):
        from torchmocap.geometry.subproblems import orthogonal_three_axis_decomposition

        ax = torch.tensor(self.AXES[0], dtype=F64)
        R = three_axis_rotation(ax, torch.tensor([0.3, -math.pi / 2, 0.2], dtype=F64))
        ang, gimbal = orthogonal_three_axis_decomposition(
            R, ax, default_theta1=torch.tensor(0.3, dtype=F64))
        assert bool(gimbal)
        assert torch.allclose(ang[0], torch.tensor([0.3, -math.pi / 2, 0.2], dtype=F64))
        assert float((three_axis_rotation(ax.expand(2, 3, 3), ang) - R).abs().max()) < 1e-12

    def test_gradcheck(self):
        from torchmocap.geometry.subproblems import orthogonal_three_axis_decomposition

        ax = torch.tensor(self.AXES[1], dtype=F64)
        a = torch.tensor([[0.3, 0.4, -0.2], [1.0, -0.5, 2.0]], dtype=F64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda x: orthogonal_three_axis_decomposition(three_axis_rotation(ax, x), ax)[0],
            (a,))
