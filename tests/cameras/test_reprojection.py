"""Reprojection pieces of the camera refinement: Catmull–Rom interpolation in time (whole frames
exact, quadratics reproduced inside, lines extrapolated past the ends, C¹ in time), the robust
losses (IRLS weight = ρ'), residuals and the loss of tensor points and of a callable of the
cameras' times, missed detections out of the loss, gradchecks in float64, and the
RigRefinement module equal to the functions it wraps."""

from __future__ import annotations

import pytest
import torch

from torchmocap.cameras import (
    RefinementError,
    RigParametrization,
    RigPriors,
    RigRefinement,
    RobustLoss,
    interpolate_in_time,
    make_ring_rig,
    prior_loss,
    reprojection_loss,
    reprojection_residuals,
)
from torchmocap.cameras.reprojection import interpolation_weights


def _trajectory(T=8, K=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(T, K, 3, generator=g, dtype=torch.float64) * 0.4 + torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64)


def _detections(rig, X, offsets=None):
    r = reprojection_residuals(X, torch.zeros(X.shape[0], rig.num_cameras, X.shape[1], 3,
                                              dtype=X.dtype), rig.K, rig.R, rig.t, rig.dist,
                               offsets)
    return torch.cat([r, torch.ones_like(r[..., :1])], -1)  # exact detections


