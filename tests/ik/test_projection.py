"""Projection onto the skeleton manifold (Hauberg & Pedersen eqs. 6-7): round trips, monotone
cost, joint limits and constrained optimality, an independent solver, derivatives vs autograd,
module == function, errors."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.optimize
import torch

from torchmocap.ik import ProjectionResult, SkeletonProjection, project_to_skeleton
from torchmocap.ik.projection import _plan, _Problem
from torchmocap.skeleton import human31, upper_body

F64 = torch.float64
PRESETS = {"human31": human31, "upper_body": upper_body}


def _poses(sk, n, gen, dtype=F64, margin=0.05):
    """Uniform poses inside the joint limits (unlimited rotations in [-2, 2], translations in
    [-0.2, 0.2] m)."""
    lo, hi = sk.lower.to(dtype).clone(), sk.upper.to(dtype).clone()
    lo = torch.where(torch.isinf(lo), torch.full_like(lo, -2.0), lo + margin)
    hi = torch.where(torch.isinf(hi), torch.full_like(hi, 2.0), hi - margin)
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=gen, dtype=dtype)
    th[:, sk.translation_dofs] *= 0.1
    return th


def _problem(sk, n, seed, noise=0.03, perturb=0.0, dtype=F64):
    """Poses, their joint positions plus ``noise`` (metres per coordinate) and a warm start
    perturbed by ``perturb`` radians (clamped into the limits)."""
    gen = torch.Generator().manual_seed(seed)
    th = _poses(sk, n, gen, dtype)
    x = sk(th).positions
    x = x + noise * torch.randn(x.shape, generator=gen, dtype=dtype)
    start = sk.clamp(th + perturb * torch.randn(th.shape, generator=gen, dtype=dtype))
    return th, x, start


def _cost(sk, theta, x, theta0, prior_weight, joints=None, weights=None):
    """Independent evaluation of the objective with the skeleton's own forward kinematics."""
    F = sk(theta).positions
    if joints is not None:
        F = F[..., joints, :]
    d2 = ((F - x) ** 2).sum(-1)
    if weights is not None:
        d2 = d2 * weights
    return d2.sum(-1) + prior_weight**2 * ((theta - sk.clamp(theta0)) ** 2).sum(-1)


@pytest.fixture(scope="module")
def sk64():
    return human31().double()


