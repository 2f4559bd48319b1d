"""Bundle adjustment of a rig from the subject's detections (no board): on synthesised scenes
with a known rig it recovers rotations, centres, focal lengths and time offsets (up to the
world's similarity) to stated tolerances over several seeds; its normal equations are those of
the dense Jacobian; its standard deviations match the spread over noise draws; a robust loss
ignores outliers; a rig refined on some frames serves the others; every bad input is a typed
error naming the argument; on the real recording it lowers every camera's residual."""

from __future__ import annotations

import json

import pytest
import torch

from torchmocap.cameras import (
    BundleAdjustmentResult,
    RefinementError,
    RigParametrization,
    RigPriors,
    RobustLoss,
    bundle_adjust,
    make_ring_rig,
)
from torchmocap.cameras.bundle_adjustment import _Problem

from .calibration_scenes import FPS, make_scene, rig_errors

TIME_GROUPS = ("rotation", "translation", "focal", "time_offset")
#: what the synthetic recovery achieves (4 cameras 3.5 m from a walking 1.7 m subject, 1280x960
#: images, 2 px noise, 10 % missed, 60 frames, 25 points; perturbed by 1-3 deg, 2-5 cm, 2-5 %
#: focal and offsets 0 / +0.3 / -0.5 / +1.2 frames), measured over 6 seeds: rotation <= 0.08 deg,
#: centre <= 29 mm (the distance along the optical axis is what focal length trades with),
#: focal <= 1.05 %, offsets <= 0.016 frames
TOL_ROTATION_DEG, TOL_CENTRE_M, TOL_FOCAL, TOL_OFFSET = 0.2, 0.035, 0.015, 0.05


