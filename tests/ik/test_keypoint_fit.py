"""Fitting the subject to triangulated keypoints: exact on noiseless keypoints of a differently
proportioned, kneeling, turned-around subject; bone lengths within a stated tolerance under
1 cm noise and missing keypoints; robust to a wrongly triangulated keypoint; several starts
beat one on a subject facing the other way; and on the real pose2sim_balancing detections an
adult's height and a reprojection error of the order of the triangulation's own."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torchmocap.cameras import triangulate_dlt
from torchmocap.ik import SEATED, fit_keypoint_subject
from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map

F64 = torch.float64


def _subject():
    """human31 scaled by 0.92 with 6 % longer thighs and 7 % shorter forearms, and the
    BODY_25B map with offsets scaled by 0.92."""
    sk = human31().double().with_bone_lengths(scale=0.92)
    L = sk.bone_lengths()
    sk = sk.with_bone_lengths({"l_knee": 1.06 * L["l_knee"], "r_knee": 1.06 * L["r_knee"],
                               "l_wrist": 0.93 * L["l_wrist"], "r_wrist": 0.93 * L["r_wrist"]})
    kmap = load_keypoint_map("body_25b", sk)
    return sk, dataclasses.replace(kmap, offsets=kmap.offsets * 0.92)


def _kneeling(sk, T, seed):
    """T poses around a kneeling lunge, trunk bent forward, arms raised, facing +y (turned
    around from the template)."""
    g = torch.Generator().manual_seed(seed)
    th = sk.zero_pose((T,), dtype=F64)
    for dof, v in {"pelvis_rz": math.pi, "spine_flex": 0.5, "l_hip_flex": 1.4,
                   "l_knee_flex": 1.6, "r_hip_flex": 0.2, "r_knee_flex": 1.9,
                   "l_shoulder_flex": 1.2, "r_shoulder_abd": 0.8, "l_elbow_flex": 0.9}.items():
        th[:, sk.dof_index(dof)] = v
    th[:, :3] = torch.tensor([0.3, -0.2, -0.35], dtype=F64)
    th[:, 3:] += 0.1 * torch.randn(T, sk.num_dofs - 3, generator=g, dtype=F64)
    return sk.clamp(th)


def _keypoints(sk, kmap, th, noise=0.0, missing=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    kin = sk(th)
    x = keypoint_positions(kin.positions, kin.rotations, kmap)
    x = x + noise * torch.randn(x.shape, generator=g, dtype=F64)
    x[torch.rand(x.shape[:2], generator=g, dtype=F64) < missing] = float("nan")
    return x


class TestFitKeypointSubject:
    def test_feature_exact_without_noise(self):
        sk, kmap = _subject()
        th = _kneeling(sk, 3, seed=0)
        fit = fit_keypoint_subject(_keypoints(sk, kmap, th), None, "body_25b")
        assert fit.theta.shape == (3, 31) and fit.residual.shape == (3, 25)
        assert float(fit.residual.max()) < 1e-4  # m
        true = sk.bone_lengths()
        err = {k: abs(v - true[k]) for k, v in fit.lengths.items()}
        assert max(err.values()) < 1e-3, err  # the weak pull to the template: 0.2 mm
        assert fit.scale == pytest.approx(0.92, abs=0.01)
        # the fitted skeleton's keypoints at the fitted poses are the data
        kin = fit.skeleton(fit.theta)
        x = keypoint_positions(kin.positions, kin.rotations, fit.keypoint_map)
        torch.testing.assert_close(x, _keypoints(sk, kmap, th), atol=1e-4, rtol=0)

    def test_feature_noise_and_missing_keypoints(self):
        """1 cm noise per coordinate, 10 % missing keypoints, 8 frames: every observed bone
        within 2 cm (measured: within 1.04 cm over six seeds) and the median residual at the
        noise level."""
        sk, kmap = _subject()
        th = _kneeling(sk, 8, seed=1)
        pts = _keypoints(sk, kmap, th, noise=0.01, missing=0.1, seed=1)
        fit = fit_keypoint_subject(pts, None, kmap)
        true = sk.bone_lengths()
        err = {k: abs(v - true[k]) for k, v in fit.lengths.items()
               if k not in ("l_hand", "r_hand", "spine")}  # no keypoint observes these
        assert max(err.values()) < 0.02, err
        assert float(fit.residual.nanmedian()) < 0.015
        assert bool(torch.isnan(fit.residual).any())  # missing points have no residual
        # held offset components keep the scaled template's (TRUNK_HOLD: the shoulders'
        # height), free ones moved
        off = fit.skeleton.offsets.double()
        assert float(off[sk.joint_index("l_shoulder"), 2]) == pytest.approx(0.36 * fit.scale,
                                                                            rel=1e-6)
        assert float(off[sk.joint_index("l_shoulder"), 0]) != pytest.approx(0.18 * fit.scale,
                                                                            rel=1e-4)

    def test_feature_robust_to_a_wrong_keypoint(self):
        """A keypoint triangulated 1 m off in half the frames barely moves the fit."""
        sk, kmap = _subject()
        th = _kneeling(sk, 6, seed=2)
        pts = _keypoints(sk, kmap, th, noise=0.005, seed=2)
        bad = pts.clone()
        nose = kmap.names.index("Nose")
        bad[::2, nose] += torch.tensor([0.6, -0.5, 0.6], dtype=F64)
        fit = fit_keypoint_subject(bad, None, kmap)
        true = sk.bone_lengths()
        err = {k: abs(v - true[k]) for k, v in fit.lengths.items()
               if k not in ("l_hand", "r_hand", "spine")}
        assert max(err.values()) < 0.015, err
        others = torch.ones(25, dtype=torch.bool)
        others[nose] = False
        assert float(fit.residual[:, others].max()) < 0.03
        assert float(fit.residual[::2, nose].min()) > 0.8  # the wrong points stay unexplained

    def test_feature_several_starts_beat_one(self):
        """A subject standing with its back to the template's facing direction: one start
        (standing, facing -y) ends in a wrong minimum; the starts over headings find it."""
        sk = human31().double()
        kmap = load_keypoint_map("body_25b", sk)
        th = sk.zero_pose((1,), dtype=F64)
        th[0, sk.dof_index("pelvis_rz")] = math.pi
        pts = _keypoints(sk, kmap, th)
        one = fit_keypoint_subject(pts, None, kmap, headings=1, postures=({},),
                                   refine_iterations=0)
        many = fit_keypoint_subject(pts, None, kmap, refine_iterations=0)
        assert many.info["starts"] == 16 and one.info["starts"] == 1
        assert float(one.residual.median()) > 0.05  # measured 0.15 m
        assert float(many.residual.max()) < 1e-4
        assert float(many.cost[0]) < float(one.cost[0])

    def test_cardinality(self):
        """Columns by name (any order), weights per point, frames of any count; postures and
        headings multiply the starts."""
        sk = human31().double()
        kmap = load_keypoint_map("body_25b", sk)
        th = _kneeling(sk, 2, seed=3)
        pts = _keypoints(sk, kmap, th)
        names = list(kmap.format_keypoints)
        perm = torch.arange(24, -1, -1)
        w = torch.ones(2, 25, dtype=F64)
        w[0, 3] = 0.0
        fit = fit_keypoint_subject(pts[:, perm], w[:, perm], kmap,
                                   keypoint_names=[names[i] for i in perm], headings=3,
                                   postures=({}, SEATED, {"l_knee_flex": 45.0}))
        assert fit.info["starts"] == 9 and fit.info["start_index"].shape == (2,)
        seen = torch.isfinite(fit.residual)
        assert not bool(seen[0, 3]) and int(seen.sum()) == 49
        assert float(fit.residual[seen].max()) < 1e-3

    def test_exception(self):
        sk, kmap = _subject()
        pts = _keypoints(sk, kmap, _kneeling(sk, 2, seed=4))
        with pytest.raises(ValueError, match=r"points: expected shape \(T0, K, 3\)"):
            fit_keypoint_subject(pts[0])
        with pytest.raises(ValueError, match=r"weights: expected shape \(2, 25\)"):
            fit_keypoint_subject(pts, torch.ones(2, 24))
        with pytest.raises(ValueError, match="weights: expected finite values >= 0"):
            fit_keypoint_subject(pts, -torch.ones(2, 25))
        with pytest.raises(ValueError, match="keypoint_names: 3 names for 25"):
            fit_keypoint_subject(pts, keypoint_names=["a", "b", "c"])
        few = pts.clone()
        few[1, 3:] = float("nan")
        with pytest.raises(ValueError, match=r"frames \[1\] have fewer than 4"):
            fit_keypoint_subject(few)
        with pytest.raises(ValueError, match="unknown DoF 'l_knee_bend'"):
            fit_keypoint_subject(pts, postures=({"l_knee_bend": 10.0},))
        for kw in (dict(headings=0), dict(refine_iterations=-1), dict(iterations=True),
                   dict(robust_scale=0.0), dict(length_prior=float("nan")),
                   dict(hold={"l_shouldr": "z"}), dict(hold={"l_shoulder": "w"})):
            with pytest.raises(ValueError, match=next(iter(kw))):
                fit_keypoint_subject(pts, **kw)


@pytest.fixture(scope="module")
def pose2sim(pose2sim_calibrated_rig, pose2sim_detections):
    """The four calibrated views of pose2sim_balancing and the associated BODY_25B detections
    of its first 10 frames, ``(T, C, 25, 3)``."""
    return pose2sim_calibrated_rig, pose2sim_detections


def test_real_recording(pose2sim):
    """The associated detections of 10 frames, triangulated by plain DLT (the nose is wrongly
    triangulated in 5 of them) and fitted: an adult's height, and the fitted keypoints
    reproject into the four views with a median error within 15 % of the triangulation's own
    (measured: 14.2 px vs 13.5 px on 1920-pixel-high images, detections above 0.3)."""
    rig, det = pose2sim
    conf = det[..., 2]
    X = triangulate_dlt(det[..., :2], conf, rig)
    fit = fit_keypoint_subject(X, conf.mean(1), "body_25b")
    # standing straight (zero pose): the head top's height above the lowest keypoint (heels)
    sk = fit.skeleton
    kin0 = sk(sk.zero_pose((), dtype=F64))
    feet = keypoint_positions(kin0.positions, kin0.rotations, fit.keypoint_map)[:, 2].min()
    stature = float(kin0.positions[sk.joint_index("head_top"), 2] - feet)
    assert 1.55 < stature < 1.95, stature  # measured 1.74 m
    ok = conf > 0.3
    kin = fit.skeleton(fit.theta)
    x = keypoint_positions(kin.positions, kin.rotations, fit.keypoint_map)
    e_fit = (rig.project(x)[0] - det[..., :2]).norm(dim=-1)[ok]
    e_tri = (rig.project(X)[0] - det[..., :2]).norm(dim=-1)[ok]
    med_fit, med_tri = float(e_fit.median()), float(e_tri.median())
    assert 5.0 < med_tri < 20.0
    assert med_fit < 1.15 * med_tri, (med_fit, med_tri)
    # limb lengths of an adult (m)
    for bone, (lo, hi) in {"l_knee": (0.33, 0.5), "l_ankle": (0.33, 0.5),
                           "l_elbow": (0.22, 0.36), "l_wrist": (0.2, 0.32)}.items():
        assert lo < fit.lengths[bone] < hi, (bone, fit.lengths[bone])