class TestProjectToSkeleton:
    def test_smoke(self, device, dtype):
        sk = human31().to(device=device, dtype=dtype)
        th = torch.zeros(4, sk.num_dofs, dtype=dtype, device=device)
        x = sk(th).positions
        res = project_to_skeleton(sk, x, th)
        assert isinstance(res, ProjectionResult)
        assert res.theta.shape == (4, 31) and res.residual.shape == (4, 21)
        assert res.cost.shape == (4,) and res.converged.shape == (4,)
        assert res.theta.dtype == dtype and res.theta.device == x.device
        assert res.converged.dtype == torch.bool and isinstance(res.iterations, int)
        assert res.cost_trace is None
        assert res.residual.max() < (1e-5 if dtype == F64 else 1e-4)

    @pytest.mark.parametrize("P", [1, 500])
    def test_cardinality(self, P):
        sk = human31()
        th, x, start = _problem(sk, P, 3, noise=0.02, dtype=torch.float32)
        res = project_to_skeleton(sk, x, start, iterations=100)
        assert res.theta.shape == (P, 31) and res.residual.shape == (P, 21)
        assert res.converged.all()
        assert sk.within_limits(res.theta).all()
        # a shared (D,) warm start broadcasts over the batch
        res1 = project_to_skeleton(sk, x, th[0])
        assert res1.theta.shape == (P, 31)

    @pytest.mark.parametrize("name", ["human31", "upper_body"])
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_round_trip(self, name, seed):
        # exact joint positions of in-limit poses, warm start perturbed by ~0.1 rad per DoF:
        # the joint positions are recovered (angles need not be: a straight limb's twist and
        # the neck twist with the head on its axis are unobservable from positions)
        sk = PRESETS[name]().double()
        th, x, start = _problem(sk, 64, seed, noise=0.0, perturb=0.1)
        res = project_to_skeleton(sk, x, start, prior_weight=1e-6, tol=1e-9, iterations=100)
        assert res.converged.all()
        assert res.residual.max() < 1e-5
        assert (sk(res.theta).positions - sk(th).positions).norm(dim=-1).max() < 1e-5
        assert sk.within_limits(res.theta).all()

    def test_round_trip_float32(self):
        sk = human31()
        th, x, start = _problem(sk, 64, 4, noise=0.0, perturb=0.1, dtype=torch.float32)
        res = project_to_skeleton(sk, x, start, prior_weight=1e-6, tol=1e-6, iterations=100)
        assert res.theta.dtype == torch.float32
        assert res.residual.max() < 1e-4
        assert sk.within_limits(res.theta).all()

    def test_feature_result_fields(self, sk64):
        th, x, start = _problem(sk64, 32, 5)
        res = project_to_skeleton(sk64, x, start)
        # residual and cost agree with an independent evaluation at the returned poses
        F = sk64(res.theta).positions
        torch.testing.assert_close(res.residual, (F - x).norm(dim=-1), rtol=0, atol=1e-9)
        torch.testing.assert_close(res.cost, _cost(sk64, res.theta, x, start, 1e-3),
                                   rtol=1e-9, atol=1e-12)

    @pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
    def test_cost_monotone(self, dtype):
        sk = human31().to(dtype)
        th, x, start = _problem(sk, 100, 6, noise=0.03, perturb=0.2, dtype=dtype)
        res = project_to_skeleton(sk, x, start, iterations=25, return_trace=True)
        tr = res.cost_trace
        assert tr.shape == (res.iterations + 1, 100)
        assert (tr[1:] <= tr[:-1]).all()  # accepted steps never increase the cost
        assert (tr[-1] < tr[0]).all()
        torch.testing.assert_close(tr[0], _cost(sk, start, x, start, 1e-3))
        # the traced cost is the true cost (up to rounding), and `iterations=k` stops at row k
        torch.testing.assert_close(tr[-1], res.cost)
        for k in (1, 3):
            rk = project_to_skeleton(sk, x, start, iterations=k)
            assert rk.iterations == k
            torch.testing.assert_close(rk.cost, tr[k])
            torch.testing.assert_close(rk.cost, _cost(sk, rk.theta, x, start, 1e-3),
                                       rtol=1e-4 if dtype == torch.float32 else 1e-9,
                                       atol=1e-7 if dtype == torch.float32 else 1e-12)

    def test_iterations_zero_returns_clamped_start(self, sk64):
        th, x, start = _problem(sk64, 8, 7)
        out = start.clone()
        out[:, sk64.dof_index("l_knee_flex")] = -0.5  # outside the limits
        res = project_to_skeleton(sk64, x, out, iterations=0)
        torch.testing.assert_close(res.theta, sk64.clamp(out))
        assert res.iterations == 0 and not res.converged.any()

    def test_limits_and_constrained_minimum(self, sk64):
        # targets of poses far outside the limits (elbows and knees bent backwards, shoulder
        # twisted past its range): the result stays inside the box and is a constrained
        # minimum: no feasible coordinate move lowers the cost
        gen = torch.Generator().manual_seed(8)
        th = _poses(sk64, 24, gen)
        bad = th.clone()
        for name in ("l_elbow_flex", "r_elbow_flex", "l_knee_flex", "r_knee_flex"):
            bad[:, sk64.dof_index(name)] = -0.6 - 0.4 * torch.rand(24, generator=gen, dtype=F64)
        bad[:, sk64.dof_index("l_shoulder_int")] = 1.8
        x = sk64(bad).positions  # reachable only outside the limits
        res = project_to_skeleton(sk64, x, th, tol=1e-9, iterations=200)
        lo, hi = sk64.lower.double(), sk64.upper.double()
        assert ((res.theta >= lo) & (res.theta <= hi)).all()
        at_bound = (res.theta == lo) | (res.theta == hi)
        assert at_bound[:, sk64.dof_index("l_knee_flex")].float().mean() > 0.8  # on the bound
        assert res.converged.all()
        c0 = _cost(sk64, res.theta, x, th, 1e-3)  # ~0.05 m^2
        for eps in (1e-4, -1e-4, 1e-3, -1e-3):
            for d in range(sk64.num_dofs):
                moved = res.theta.clone()
                moved[:, d] += eps
                feasible = (moved[:, d] >= lo[d]) & (moved[:, d] <= hi[d])
                c1 = _cost(sk64, moved, x, th, 1e-3)
                assert (c1[feasible] >= c0[feasible] - 1e-9).all(), (d, eps)

    def test_kkt_with_noise(self, sk64):
        # first-order optimality from autograd: zero gradient on the free coordinates, the
        # gradient points outward on the coordinates held at a bound
        th, x, start = _problem(sk64, 40, 9, noise=0.03)
        res = project_to_skeleton(sk64, x, start, tol=1e-9, iterations=200)
        assert res.converged.all()
        t = res.theta.clone().requires_grad_(True)
        _cost(sk64, t, x, start, 1e-3).sum().backward()
        grad = t.grad
        lo, hi = sk64.lower.double(), sk64.upper.double()
        at_lo, at_hi = res.theta == lo, res.theta == hi
        free = ~(at_lo | at_hi)
        assert grad[free].abs().max() < 1e-7
        assert (grad[at_lo] >= -1e-7).all() and (grad[at_hi] <= 1e-7).all()

    def test_vs_scipy_least_squares(self, sk64):
        # an independent bounded least-squares solver (trust-region reflective) from the same
        # warm start reaches the same minimum
        th, x, start = _problem(sk64, 3, 10, noise=0.015)
        lo, hi = sk64.lower.double().numpy(), sk64.upper.double().numpy()
        lam = 1e-3
        res = project_to_skeleton(sk64, x, start, prior_weight=lam, tol=1e-10, iterations=200)
        for n in range(3):
            xn, t0 = x[n], start[n]

            def fun(v, xn=xn, t0=t0):
                t = torch.from_numpy(v)
                r = torch.cat([(sk64(t).positions - xn).reshape(-1), lam * (t - t0)])
                return r.numpy()

            sol = scipy.optimize.least_squares(fun, t0.numpy(), bounds=(lo, hi), method="trf",
                                               xtol=1e-14, ftol=1e-14, gtol=1e-12)
            assert abs(2 * sol.cost - float(res.cost[n])) < 1e-9 * max(1.0, 2 * sol.cost)
            assert float(res.cost[n]) <= 2 * sol.cost + 1e-12
            np.testing.assert_allclose(res.residual[n].numpy(),
                                       np.linalg.norm(fun(sol.x)[:63].reshape(21, 3), axis=1),
                                       atol=1e-5)

    def test_joint_subset_and_weights(self, sk64):
        th, x, start = _problem(sk64, 16, 11, noise=0.0, perturb=0.05)
        ends = ["head_top", "l_hand", "r_hand", "l_toe", "r_toe", "pelvis", "l_elbow",
                "r_elbow", "l_knee", "r_knee", "neck", "l_shoulder", "r_shoulder"]
        idx = [sk64.joint_index(j) for j in ends]
        res = project_to_skeleton(sk64, x[:, idx], start, joints=ends, prior_weight=1e-6,
                                  tol=1e-9, iterations=100)
        assert res.residual.shape == (16, len(ends))
        assert res.residual.max() < 1e-5
        # a zero-weight joint is ignored: an outlier on it changes nothing
        xo = x.clone()
        xo[:, sk64.joint_index("l_hand")] += 0.5
        w = torch.ones(21, dtype=F64)
        w[sk64.joint_index("l_hand")] = 0.0
        rw = project_to_skeleton(sk64, xo, start, joint_weights=w, tol=1e-9, iterations=100)
        keep = [j for j in range(21) if j != sk64.joint_index("l_hand")]
        rs = project_to_skeleton(sk64, xo[:, keep], start, joints=keep, tol=1e-9, iterations=100)
        torch.testing.assert_close(rw.cost, rs.cost, rtol=0, atol=1e-12)
        torch.testing.assert_close(rw.theta, rs.theta, rtol=0, atol=1e-7)
        # weights scale the squared distances
        w2 = torch.full((21,), 4.0, dtype=F64)
        th2, x2, s2 = _problem(sk64, 8, 12, noise=0.02)
        r1 = project_to_skeleton(sk64, x2, s2, prior_weight=0.0, tol=1e-9, iterations=100)
        r4 = project_to_skeleton(sk64, x2, s2, joint_weights=w2, prior_weight=0.0, tol=1e-9,
                                 iterations=100)
        torch.testing.assert_close(r4.cost, 4 * r1.cost, rtol=1e-7, atol=1e-12)

    def test_prior_holds_unobservable_directions(self, sk64):
        # the head joints lie on the neck-twist axis: positions do not observe the twist, the
        # pull towards the warm start keeps it where it was
        gen = torch.Generator().manual_seed(13)
        th = _poses(sk64, 10, gen)
        x = sk64(th).positions
        start = th.clone()
        twist = sk64.dof_index("neck_twist")
        start[:, twist] = th[:, twist] + 0.3
        start = sk64.clamp(start)
        res = project_to_skeleton(sk64, x, start, tol=1e-9, iterations=100)
        torch.testing.assert_close(res.theta[:, twist], start[:, twist], rtol=0, atol=1e-6)
        assert res.residual.max() < 1e-5

    def test_converged_flags(self, sk64):
        th, x, start = _problem(sk64, 50, 14, noise=0.03)
        r1 = project_to_skeleton(sk64, x, start, iterations=1)
        assert r1.iterations == 1 and not r1.converged.all()
        r = project_to_skeleton(sk64, x, start)
        assert r.converged.all() and r.iterations < 50

    def test_derivatives_match_autograd(self):
        # the moment-based Gauss-Newton matrix, exact Hessian and gradient (private helper)
        for sk in (human31().double(), upper_body().double()):
            gen = torch.Generator().manual_seed(15)
            th = _poses(sk, 3, gen)
            sel = list(range(0, sk.num_joints, 2))
            x = sk(th).positions[:, sel] + 0.1 * torch.randn(3, len(sel), 3, generator=gen,
                                                             dtype=F64)
            w = torch.rand(len(sel), generator=gen, dtype=F64) + 0.5
            th0 = sk.clamp(th + 0.1)
            prob = _Problem(sk, _plan(sk, F64, x.device), x, th0, sel, w, 1e-2)
            p, axes = prob.kinematics(th)
            Hn, g, dgn, Hgn = prob.derivatives(p, axes, prob.x, th - prob.theta0,
                                               torch.ones(3, dtype=torch.bool))
            for newton in (False, True):
                Hl = Hn if newton else Hgn
                assert (Hl.triu(1) == 0).all()
                H = Hl + Hl.transpose(1, 2) - torch.diag_embed(Hl.diagonal(dim1=1, dim2=2))
                for k in range(3):
                    def half_cost(t, k=k, sk=sk, sel=sel, x=x, w=w, th0=th0):
                        r = (sk(t).positions[sel] - x[k]) ** 2
                        return 0.5 * (r.sum(-1) * w).sum() + 0.5e-4 * ((t - th0[k]) ** 2).sum()

                    def weighted_positions(t, sk=sk, sel=sel, w=w):
                        return (sk(t).positions[sel] * w.sqrt()[:, None]).reshape(-1)

                    if newton:
                        ref = torch.autograd.functional.hessian(half_cost, th[k])
                    else:
                        Jr = torch.autograd.functional.jacobian(weighted_positions, th[k])
                        ref = Jr.T @ Jr + 1e-4 * torch.eye(sk.num_dofs, dtype=F64)
                    torch.testing.assert_close(H[k], ref, rtol=0, atol=1e-12)
                    grad = torch.autograd.functional.jacobian(half_cost, th[k])
                    torch.testing.assert_close(g[k], grad, rtol=0, atol=1e-12)
                    if not newton:  # the (floored) Gauss-Newton diagonal scales the damping
                        diag = ref.diagonal()
                        torch.testing.assert_close(
                            dgn[k], diag.clamp_min(0.1 * float(diag.mean())), rtol=0, atol=1e-12)

    def test_free_dofs_derivatives_are_the_submatrix(self):
        # with a subset of free DoFs (two of the three translations, some rotations) the
        # assembled model matrix and gradient are the full ones restricted to that subset
        sk = human31().double()
        gen = torch.Generator().manual_seed(17)
        th = _poses(sk, 2, gen)
        x = sk(th).positions + 0.05 * torch.randn(2, 21, 3, generator=gen, dtype=F64)
        w = torch.rand(21, generator=gen, dtype=F64) + 0.5
        free = [0, 2, 4, 7, 8, 12, 20, 21, 22, 30]
        full = _Problem(sk, _plan(sk, F64, x.device), x, th, list(range(21)), w, 1e-2)
        red = _Problem(sk, _plan(sk, F64, x.device), x, th, list(range(21)), w, 1e-2, free)
        for newton in (False, True):
            flag = torch.full((2,), newton)
            p, axes = full.kinematics(th)
            Hf, gf, df, _ = full.derivatives(p, axes, full.x, torch.zeros_like(th), flag)
            p, axes = red.kinematics(th)
            Hr, gr, dr, _ = red.derivatives(p, axes, red.x, torch.zeros(2, len(free),
                                                                      dtype=F64), flag)
            torch.testing.assert_close(Hr, Hf[:, free][:, :, free], rtol=0, atol=1e-12)
            torch.testing.assert_close(gr, gf[:, free], rtol=0, atol=1e-12)

    def test_free_dofs_solve_only_those(self, sk64):
        # the frozen DoFs keep each problem's own warm start exactly; the free ones reach the
        # minimum an independent bounded solver finds over them alone
        gen = torch.Generator().manual_seed(18)
        th = _poses(sk64, 3, gen)
        start = sk64.clamp(th + 0.1 * torch.randn(th.shape, generator=gen, dtype=F64))
        x = sk64(th).positions + 0.01 * torch.randn(3, 21, 3, generator=gen, dtype=F64)
        upper = [sk64.dof_index(n) for n in sk64.dof_names
                 if n.split("_")[0] in ("spine", "chest", "neck", "l", "r")
                 and not any(k in n for k in ("hip", "knee", "ankle", "toe"))]
        assert 8 < len(upper) < 25
        mask = torch.zeros(31, dtype=torch.bool)
        mask[upper] = True
        lam = 1e-3
        res = project_to_skeleton(sk64, x, start, free_dofs=mask, prior_weight=lam, tol=1e-10,
                                  iterations=200)
        frozen = ~mask
        assert torch.equal(res.theta[:, frozen], start[:, frozen])
        lo, hi = sk64.lower.double()[upper].numpy(), sk64.upper.double()[upper].numpy()
        for n in range(3):
            def fun(v, n=n):
                t = start[n].clone()
                t[upper] = torch.from_numpy(v)
                return torch.cat([(sk64(t).positions - x[n]).reshape(-1),
                                  lam * (t[upper] - start[n, upper])]).numpy()

            sol = scipy.optimize.least_squares(fun, start[n, upper].numpy(), bounds=(lo, hi),
                                               method="trf", xtol=1e-14, ftol=1e-14, gtol=1e-12)
            assert abs(2 * sol.cost - float(res.cost[n])) < 1e-8 * max(1.0, 2 * sol.cost)
        # the same as freezing them by zero-width limits in the full solve
        pinned = copy.deepcopy(sk64)
        one = start[:1].expand(3, -1)
        pinned.lower[frozen] = one[0, frozen]
        pinned.upper[frozen] = one[0, frozen]
        a = project_to_skeleton(pinned, x, one, prior_weight=lam, tol=1e-10, iterations=200)
        b = project_to_skeleton(sk64, x, one, free_dofs=upper, prior_weight=lam, tol=1e-10,
                                iterations=200)
        torch.testing.assert_close(b.theta, a.theta, rtol=0, atol=1e-6)
        # translations alone
        t = project_to_skeleton(sk64, x, start, free_dofs=[0, 1, 2], tol=1e-10, iterations=50)
        shift = (x - sk64(start).positions).mean(1)
        torch.testing.assert_close(t.theta[:, :3], start[:, :3] + shift, rtol=0, atol=1e-6)
        with pytest.raises(ValueError, match="free_dofs: indices must lie in"):
            project_to_skeleton(sk64, x, start, free_dofs=[0, 31])
        with pytest.raises(ValueError, match="free_dofs: duplicate"):
            project_to_skeleton(sk64, x, start, free_dofs=[3, 3])
        with pytest.raises(ValueError, match=r"free_dofs: expected a bool mask of shape \(31,\)"):
            project_to_skeleton(sk64, x, start, free_dofs=mask[:5])
        with pytest.raises(ValueError, match="free_dofs: expected at least one"):
            project_to_skeleton(sk64, x, start, free_dofs=[])
        with pytest.raises(ValueError, match="free_dofs: expected DoF indices"):
            project_to_skeleton(sk64, x, start, free_dofs=["neck"])

    def test_module(self, sk64):
        th, x, start = _problem(sk64, 20, 16)
        w = torch.linspace(0.5, 2.0, 21, dtype=F64)
        proj = SkeletonProjection(sk64, joint_weights=w, prior_weight=2e-3, iterations=12,
                                  tol=1e-5)
        a = proj(x, start)
        b = project_to_skeleton(sk64, x, start, joint_weights=w, prior_weight=2e-3,
                                iterations=12, tol=1e-5)
        assert torch.equal(a.theta, b.theta) and torch.equal(a.cost, b.cost)
        assert torch.equal(a.converged, b.converged) and a.iterations == b.iterations
        assert "prior_weight=0.002" in repr(proj)
        # the module moves and casts with its skeleton and buffers
        p32 = proj.float()
        assert p32.skeleton.offsets.dtype == torch.float32
        assert p32(x.float(), start.float()).theta.dtype == torch.float32

    def test_exception(self, sk64):
        th = torch.zeros(2, 31, dtype=F64)
        x = sk64(th).positions
        with pytest.raises(ValueError, match=r"targets: expected shape \(P, 21, 3\), got \(5, 3\)"):
            project_to_skeleton(sk64, torch.zeros(5, 3, dtype=F64), th)
        with pytest.raises(ValueError, match=r"targets: expected shape \(P, 21, 3\)"):
            project_to_skeleton(sk64, x[:, :20], th)
        with pytest.raises(ValueError, match="targets: expected finite"):
            project_to_skeleton(sk64, torch.full_like(x, float("nan")), th)
        with pytest.raises(ValueError, match=r"theta0: expected shape \(31,\) or \(2, 31\)"):
            project_to_skeleton(sk64, x, th[:, :30])
        with pytest.raises(ValueError, match=r"theta0: expected shape"):
            project_to_skeleton(sk64, x, torch.zeros(3, 31, dtype=F64))
        with pytest.raises(ValueError, match="theta0: expected finite"):
            project_to_skeleton(sk64, x, torch.full_like(th, float("inf")))
        with pytest.raises(ValueError, match="targets: expected at least one problem"):
            project_to_skeleton(sk64, x[:0], th[:0])
        with pytest.raises(ValueError, match=r"joint_weights: expected shape \(21,\)"):
            project_to_skeleton(sk64, x, th, joint_weights=torch.ones(3, dtype=F64))
        with pytest.raises(ValueError, match="joint_weights: expected finite values >= 0"):
            project_to_skeleton(sk64, x, th, joint_weights=-torch.ones(21, dtype=F64))
        with pytest.raises(ValueError, match="joint_weights: expected at least one positive"):
            project_to_skeleton(sk64, x, th, joint_weights=torch.zeros(21, dtype=F64))
        with pytest.raises(ValueError, match="prior_weight"):
            project_to_skeleton(sk64, x, th, prior_weight=-1.0)
        with pytest.raises(ValueError, match="iterations"):
            project_to_skeleton(sk64, x, th, iterations=-1)
        with pytest.raises(ValueError, match="tol"):
            project_to_skeleton(sk64, x, th, tol=float("nan"))
        with pytest.raises(ValueError, match="damping"):
            project_to_skeleton(sk64, x, th, damping=0.0)
        with pytest.raises(ValueError, match="joints: unknown joint 'nose'"):
            project_to_skeleton(sk64, x[:, :1], th, joints=["nose"])
        with pytest.raises(ValueError, match="joints: duplicate"):
            project_to_skeleton(sk64, x[:, :2], th, joints=[1, 1])
        with pytest.raises(ValueError, match="joints: index 40 out of range"):
            project_to_skeleton(sk64, x[:, :1], th, joints=[40])
        with pytest.raises(TypeError, match="skeleton: expected a Skeleton"):
            project_to_skeleton("human31", x, th)
        with pytest.raises(TypeError, match="targets: expected a torch.Tensor"):
            project_to_skeleton(sk64, x.numpy(), th)
        with pytest.raises(ValueError, match="joints: unknown joint"):
            SkeletonProjection(sk64, joints=["nose"])