class TestInterpolateInTime:
    def test_smoke(self):
        X = _trajectory()
        out = interpolate_in_time(X, torch.tensor([[0.5, 2.0], [3.25, 6.9]]))
        assert out.shape == (2, 2, 3, 3) and out.dtype == torch.float64

    def test_feature_whole_frames_are_exact(self):
        X = _trajectory()
        torch.testing.assert_close(interpolate_in_time(X, torch.arange(8.0)), X, atol=0,
                                   rtol=0)

    def test_feature_polynomials(self):
        """Quadratics are reproduced inside the trajectory (Catmull–Rom's exact tangents),
        lines everywhere, past the ends too (linear extrapolation)."""
        f = torch.arange(10, dtype=torch.float64)
        coef = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
        quad = (0.5 + 0.1 * f[:, None] - 0.02 * f[:, None] ** 2) * coef  # (T, 3)
        s = torch.linspace(1.0, 8.0, 29, dtype=torch.float64)
        want = (0.5 + 0.1 * s[:, None] - 0.02 * s[:, None] ** 2) * coef
        torch.testing.assert_close(interpolate_in_time(quad[:, None], s)[:, 0], want,
                                   atol=1e-12, rtol=0)
        line = (0.2 + 0.3 * f[:, None]) * coef
        s = torch.linspace(-2.5, 11.5, 57, dtype=torch.float64)
        torch.testing.assert_close(interpolate_in_time(line[:, None], s)[:, 0],
                                   (0.2 + 0.3 * s[:, None]) * coef, atol=1e-12, rtol=0)

    def test_feature_c1_in_time(self):
        """The derivative in time is continuous across whole frames (no kink at offset 0)."""
        X = _trajectory(T=10)
        for t in (0.0, 3.0, 9.0):
            eps = 1e-7
            times = torch.tensor([t - eps, t + eps], dtype=torch.float64)
            _, _, dw = interpolation_weights(times, 10)
            frames, _, _ = interpolation_weights(times, 10)
            vel = (X[frames] * dw[..., None, None]).sum(-3)
            torch.testing.assert_close(vel[0], vel[1], atol=1e-5, rtol=0)

    def test_exception(self):
        with pytest.raises(RefinementError, match="at least 4 frames"):
            interpolate_in_time(_trajectory(T=3), torch.tensor([1.0]))
        with pytest.raises(RefinementError, match="points: expected shape"):
            interpolate_in_time(torch.zeros(5, 3), torch.tensor([1.0]))

    def test_gradcheck(self):
        X = _trajectory(T=6, K=2).requires_grad_()
        s = torch.tensor([0.3, 1.7, 4.4, -0.6, 5.2], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(interpolate_in_time, (X, s), eps=1e-6, atol=1e-6)


class TestRobustLoss:
    @pytest.mark.parametrize("kind", ["cauchy", "huber", "squared"])
    def test_feature_weight_is_the_derivative(self, kind):
        loss = RobustLoss(kind=kind, scale_px=5.0)
        s = torch.tensor([0.01, 4.0, 24.9, 25.1, 100.0, 1e4], dtype=torch.float64,
                         requires_grad=True)
        (grad,) = torch.autograd.grad(loss.rho(s).sum(), s)
        torch.testing.assert_close(grad, loss.weight(s.detach()))
        small = torch.tensor([1e-4], dtype=torch.float64)
        torch.testing.assert_close(loss.rho(small), small, rtol=1e-5, atol=0)
        if kind != "squared":
            assert float(loss.weight(torch.tensor(1e4))) < 0.1  # outliers count less

    def test_feature_detection_weights(self):
        conf = torch.tensor([0.0, 0.2, 0.3, 0.31, 0.9])
        assert RobustLoss().detection_weights(conf).tolist() == pytest.approx(
            [0, 0, 0, 0.31, 0.9])
        w = RobustLoss(confidence_weighted=False, min_confidence=0.0).detection_weights(conf)
        assert w.tolist() == [0, 1, 1, 1, 1]

    def test_exception(self):
        for kw, match in ((dict(kind="tukey"), "loss.kind"), (dict(scale_px=0.0), "scale_px"),
                          (dict(scale_px=float("nan")), "scale_px"),
                          (dict(min_confidence=1.0), "min_confidence"),
                          (dict(confidence_weighted=1), "confidence_weighted")):
            with pytest.raises(RefinementError, match=match):
                RobustLoss(**kw)
        with pytest.raises(RefinementError, match="unknown setting"):
            RobustLoss.from_dict({"scale": 3.0})
        assert RobustLoss.from_dict({"scale_px": 3.0}).scale_px == 3.0
        assert RobustLoss.from_dict(None) == RobustLoss()


class TestReprojection:
    def test_smoke(self):
        rig = make_ring_rig(3).double()
        X = _trajectory()
        det = _detections(rig, X)
        r = reprojection_residuals(X, det, rig.K, rig.R, rig.t, rig.dist)
        assert r.shape == (8, 3, 3, 2) and float(r.abs().max()) < 1e-9
        assert float(reprojection_loss(X, det, rig.K, rig.R, rig.t, rig.dist)) < 1e-15

    def test_feature_time_offsets_and_callable(self):
        """A camera with offset d sees the trajectory at t + d; a callable of the cameras'
        times gives the same residuals as the interpolated tensor."""
        rig = make_ring_rig(3).double()
        X = _trajectory()
        off = torch.tensor([0.0, 0.4, -1.3], dtype=torch.float64)
        det = _detections(rig, X, off)
        r = reprojection_residuals(X, det, rig.K, rig.R, rig.t, rig.dist, off)
        assert float(r.abs().max()) < 1e-9
        # without the offsets the cameras disagree
        assert float(reprojection_residuals(X, det, rig.K, rig.R, rig.t, rig.dist).abs()
                      .max()) > 1.0
        seen = []

        def points(times):
            seen.append(times)
            return interpolate_in_time(X, times)

        r2 = reprojection_residuals(points, det, rig.K, rig.R, rig.t, rig.dist, off)
        torch.testing.assert_close(r2, r)
        assert seen[0].shape == (3, 8)
        torch.testing.assert_close(seen[0][:, 2], 2 + off)

    def test_feature_missed_detections_are_out(self):
        rig = make_ring_rig(3).double()
        X = _trajectory()
        det = _detections(rig, X)
        det[0, 1, 2] = torch.tensor([float("nan"), 5.0, 0.0], dtype=torch.float64)  # missed
        det[1, 0, 0, :2] += 30.0
        loss = RobustLoss(kind="squared", min_confidence=0.0)
        val = reprojection_loss(X, det, rig.K, rig.R, rig.t, rig.dist, loss=loss, noise_px=2.0)
        assert float(val) == pytest.approx(0.5 * 1800 / 4)
        det[1, 0, 0, 2] = 0.0
        assert float(reprojection_loss(X, det, rig.K, rig.R, rig.t, rig.dist, loss=loss)) \
            < 1e-12

    def test_exception(self):
        rig = make_ring_rig(3).double()
        X = _trajectory()
        det = _detections(rig, X)
        with pytest.raises(RefinementError, match="detections: expected shape"):
            reprojection_residuals(X, det[:, :2], rig.K, rig.R, rig.t, rig.dist)
        with pytest.raises(RefinementError, match="points: expected shape"):
            reprojection_residuals(X[:, :2], det, rig.K, rig.R, rig.t, rig.dist)
        with pytest.raises(RefinementError, match="points: the callable must return"):
            reprojection_residuals(lambda times: X, det, rig.K, rig.R, rig.t, rig.dist)

    def test_gradcheck(self):
        """The loss is differentiable in the rig's values (every group, time offsets
        included) and in the points."""
        rig = make_ring_rig(3, image_size=(640, 480)).double()
        par = RigParametrization(rig, ("rotation", "translation", "focal_xy", "principal_point",
                                       "distortion", "time_offset"), gauge="none",
                                 time_gauge="none")
        X = _trajectory(T=6, K=2)
        g = torch.Generator().manual_seed(0)
        det = _detections(rig, X, torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64))
        det[..., :2] += torch.randn(det[..., :2].shape, generator=g, dtype=torch.float64)
        y = (0.3 * torch.randn(par.num_parameters, generator=g, dtype=torch.float64)
             ).requires_grad_()
        Xg = X.clone().requires_grad_()

        def loss(y, Xg):
            v = par.values(y)
            K, R, t, d = par.camera_tensors(v)
            return reprojection_loss(Xg, det, K, R, t, d, v[:, 12], RobustLoss(scale_px=3.0))

        assert torch.autograd.gradcheck(loss, (y, Xg), eps=1e-6, atol=1e-5)


