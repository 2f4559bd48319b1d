"""The robust 2D-joint energy: value, gradcheck, analytic gradient and Gauss-Newton Hessian
against autograd, missing joints, confidence weights, outliers, empty evidence, the module."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import (
    ROBUST_COSTS,
    EmptyEvidenceError,
    FrameEnergy,
    Joints2DLikelihood,
    Poses,
    WeightedSum,
    joints2d_energy,
    robust_cost,
)
from torchmocap.skeleton import human31


def _pose(sk, g, scale=0.3):
    th = sk.zero_pose((1,))
    th[0, 6:] = scale * torch.randn(sk.num_dofs - 6, generator=g, dtype=th.dtype)
    return sk.clamp(th)


@pytest.fixture(scope="module")
def scene64():
    sk = human31().double()
    rig = make_ring_rig(2, image_size=(640, 480))  # float64
    g = torch.Generator().manual_seed(0)
    th = _pose(sk, g)
    pix = rig.project(sk(th).positions[0])[0]  # (C, J, 2)
    conf = 0.5 + 0.5 * torch.rand(2, 21, 1, generator=g, dtype=torch.float64)
    obs = torch.cat([pix + 2 * torch.randn(2, 21, 2, generator=g, dtype=torch.float64), conf],
                    -1)
    obs[0, 3, 2] = 0.0  # a missed joint
    return sk, rig, th, obs, g


def _frame(obs):
    return Frame(index=0, time=0.0, joints2d=obs)


def _term(sk, rig, **kw):
    return Joints2DLikelihood(rig, skeleton=sk, **kw)


class TestRobustCost:
    def test_feature_values_and_derivatives(self):
        z = torch.tensor([0.0, 0.5, 1.0, 4.0, 100.0], dtype=torch.float64, requires_grad=True)
        for kind in ROBUST_COSTS:
            rho, drho = robust_cost(z, kind)
            (g,) = torch.autograd.grad(rho.sum(), z)
            assert torch.allclose(g, drho, atol=1e-12), kind
            assert rho[0] == 0 and bool((torch.diff(rho) > 0).all()), kind  # 0 at 0, increasing
        assert robust_cost(torch.tensor([3.0]), "cauchy")[0].item() == pytest.approx(math.log(4))
        assert robust_cost(torch.tensor([1e8]), "geman_mcclure")[0].item() <= 1.0
        assert robust_cost(torch.tensor([4.0]), "huber")[0].item() == pytest.approx(3.0)

    def test_exception(self):
        with pytest.raises(ValueError, match="robust"):
            robust_cost(torch.zeros(1), "tukey")


class TestJoints2DLikelihood:
    def test_smoke(self, scene64):
        sk, rig, th, obs, g = scene64
        term = _term(sk, rig)
        o = term.prepare(_frame(obs))
        assert o.num_valid == 2 * 21 - 1 and o.uv.shape == (2, 21, 2)
        e = term.energy(Poses(th.expand(3, -1), sk), o)
        assert e.shape == (3,) and bool(torch.isfinite(e).all())
        assert term.requires == ("joints2d",)

    def test_feature_zero_at_exact_projections_and_grows(self):
        sk = human31()
        rig = make_ring_rig(1).float()
        th = sk.zero_pose((1,))
        th[0, sk.dof_index("l_elbow_flex")] = 1.0
        pix = rig.project(sk(th).positions[0])[0]
        obs = torch.cat([pix, torch.ones(1, 21, 1)], -1)
        term = _term(sk, rig)
        V = FrameEnergy(term, term.prepare(_frame(obs)), sk)
        pert = th.expand(4, -1).clone()
        for k, s in enumerate((0.0, 0.05, 0.2, 0.5)):
            pert[k, 6:] += s
        v = V(pert)
        assert v[0].item() == pytest.approx(0.0, abs=1e-6)
        assert bool((torch.diff(v) > 0).all())

    def test_feature_sum_is_n_times_weighted_mean(self, scene64):
        sk, rig, th, obs, g = scene64
        x = th + 0.1 * torch.randn(4, sk.num_dofs, generator=g, dtype=torch.float64)
        pos = sk(x).positions
        s = _term(sk, rig, reduction="sum")
        m = _term(sk, rig, reduction="mean")
        os_, om = s.prepare(_frame(obs)), m.prepare(_frame(obs))
        pix = rig.project(pos)[0]
        z = ((pix - obs[..., :2]) ** 2).sum(-1) / 16.0
        w = obs[..., 2]
        mean = (w * torch.log1p(z)).sum((-1, -2)) / w.sum()
        assert torch.allclose(m.energy(Poses(x, sk), om), mean, atol=1e-9)
        assert torch.allclose(s.energy(Poses(x, sk), os_), mean * 41, atol=1e-8)
        assert torch.allclose(joints2d_energy(pos, os_, rig), mean * 41, atol=1e-8)

    def test_gradcheck(self, scene64):
        sk, rig, th, obs, g = scene64
        for robust in ROBUST_COSTS:
            term = _term(sk, rig, robust=robust)
            V = FrameEnergy(term, term.prepare(_frame(obs)), sk)
            x = (th + 0.05 * torch.randn(2, sk.num_dofs, generator=g, dtype=torch.float64))
            x.requires_grad_(True)
            assert torch.autograd.gradcheck(V, (x,), eps=1e-6, atol=1e-5), robust

    def test_feature_analytic_gradient_equals_autograd(self, scene64):
        sk, rig, th, obs, g = scene64
        x = th + 0.2 * torch.randn(6, sk.num_dofs, generator=g, dtype=torch.float64)
        x[:, :3] += 0.1 * torch.randn(6, 3, generator=g, dtype=torch.float64)
        for robust in ROBUST_COSTS:
            for reduction in ("sum", "mean"):
                term = _term(sk, rig, robust=robust, reduction=reduction)
                o = term.prepare(_frame(obs))
                xx = x.clone().requires_grad_(True)
                v = FrameEnergy(term, o, sk)(xx)
                (ga,) = torch.autograd.grad(v.sum(), xx)
                v2, g2, H = term.gauss_newton(Poses(x, sk), o)
                assert torch.allclose(v2, v.detach(), rtol=1e-10, atol=1e-10), robust
                assert torch.allclose(g2, ga, rtol=1e-8, atol=1e-8 * ga.abs().max()), robust
                assert H.shape == (6, 31, 31)
                assert torch.allclose(H, H.transpose(-1, -2))
                assert float(torch.linalg.eigvalsh(H).min()) > -1e-8 * float(H.abs().max())

    def test_feature_gauss_newton_is_the_hessian_at_zero_residual(self):
        sk = human31().double()
        rig = make_ring_rig(1, image_size=(640, 480))
        g = torch.Generator().manual_seed(3)
        th = _pose(sk, g, 0.4)
        pix = rig.project(sk(th).positions[0])[0]
        obs = torch.cat([pix, torch.ones(1, 21, 1, dtype=torch.float64)], -1)
        for robust in ("cauchy", "huber", "gaussian"):
            term = _term(sk, rig, robust=robust)
            o = term.prepare(_frame(obs))
            V = FrameEnergy(term, o, sk)
            H_true = torch.autograd.functional.hessian(lambda x, V=V: V(x[None])[0], th[0])
            _, _, H = term.gauss_newton(th, o)
            assert torch.allclose(H[0], H_true, atol=1e-7 * float(H_true.abs().max())), robust

    def test_feature_missing_joints_are_skipped(self, scene64):
        sk, rig, th, obs, g = scene64
        term = _term(sk, rig)
        x = th + 0.1 * torch.randn(3, sk.num_dofs, generator=g, dtype=torch.float64)
        base = term.energy(Poses(x, sk), term.prepare(_frame(obs)))
        moved = obs.clone()
        moved[0, 3, :2] = torch.tensor([1e4, -1e4])  # the missed joint's pixels: ignored
        assert torch.equal(term.energy(Poses(x, sk), term.prepare(_frame(moved))), base)
        nan = obs.clone()
        nan[0, 3, :2] = math.nan  # a missed joint may carry anything
        assert torch.allclose(term.energy(Poses(x, sk), term.prepare(_frame(nan))), base)

    def test_feature_missed_detections_cost_nothing_even_at_infinite_pixels(self):
        """A missed detection (weight 0) adds nothing, also where a pose projects its joint to
        an infinite pixel (0 * inf must not make the energy NaN)."""
        from torchmocap.likelihoods.joints2d import Joints2DObservation, joints2d_energy

        class Far:
            def project(self, X):
                pix = X[..., None, :, :2] * 100.0
                pix[..., 0, 1, :] = float("inf")  # joint 1 infinitely far in the camera
                return pix, None, None

        uv = torch.zeros(1, 2, 2, dtype=torch.float64)
        obs = Joints2DObservation(uv, torch.tensor([[1.0, 0.0]], dtype=torch.float64),
                                  torch.tensor([0, 1]), 1, 1.0)
        X = torch.tensor([[[0.01, 0.0, 1.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
        v = joints2d_energy(X, obs, Far(), 2.0)
        assert bool(torch.isfinite(v).all())
        assert float(v) == pytest.approx(math.log1p(1.0 / 4.0))

    def test_feature_confidences_weigh_the_detections(self, scene64):
        sk, rig, th, obs, g = scene64
        term = _term(sk, rig, reduction="mean")
        x = th.clone()
        a = obs.clone()
        a[..., 2] = 1.0
        a[0, 5, :2] += 40.0  # one detection far off
        e_full = term.energy(Poses(x, sk), term.prepare(_frame(a)))
        b = a.clone()
        b[0, 5, 2] = 0.1  # the same detection, low confidence
        e_low = term.energy(Poses(x, sk), term.prepare(_frame(b)))
        assert e_low.item() < e_full.item()
        # the exact weighted mean
        pix = rig.project(sk(x).positions)[0]
        rho = torch.log1p(((pix - b[..., :2]) ** 2).sum(-1) / 16.0)
        w = b[..., 2]
        assert e_low.item() == pytest.approx(float((w * rho).sum() / w.sum()), rel=1e-10)
        # min_confidence drops it
        drop = _term(sk, rig, reduction="mean", min_confidence=0.2)
        ob = drop.prepare(_frame(b))
        assert ob.num_valid == 2 * 21 - 1 and float(ob.weight[0, 5]) == 0.0

    def test_feature_an_outlier_changes_the_energy_by_a_bounded_amount(self, scene64):
        sk, rig, th, obs, g = scene64
        x = th.clone()
        for robust, bound in (("geman_mcclure", 1.0), ("cauchy", None)):
            term = _term(sk, rig, robust=robust, reduction="sum")
            changes = []
            for dist in (50.0, 500.0, 5000.0, 50000.0):
                o = obs.clone()
                o[0, 7, :2] += dist
                o[0, 7, 2] = 1.0
                ref = obs.clone()
                ref[0, 7, 2] = 1.0
                v = term.energy(Poses(x, sk), term.prepare(_frame(o)))
                v0 = term.energy(Poses(x, sk), term.prepare(_frame(ref)))
                changes.append(float(v - v0))
            w = obs[..., 2].clone()
            w[0, 7] = 1.0
            n_over_w = 41 / float(w.sum())
            if bound is not None:  # bounded cost: at most one detection's worth
                assert max(changes) <= bound * n_over_w * 1.0 + 1e-9
            else:  # Cauchy: grows like log, 1000x farther costs ~2 log(1000) more, not 1e6x
                assert changes[-1] - changes[0] < 2 * math.log(1000) * n_over_w + 1.0
        # and a Gaussian (non-robust) cost explodes
        gauss = _term(sk, rig, robust="gaussian")
        o = obs.clone()
        o[0, 7, :2] += 5000.0
        assert float(gauss.energy(Poses(x, sk), gauss.prepare(_frame(o)))) > 1e5
        # the influence of a far outlier redescends: its gradient vanishes with the distance
        one = _term(sk, rig, robust="cauchy", joints=["l_wrist"])
        grads = []
        for dist in (10.0, 1e5):
            o = obs.clone()
            o[:, 7, :2] = rig.project(sk(x).positions[0])[0][:, 7] + dist
            o[:, 7, 2] = 1.0
            grads.append(one.gauss_newton(x, one.prepare(_frame(o)))[1].norm())
        assert float(grads[1]) < 1e-3 * float(grads[0])

    def test_feature_empty_evidence_is_not_a_perfect_score(self, scene64):
        sk, rig, th, obs, g = scene64
        empty = obs.clone()
        empty[..., 2] = 0.0
        with pytest.raises(EmptyEvidenceError, match="no valid 2D joint"):
            _term(sk, rig).prepare(_frame(empty))
        term = _term(sk, rig, on_empty="uninformative")
        o = term.prepare(_frame(empty))
        assert o.empty and o.num_valid == 0
        x = th.expand(3, -1)
        v = term.energy(Poses(x, sk), o)
        # constant (no pose is favoured) and worse than a perfect match
        assert torch.equal(v, v[:1].expand(3)) and float(v[0]) > 0
        pix = rig.project(sk(th).positions[0])[0]
        perfect = torch.cat([pix, torch.ones(2, 21, 1, dtype=torch.float64)], -1)
        vp = term.energy(Poses(th, sk), term.prepare(_frame(perfect)))
        assert float(v[0]) > float(vp[0]) + 1.0
        v2, g2, H2 = term.gauss_newton(x, o)
        assert torch.equal(v2, v) and not bool(g2.any()) and not bool(H2.any())

    def test_feature_joint_subset(self, scene64):
        sk, rig, th, obs, g = scene64
        legs = ["l_hip", "l_knee", "l_ankle", "l_toe"]
        term = _term(sk, rig, joints=legs)
        o = term.prepare(_frame(obs))
        assert o.uv.shape == (2, 4, 2) and o.joints.tolist() == [sk.joint_index(j) for j in legs]
        x = th.expand(2, -1).clone()
        x[1, sk.dof_index("r_elbow_flex")] += 0.5  # not a leg: no change
        v = term.energy(Poses(x, sk), o)
        assert v[0].item() == pytest.approx(v[1].item(), abs=1e-12)

    def test_exception(self, scene64):
        sk, rig, th, obs, g = scene64
        with pytest.raises(ValueError, match="scale_px"):
            _term(sk, rig, scale_px=0.0)
        with pytest.raises(ValueError, match="robust"):
            _term(sk, rig, robust="l1")
        with pytest.raises(ValueError, match="on_empty"):
            _term(sk, rig, on_empty="ignore")
        with pytest.raises(ValueError, match="needs the skeleton"):
            Joints2DLikelihood(rig, joints=["l_hip"])
        with pytest.raises(ValueError, match="cameras"):
            _term(sk, rig).prepare(_frame(obs[:1]))
        with pytest.raises(ValueError, match="joints per camera"):
            _term(sk, rig).prepare(_frame(obs[:, :20]))
        with pytest.raises(ValueError, match="no 2D joint"):
            _term(sk, rig).prepare(Frame(index=4, time=0.0))
        bad = obs.clone()
        bad[0, 0, 2] = -1.0
        with pytest.raises(ValueError, match=">= 0"):
            _term(sk, rig).prepare(_frame(bad))
        distorted = make_ring_rig(2, image_size=(640, 480))
        distorted.dist[:, 0] = 0.05
        term = Joints2DLikelihood(distorted, skeleton=sk)
        with pytest.raises(ValueError, match="pinhole"):
            term.gauss_newton(th, term.prepare(_frame(obs)))

    def test_module_in_a_weighted_sum(self, scene64):
        sk, rig, th, obs, g = scene64
        term = _term(sk, rig)
        ws = WeightedSum({"joints2d": term}, {"joints2d": 2.0})
        x = th + 0.1 * torch.randn(3, sk.num_dofs, generator=g, dtype=torch.float64)
        v_ws = FrameEnergy(ws, ws.prepare(_frame(obs)), sk)(x)
        v_t = FrameEnergy(term, term.prepare(_frame(obs)), sk)(x)
        assert torch.allclose(v_ws, 2 * v_t)
        assert ws.requires == ("joints2d",)