class TestBundleAdjust:
    def test_smoke(self):
        sc = make_scene(0, T=6, K=10, noise_px=0.0)
        res = bundle_adjust(sc.detections, sc.perturbed, noise_px=1.0, priors=RigPriors(
            rotation_deg=None, translation_m=None, focal_percent=None))
        assert isinstance(res, BundleAdjustmentResult) and res.converged
        assert res.points.shape == (6, 10, 3) and res.values.shape == (4, 13)
        assert res.rig.num_cameras == 4 and res.rig.names == sc.rig.names
        assert float(res.residual_px_after.max()) < 1e-5
        assert float(res.residual_px_before.min()) > 1.0
        assert res.cost_final < 1e-6 * res.cost_initial
        assert bool(torch.isnan(res.std[:, 8:]).all()) and bool((res.std[:, :7] > 0).all())
        err = rig_errors(res.rig, sc.rig)
        assert float(err["rotation_deg"].max()) < 1e-5 and float(err["focal"].abs().max()) < 1e-6
        json.dumps(res.report())

    def test_feature_dtype_and_frames(self):
        """A float32 rig comes back float32; a frame range refines those frames only, and the
        rig refined on them serves the other frames."""
        sc = make_scene(1, T=30, K=15)
        res = bundle_adjust(sc.detections.float(), sc.perturbed.float(), frames=(0, 15))
        assert res.rig.K.dtype == torch.float32 and res.frames == range(0, 15)
        assert res.points.shape == (15, 15, 3)
        later = bundle_adjust(sc.detections, res.rig.double(), frames=range(15, 30),
                              groups=("rotation",), max_iterations=1)
        given = bundle_adjust(sc.detections, sc.perturbed, frames=range(15, 30),
                              groups=("rotation",), max_iterations=1)
        # residuals of the DLT of frames 15-29 with the rig refined on 0-14: at the noise
        assert float(later.residual_px_before.max()) < 0.6 * float(
            given.residual_px_before.min())

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_feature_recovers_rig_and_time_offsets(self, seed):
        sc = make_scene(seed, offsets=(0.0, 0.3, -0.5, 1.2))
        res = bundle_adjust(sc.detections, sc.perturbed, TIME_GROUPS, fps=FPS)
        assert res.converged, res.message
        err, before = rig_errors(res.rig, sc.rig), rig_errors(sc.perturbed, sc.rig)
        assert float(err["rotation_deg"].max()) < TOL_ROTATION_DEG, err
        assert float(err["centre_m"].max()) < TOL_CENTRE_M, err
        assert float(err["focal"].abs().max()) < TOL_FOCAL, err
        assert bool((err["rotation_deg"] < 0.25 * before["rotation_deg"]).all())
        # offsets up to the common shift the time gauge removes (their mean is zero)
        want = sc.offsets - sc.offsets.mean()
        assert float((res.time_offsets - want).abs().max()) < TOL_OFFSET, res.time_offsets
        # the errors agree with the reported standard deviations
        assert float((err["focal"] / res.std[:, 6]).abs().max()) < 4.0
        assert float(((res.time_offsets - want) / res.std[:, 12]).abs().max()) < 4.0
        assert 1.5 < res.noise_px < 2.5  # the detections' 2 px, measured
        assert not res.poorly_determined()

    def test_feature_without_time_offsets(self):
        sc = make_scene(3, T=40)
        res = bundle_adjust(sc.detections, sc.perturbed)
        err = rig_errors(res.rig, sc.rig)
        assert float(err["rotation_deg"].max()) < 0.2 and float(err["focal"].abs().max()) < 0.02
        assert float(err["centre_m"].max()) < 0.04
        assert bool(torch.isnan(res.std[:, 12]).all()) and bool((res.time_offsets == 0).all())

    def test_feature_every_group(self):
        """Intrinsics beyond focal length: noise-free detections of a perturbed principal
        point, k1, k2 and fx != fy are explained exactly again; what the subject cannot tell
        apart (on a ring of cameras at one height, a common shift of cy against fy and the
        cameras' tilt) is reported with a standard deviation that covers its error, and
        flagged."""
        sc = make_scene(5, T=10, K=25, noise_px=0.0)
        groups = ("rotation", "translation", "focal_xy", "principal_point", "distortion")
        par = RigParametrization(sc.rig, groups, gauge="none")
        v = torch.zeros(4, 13, dtype=torch.float64)
        v[:, 6], v[:, 7] = 0.02, -0.01
        v[:, 8:10] = torch.tensor([6.0, -4.0], dtype=torch.float64)
        v[:, 10:12] = torch.tensor([0.02, -0.01], dtype=torch.float64)
        start = par.refined_rig(v)
        res = bundle_adjust(sc.detections, start, groups, noise_px=1.0,
                            priors=RigPriors(principal_point_px=None, distortion=None,
                                             focal_percent=None))
        assert res.converged and float(res.residual_px_after.max()) < 1e-3
        assert float(res.residual_px_before.min()) > 3.0
        torch.testing.assert_close(res.rig.dist, sc.rig.dist, atol=1e-4, rtol=0)
        err = res.rig.K[:, :2, 2] - sc.rig.K[:, :2, 2]
        assert bool((err.abs() < 3 * res.std[:, 8:10]).all())
        assert {f"{n}.cy" for n in sc.rig.names} <= set(res.poorly_determined())

    @pytest.mark.parametrize("temporal", [False, True])
    def test_feature_normal_equations_are_the_dense_jacobians(self, temporal):
        """The Schur blocks (per point, or per keypoint trajectory with time offsets and the
        acceleration prior) equal those of the dense Jacobian of the residuals."""
        sc = make_scene(6, T=6, K=3, offsets=(0.0, 0.2, -0.3, 0.4))
        groups = TIME_GROUPS if temporal else ("rotation", "translation", "focal")
        par = RigParametrization(sc.perturbed, groups)
        loss = RobustLoss(scale_px=5.0)
        w = loss.detection_weights(sc.detections[..., 2])
        widths = RigPriors().widths(par)
        prob = _Problem(par, sc.detections[..., :2], w, loss, widths, temporal,
                        smoothing=3.0 if temporal else 0.0)
        g = torch.Generator().manual_seed(0)
        y = 0.5 * torch.randn(par.num_parameters, generator=g, dtype=torch.float64)
        X = sc.trajectory(torch.arange(6.0)) + 0.01 * torch.randn(6, 3, 3, generator=g,
                                                                   dtype=torch.float64)
        r, J_y, J_X, taps = prob.linearise(y, X)
        H_yy, g_y, H_pp, H_py, g_p = prob.normal_equations(y, X, r, J_y, J_X, taps, 2.0)
        Jy, JX = torch.autograd.functional.jacobian(prob.residuals, (y, X))
        n = y.numel()
        Jy, JX = Jy.reshape(-1, n), JX.reshape(Jy.reshape(-1, n).shape[0], -1)
        W = (w * loss.weight((r * r).sum(-1)) / 4.0)[..., None].expand_as(r).reshape(-1)
        B = par.basis
        torch.testing.assert_close(H_yy, Jy.T @ (W[:, None] * Jy) + B.T @ (
            (1 / widths ** 2)[:, None] * B), atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(g_y, Jy.T @ (W * r.reshape(-1)) + B.T @ (
            (B @ y) / widths ** 2), atol=1e-9, rtol=1e-9)
        Hxx, Hxy = JX.T @ (W[:, None] * JX), JX.T @ (W[:, None] * Jy)
        gx = JX.T @ (W * r.reshape(-1))
        if temporal:  # block per keypoint: (k, t, i) order; plus the acceleration prior
            D = torch.zeros(4, 6, dtype=torch.float64)
            for i in range(4):
                D[i, i:i + 3] = torch.tensor([1.0, -2.0, 1.0], dtype=torch.float64)
            prior = torch.kron(3.0 * D.T @ D, torch.eye(3, dtype=torch.float64))
            idx = torch.arange(54).reshape(6, 3, 3).permute(1, 0, 2).reshape(3, 18)
            for k in range(3):
                torch.testing.assert_close(H_pp[k], Hxx[idx[k]][:, idx[k]] + prior, atol=1e-8,
                                           rtol=1e-9)
                torch.testing.assert_close(H_py[k], Hxy[idx[k]], atol=1e-9, rtol=1e-9)
                torch.testing.assert_close(g_p[k], gx[idx[k]] + prior @ X[:, k].reshape(-1),
                                           atol=1e-9, rtol=1e-9)
            for a in range(3):  # no coupling between keypoints
                for b in range(3):
                    if a != b:
                        assert float(Hxx[idx[a]][:, idx[b]].abs().max()) == 0.0
        else:
            blocks = torch.stack([Hxx[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(18)])
            torch.testing.assert_close(H_pp, blocks, atol=1e-8, rtol=1e-9)
            torch.testing.assert_close(H_py, Hxy.reshape(18, 3, n), atol=1e-9, rtol=1e-9)
            torch.testing.assert_close(g_p, gx.reshape(18, 3), atol=1e-9, rtol=1e-9)

    def test_feature_uncertainty_matches_the_spread(self):
        """Refined on many noise draws of one scene, the focal lengths and centres spread as
        the reported standard deviations say (Gauss–Newton at the solution)."""
        sc = make_scene(7, T=15, K=20, noise_px=0.0, missing=0.0)
        clean = sc.detections
        focal, depth, std_f, std_d = [], [], [], []
        axis = sc.rig.R[:, 2].double()
        for k in range(12):
            g = torch.Generator().manual_seed(100 + k)
            det = clean.clone()
            det[..., :2] += 2.0 * torch.randn(det[..., :2].shape, generator=g,
                                              dtype=torch.float64)
            res = bundle_adjust(det, sc.rig, noise_px=2.0, loss=dict(kind="squared"),
                                priors=RigPriors(rotation_deg=None, translation_m=None,
                                                 focal_percent=None))
            focal.append(res.values[:, 6])
            depth.append((res.values[:, 3:6] * axis).sum(-1))
            std_f.append(res.std[:, 6])
            S = [res.covariance[13 * c + 3:13 * c + 6, 13 * c + 3:13 * c + 6] for c in range(4)]
            std_d.append(torch.stack([(a @ s @ a).sqrt() for a, s in zip(axis, S)]))
        for got, said in ((focal, std_f), (depth, std_d)):
            ratio = torch.stack(got).std(0) / torch.stack(said).mean(0)
            assert bool(((ratio > 0.5) & (ratio < 1.6)).all()), ratio

    def test_feature_robust_loss(self):
        """Wrong detections (5 %, 80 px off) barely move a Cauchy refinement; a squared loss
        is pulled off."""
        sc = make_scene(8, T=20, K=20)
        det = sc.detections.clone()
        g = torch.Generator().manual_seed(0)
        wrong = (torch.rand(det.shape[:-1], generator=g) < 0.05) & (det[..., 2] > 0)
        det[..., :2] += wrong[..., None] * torch.tensor([80.0, -60.0], dtype=torch.float64)
        kw = dict(groups=("rotation", "translation", "focal"), priors=RigPriors(
            translation_m=None, rotation_deg=None, focal_percent=None))
        robust = rig_errors(bundle_adjust(det, sc.perturbed, loss=dict(scale_px=10.0),
                                          **kw).rig, sc.rig)
        plain = rig_errors(bundle_adjust(det, sc.perturbed, loss=dict(kind="squared"),
                                         **kw).rig, sc.rig)
        assert float(robust["rotation_deg"].max()) < 0.3
        assert float(plain["rotation_deg"].max()) > 1.5 * float(robust["rotation_deg"].max())

    def test_feature_flags_what_the_prior_held(self):
        sc = make_scene(9, T=10, K=15)
        res = bundle_adjust(sc.detections, sc.perturbed,
                            ("rotation", "translation", "focal", "principal_point"),
                            priors=RigPriors(principal_point_px=0.05))
        flagged = set(res.poorly_determined())
        assert {f"{n}.{v}" for n in sc.rig.names for v in ("cx", "cy")} <= flagged
        assert not any(f.split(".")[1].startswith(("rot", "centre")) for f in flagged)

    def test_feature_real_recording(self, pose2sim_calibrated_rig, pose2sim_detections):
        """The trimmed real recording (10 frames, 4 cameras): every camera's residual falls."""
        res = bundle_adjust(pose2sim_detections, pose2sim_calibrated_rig)
        assert res.converged
        assert bool((res.residual_px_after < 0.8 * res.residual_px_before).all()), (
            res.residual_px_before, res.residual_px_after)
        assert 2.0 < res.noise_px < 15.0
        rep = res.report()
        json.dumps(rep)
        assert [c["name"] for c in rep["cameras"]] == pose2sim_calibrated_rig.names

    def test_exception(self):
        sc = make_scene(0, T=8, K=10)
        det, rig = sc.detections, sc.perturbed
        cases = [
            (dict(rig=rig.subset([0])), "rig: refining cameras from detections needs at least 2"),
            (dict(rig="Calib.toml"), "rig: expected a CameraRig"),
            (dict(detections=det[..., :2]), r"detections: expected shape \(T, 4, K, 3\)"),
            (dict(detections=det[:, :3]), r"detections: expected shape \(T, 4, K, 3\)"),
            (dict(detections=det[0]), r"detections: expected shape"),
            (dict(detections=det.long()), "detections: expected floating-point"),
            (dict(frames=(-1, 5)), "frames: frames -1..4 are not inside the sequence's 8"),
            (dict(frames=(2, 20)), "frames: frames 2..19 are not inside"),
            (dict(frames=(4, 4)), "frames: frames 4..3 are not inside"),
            (dict(frames=range(0, 8, 2)), "frames: expected consecutive frames"),
            (dict(frames="all"), r"frames: expected \(start, stop\)"),
            (dict(groups=("rotation", "zoom")), "groups: unknown parameter group 'zoom'"),
            (dict(groups=("focal", "focal_xy")), "groups: 'focal'"),
            (dict(groups=3), "groups: expected a sequence of group names"),
            (dict(groups=TIME_GROUPS, fps=30.0, max_time_offset=7.0),
             "max_time_offset: a bound of 7 frames is not smaller than the 8 refined frames"),
            (dict(groups=TIME_GROUPS, fps=30.0, priors=dict(time_offset_frames=9.0)),
             "priors.time_offset_frames: a width of 9 frames"),
            (dict(groups=TIME_GROUPS, fps=30.0, frames=(0, 3)),
             "frames: refining time offsets needs at least 4 frames"),
            (dict(groups=TIME_GROUPS), "fps: refining time offsets"),
            (dict(groups=TIME_GROUPS, fps=0.0), "fps: expected a frame rate"),
            (dict(groups=TIME_GROUPS, fps=30.0, max_time_offset=-1.0), "max_time_offset"),
            (dict(noise_px=0.0), "noise_px"),
            (dict(max_iterations=0), "max_iterations"),
            (dict(tolerance=2.0), "tolerance"),
            (dict(gauge="first"), "gauge: expected 'mean', 'none' or"),
            (dict(time_gauge=9), "time_gauge"),
            (dict(priors={"roll_deg": 1.0}), r"priors: unknown setting\(s\) \['roll_deg'\]"),
            (dict(loss={"kind": "l1"}), "loss.kind"),
            (dict(min_detections=10_000), "detections: camera 'ring0' has"),
        ]
        for kw, match in cases:
            args = dict(detections=det, rig=rig) | kw
            with pytest.raises(RefinementError, match=match):
                bundle_adjust(**args)
        bad = det.clone()
        bad[2, 1, 3, 0] = float("nan")
        with pytest.raises(RefinementError, match="detections: contains NaN or inf"):
            bundle_adjust(bad, rig)
        bad = det.clone()
        bad[0, 0, 0, 2] = -0.5
        with pytest.raises(RefinementError, match="detections: confidences must be >= 0"):
            bundle_adjust(bad, rig)
        # too few detections: two frames of three points seen by two cameras
        few = det[:2, :, :3].clone()
        few[:, 2:, :, 2] = 0.0
        with pytest.raises(RefinementError, match="detections: camera 'ring2' has 0 usable"):
            bundle_adjust(few, rig, min_detections=1)
        with pytest.raises(RefinementError, match="residuals, not more than the"):
            bundle_adjust(few[:, :2], rig.subset([0, 1]), min_detections=1)
        # a camera left without detections of points another camera sees
        lonely = det.clone()
        lonely[:, 1:, :, 2] = 0.0
        with pytest.raises(RefinementError, match="usable detections"):
            bundle_adjust(lonely, rig)


def test_make_ring_rig_scene_is_sane():
    """The synthetic scene projects inside the images (the recovery tests' premise)."""
    sc = make_scene(0)
    seen = sc.detections[..., 2] > 0
    uv = sc.detections[..., :2][seen]
    assert float(uv.min()) > 0 and float(uv[:, 0].max()) < 1280 and float(uv[:, 1].max()) < 960
    assert 0.8 < float(seen.float().mean()) < 0.92
    assert make_ring_rig(4).num_cameras == 4