class TestRigRefinement:
    def test_module(self):
        """The module's loss is the functions' (reprojection + prior) of its values."""
        rig = make_ring_rig(3).double()
        m = RigRefinement(rig, groups=("rotation", "translation", "focal", "time_offset"),
                          priors=RigPriors(rotation_deg=1.0), noise_px=2.0)
        with torch.no_grad():
            m.y.copy_(torch.linspace(-3, 3, m.y.numel(), dtype=torch.float64))
        X = _trajectory()
        det = _detections(rig, X)
        v = m.values()
        K, R, t, d = m.parametrization.camera_tensors(v)
        want = reprojection_loss(X, det, K, R, t, d, v[:, 12], noise_px=2.0) + prior_loss(
            m.parametrization.free_values(v), m.priors.widths(m.parametrization))
        torch.testing.assert_close(m(X, det), want)
        assert m.rig().num_cameras == 3 and m.time_offsets().shape == (3,)
        # float32 points (a float32 model's keypoints): the loss is promoted, the gradient
        # reaches them in their dtype
        X32 = X.float().requires_grad_()
        m(X32, det).backward()
        assert X32.grad.dtype == torch.float32 and bool(torch.isfinite(X32.grad).all())
        m32 = RigRefinement(rig.float(), groups=("rotation",)).float()
        assert m32(X.float(), det.float()).dtype == torch.float32

    def test_feature_gradient_descent_refines(self):
        """Adam on the module's parameters brings a rotated camera back (gradient-based use
        inside another objective)."""
        rig = make_ring_rig(3).double()
        X = _trajectory(T=4, K=12)
        det = _detections(rig, X)
        bad = RigRefinement(rig, groups=("rotation",), gauge="none")
        with torch.no_grad():
            bad.y.copy_(torch.tensor([20.0, -10.0, 5.0, 0, 0, 0, 0, 0, 0],
                                     dtype=torch.float64))  # mrad
        opt = torch.optim.Adam(bad.parameters(), lr=1.0)
        first = float(bad(X, det).detach())
        for _ in range(200):
            opt.zero_grad()
            loss = bad(X, det)
            loss.backward()
            opt.step()
        assert float(loss.detach()) < 1e-3 * first
        assert float(bad.y.detach().norm()) < 0.2 * 23.0  # mrad, from 23

    def test_exception(self):
        with pytest.raises(RefinementError, match="noise_px"):
            RigRefinement(make_ring_rig(2), noise_px=0.0)
        with pytest.raises(RefinementError, match="priors.rotation_deg"):
            RigRefinement(make_ring_rig(2), priors={"rotation_deg": -1.0})
