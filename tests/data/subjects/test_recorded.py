"""The subject and first pose of a recording: fitted to the triangulated keypoints of its first
frames (real pose2sim_balancing detections: an adult's stature, a first pose that reprojects
within the detector's noise, the keypoint map scaled with the body, a wrong view dropped), or a
standing start at the visual hull of the masks; settings checked."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchmocap.data.recordings.loader import load_recording
from torchmocap.data.subjects.recorded import hull_start, keypoint_start, subject_settings
from torchmocap.skeleton import Skeleton, keypoint_positions, load_keypoint_map


@pytest.fixture(scope="module")
def p2s(shared_data):
    """The trimmed recording's keypoints and rig at scale 0.5 (no masks)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        return load_recording(shared_data / "multiview" / "pose2sim_balancing", masks="none",
                              stop=6)


def _reprojection(meta, seq, frame=0):
    """Median pixel error (full-size pixels) of the first pose's keypoints, detections > 0.3."""
    sk = Skeleton.from_dict(meta["subject_skeleton"]).double()
    kmap = load_keypoint_map(meta["keypoint_map"], sk)
    kin = sk(torch.tensor(meta["initial_poses"][0], dtype=torch.float64))
    x = keypoint_positions(kin.positions, kin.rotations, kmap)
    det = seq.joints2d[frame][:, kmap.columns(seq.joint_names)].double()
    ok = det[..., 2] > 0.3
    err = (seq.rig.double().project(x)[0] - det[..., :2]).norm(dim=-1)[ok]
    return float(err.median()) / seq.meta.scale


class TestKeypointStart:
    def test_feature_real_recording(self, p2s):
        """An adult (measured 1.73 m), one first pose reprojecting with a median of 12.5 px
        in 1920-pixel-high images (14.1 px over the six fitted frames; the four-view DLT's
        own residual is ~11 px), and the map's offsets the built-in ones times the body
        scale (0.91)."""
        meta = keypoint_start(p2s.joints2d, p2s.joint_names, "body_25b", p2s.rig, {"frames": 6},
                              p2s.meta.scale)
        fit = meta["subject_fit"]
        assert 1.6 < fit["stature_m"] < 1.9, fit
        assert fit["frames"] == list(range(6)) and fit["views"] == p2s.rig.names
        sk = Skeleton.from_dict(meta["subject_skeleton"])
        theta = torch.tensor(meta["initial_poses"])
        assert theta.shape == (1, sk.num_dofs)
        assert bool((theta >= sk.lower - 1e-6).all()) and bool((theta <= sk.upper + 1e-6).all())
        assert _reprojection(meta, p2s) < 16.0
        assert fit["reprojection_px"] < 16.0 and fit["residual_m"] < 0.03
        base = load_keypoint_map("body_25b")
        fitted = load_keypoint_map(meta["keypoint_map"], sk)
        torch.testing.assert_close(fitted.offsets, base.offsets * meta["skeleton_scale"])
        assert 0.85 < meta["skeleton_scale"] < 1.1

    def test_feature_a_wrong_view_is_dropped(self, p2s):
        """Three keypoints of one view put 80 px (full size) off, as a detector's confusion
        does (right elbow, wrist and knee, seen by three or four views): the robust
        triangulation drops that view from them, and the fitted joints stay within 4 cm of
        where the clean detections put them (measured 2-3 cm); a plain DLT moves them 7-9 cm."""
        def start(joints, max_error):
            meta = keypoint_start(joints, p2s.joint_names, "body_25b", p2s.rig,
                                  {"frames": 3, "max_error_px": max_error}, 0.5)
            sk = Skeleton.from_dict(meta["subject_skeleton"])
            x = sk(torch.tensor(meta["initial_poses"][0])).positions
            return meta, x[[sk.joint_index(n) for n in ("r_elbow", "r_wrist", "r_knee")]]

        clean, x0 = start(p2s.joints2d, 30.0)
        bad = p2s.joints2d.clone()
        parts = [8, 10, 14]  # RElbow, RWrist, RKnee
        bad[:, 2, parts, 0] += 40.0 * (bad[:, 2, parts, 2] > 0)
        robust, x1 = start(bad, 30.0)
        _, x2 = start(bad, 1e6)
        assert robust["subject_fit"]["dropped_views"] >= clean["subject_fit"]["dropped_views"] \
            + 5
        d_robust, d_plain = (x1 - x0).norm(dim=-1), (x2 - x0).norm(dim=-1)
        assert float(d_robust.max()) < 0.04 and float(d_plain.min()) > 0.05, (d_robust, d_plain)

    def test_exception(self, p2s):
        with pytest.raises(ValueError, match="needs at least two views"):
            keypoint_start(p2s.joints2d[:, :1], p2s.joint_names, "body_25b", p2s.rig.subset([0]))
        few = p2s.joints2d.clone()
        few[0, :, 2:] = 0.0
        with pytest.raises(ValueError, match="frame 0 has [0-2] keypoints seen by two views"):
            keypoint_start(few, p2s.joint_names, "body_25b", p2s.rig)
        for kw, match in (({"frames": 0}, "data.subject.frames"),
                          ({"max_error_px": -1}, "data.subject.max_error_px"),
                          ({"keypoint_map": 3}, "data.subject.keypoint_map"),
                          ({"frame": 3}, r"data.subject: unknown setting\(s\) \['frame'\]")):
            with pytest.raises(ValueError, match=match):
                subject_settings(kw)


class TestHullStart:
    def test_feature_bodytrack(self, shared_data):
        """The bodytrack frame: a standing human31 scaled to the hull (1.7-1.8 m), one
        candidate per heading, all at the hull's centre."""
        from torchmocap.data.recordings.bodytrack import load_bodytrack

        rig, _, masks = load_bodytrack(shared_data / "multiview" / "bodytrack_sequenceB_1", 0.5)
        meta = hull_start(rig, masks, headings=4)
        cand = torch.tensor(meta["initial_poses"])
        sk = Skeleton.from_dict(meta["subject_skeleton"])
        assert cand.shape == (4, sk.num_dofs) and rig.K.dtype == torch.float64  # not converted
        torch.testing.assert_close(cand[:, :2], torch.tensor(meta["hull_centre"][:2]).expand(4, 2))
        assert 1.5 < meta["hull_top_m"] < 2.0
        with pytest.raises(ValueError, match="data.headings"):
            hull_start(rig, masks, headings=0)
        with pytest.raises(ValueError, match="visual hull of the masks is empty"):
            hull_start(rig, torch.zeros_like(masks))
