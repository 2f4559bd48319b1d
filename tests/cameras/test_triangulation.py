"""Confidence-weighted DLT triangulation: exact on noiseless projections (with and without lens
distortion), weights drop cameras, fewer than two views give NaN, and on the real
pose2sim_balancing detections the triangulated keypoints reproject within the detector's noise
and agree with Pose2Sim's own triangulation. The robust variant drops the one wrong view of a
point and keeps the views that agree."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmocap.cameras import CameraRig, make_ring_rig
from torchmocap.cameras.triangulation import triangulate_dlt, triangulate_robust


def _points(n=50, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor(
        [1.0, 1.0, 1.6], dtype=dtype) + torch.tensor([0, 0, 1.0], dtype=dtype)


class TestTriangulateDLT:
    def test_feature_exact(self):
        rig = make_ring_rig(4).double()
        X = _points()
        pix = rig.project(X)[0]
        Y = triangulate_dlt(pix, torch.ones(4, X.shape[0], dtype=X.dtype), rig)
        torch.testing.assert_close(Y, X, atol=1e-8, rtol=0)

    def test_feature_distortion(self):
        base = make_ring_rig(3).double()
        dist = torch.tensor([[-0.2, 0.05, 1e-3, -2e-3, 0.0]] * 3, dtype=torch.float64)
        rig = CameraRig(base.K, base.R, base.t, base.image_size, dist)
        X = _points(seed=1)
        pix = rig.project(X)[0]
        Y = triangulate_dlt(pix, torch.ones(3, X.shape[0], dtype=X.dtype), rig)
        torch.testing.assert_close(Y, X, atol=1e-6, rtol=0)
        # ignoring the distortion is wrong by much more
        Z = triangulate_dlt(pix, torch.ones(3, X.shape[0], dtype=X.dtype), rig, undistort=False)
        assert float((Z - X).norm(dim=-1).median()) > 1e-3

    def test_feature_weights_drop_cameras(self):
        rig = make_ring_rig(4).double()
        X = _points(10)
        pix = rig.project(X)[0].clone()
        pix[2] += 80.0  # camera 2's detections are wrong...
        w = torch.ones(4, 10, dtype=X.dtype)
        w[2] = 0.0  # ...and dropped
        torch.testing.assert_close(triangulate_dlt(pix, w, rig), X, atol=1e-8, rtol=0)
        assert float((triangulate_dlt(pix, torch.ones_like(w), rig) - X).norm(dim=-1).min()) > 1e-3

    def test_cardinality(self):
        rig = make_ring_rig(4).double()
        X = _points(6)
        pix = rig.project(X)[0]  # (C, N, 2)
        batch = torch.stack([pix, pix, pix])  # (T, C, N, 2)
        w = torch.ones(3, 4, 6, dtype=X.dtype)
        w[1, 1:, 0] = 0  # frame 1, point 0: one view only
        w[2, :, 3] = 0  # frame 2, point 3: no view
        Y = triangulate_dlt(batch, w, rig)
        assert Y.shape == (3, 6, 3)
        assert bool(torch.isnan(Y[1, 0]).all()) and bool(torch.isnan(Y[2, 3]).all())
        ok = torch.isfinite(Y).all(-1)
        assert int(ok.sum()) == 16
        torch.testing.assert_close(Y[ok], X.expand(3, 6, 3)[ok], atol=1e-8, rtol=0)
        # a NaN pixel counts as not seen
        pix2 = pix.clone()
        pix2[0, 0] = float("nan")
        torch.testing.assert_close(triangulate_dlt(pix2, torch.ones(4, 6, dtype=X.dtype), rig),
                                   X, atol=1e-8, rtol=0)

    def test_exception(self):
        rig = make_ring_rig(4).double()
        pix = torch.zeros(3, 5, 2, dtype=torch.float64)
        with pytest.raises(ValueError, match="pixels"):
            triangulate_dlt(pix, torch.ones(3, 5), rig)
        pix = torch.zeros(4, 5, 2, dtype=torch.float64)
        with pytest.raises(ValueError, match="weights"):
            triangulate_dlt(pix, torch.ones(4, 4), rig)
        with pytest.raises(ValueError, match="weights"):
            triangulate_dlt(pix, -torch.ones(4, 5), rig)
        with pytest.raises(ValueError, match="min_views"):
            triangulate_dlt(pix, torch.ones(4, 5), rig, min_views=1)

    def test_real_recording(self, pose2sim_root, pose2sim_calibrated_rig, pose2sim_detections):
        """pose2sim_balancing: the associated BODY_25B detections of frame 0, triangulated from
        the four views, reproject with a median error of ~10 px (OpenPose noise and
        calibration on 1920-pixel images) and lie within a few cm of Pose2Sim's own
        triangulation of the same detections."""
        root, rig, det = pose2sim_root, pose2sim_calibrated_rig, pose2sim_detections[0]
        X = triangulate_dlt(det[..., :2], det[..., 2], rig)
        seen = (det[..., 2] > 0.3).sum(0) >= 3
        assert int(seen.sum()) >= 20
        pix = rig.project(X[seen])[0]
        err = (pix - det[:, seen, :2]).norm(dim=-1)[det[:, seen, 2] > 0.3]
        assert 2.0 < float(err.median()) < 20.0
        # Pose2Sim's TRC (Y up: (x, y, z)_trc = (y, z, x)_world), frame 1 = our frame 0
        trc = (root / "pose2sim_output" / "S00_P00_T01_BalancingTrial_0-100.trc").read_text()
        lines = trc.splitlines()
        names = [n for n in lines[3].split("\t")[2:] if n]
        row = np.array(lines[5].split("\t")[2:2 + 3 * len(names)], dtype=float).reshape(-1, 3)
        world = row[:, [2, 0, 1]]
        body25b = {"RHip": 12, "RKnee": 14, "RAnkle": 16, "LHip": 11, "LKnee": 13,
                   "LAnkle": 15, "RShoulder": 6, "RElbow": 8, "RWrist": 10, "LShoulder": 5,
                   "LElbow": 7, "LWrist": 9}
        d = [float(np.linalg.norm(X[k].numpy() - world[names.index(n)]))
             for n, k in body25b.items()]
        assert np.median(d) < 0.05, d  # measured 2.9 cm (Pose2Sim drops views by error)


class TestTriangulateRobust:
    def test_feature_drops_the_wrong_view(self):
        """One view 40 px off for half the points: those points lose exactly that view and come
        out exact; the others keep every view; a plain DLT is pulled off."""
        rig = make_ring_rig(4, image_size=(640, 480)).double()
        X = _points(20)
        pix = rig.project(X)[0].clone()  # (C, N, 2)
        pix[1, :10] += torch.tensor([40.0, -30.0], dtype=X.dtype)
        w = torch.ones(4, 20, dtype=X.dtype)
        Y, used = triangulate_robust(pix, w, rig, max_error=5.0)
        torch.testing.assert_close(Y, X, atol=1e-6, rtol=0)
        assert bool((used[1, :10] == 0).all()) and int((used == 0).sum()) == 10
        plain = triangulate_dlt(pix, w, rig)
        assert float((plain[:10] - X[:10]).norm(dim=-1).min()) > 5e-3

    def test_feature_noise_within_the_threshold_keeps_every_view(self):
        rig = make_ring_rig(3).double()
        X = _points(30, seed=2)
        g = torch.Generator().manual_seed(0)
        pix = rig.project(X)[0] + torch.randn(3, 30, 2, generator=g, dtype=X.dtype)
        w = torch.ones(3, 30, dtype=X.dtype)
        Y, used = triangulate_robust(pix, w, rig, max_error=10.0)
        assert torch.equal(used, w)
        torch.testing.assert_close(Y, triangulate_dlt(pix, w, rig))

    def test_cardinality(self):
        """Leading dims; a missed view stays missed; a point whose only two views disagree is
        not triangulated (no two views agree), one whose two views agree is."""
        rig = make_ring_rig(4).double()
        X = _points(5)
        pix = rig.project(X)[0]
        pix = torch.stack([pix, pix.clone()])  # (T, C, N, 2)
        pix[1, 0, 2] += 50.0
        w = torch.ones(2, 4, 5, dtype=X.dtype)
        w[:, 2:, 3:] = 0.0  # points 3 and 4: two views only
        pix[:, 1, 4] += torch.tensor([50.0, -50.0], dtype=X.dtype)  # point 4's views disagree
        Y, used = triangulate_robust(pix, w, rig, max_error=3.0, min_views=2)
        assert Y.shape == (2, 5, 3) and used.shape == (2, 4, 5)
        assert used[1, 0, 2] == 0 and int((used[0, :, :3] == 0).sum()) == 0
        assert bool((used[:, :, 4] == 0).all()) and bool(torch.isnan(Y[:, 4]).all())
        assert bool((used[:, :2, 3] == 1).all()) and bool((used[:, 2:, 3:] == 0).all())
        torch.testing.assert_close(Y[:, :4], X[:4].expand(2, 4, 3), atol=1e-6, rtol=0)

    def test_exception(self):
        rig = make_ring_rig(4).double()
        pix = torch.zeros(4, 5, 2, dtype=torch.float64)
        for bad in (0.0, -1.0, float("inf"), True, "5"):
            with pytest.raises(ValueError, match="max_error"):
                triangulate_robust(pix, torch.ones(4, 5), rig, bad)
        with pytest.raises(ValueError, match="weights"):
            triangulate_robust(pix, torch.ones(4, 4), rig, 5.0)
