"""Choosing the subject among several detected people: the real raw detections of
pose2sim_balancing (a bystander in cam01/cam02) against Pose2Sim's own association, and
synthetic scenes with a bystander, a split body and two consistent people."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.cameras import make_ring_rig, read_toml_calibration
from torchmocap.data.recordings.person_selection import person_agreement, select_person
from torchmocap.io.frames import numbered_files
from torchmocap.io.openpose import read_openpose_json

F64 = torch.float64
CAMS = ["cam01", "cam02", "cam03", "cam04"]


@pytest.fixture(scope="module")
def recording(shared_data):
    root = shared_data / "multiview" / "pose2sim_balancing"
    rig = read_toml_calibration(root / "calibration" / "Calib.toml")

    def people(folder: str) -> list[list[torch.Tensor]]:
        files = {c: numbered_files(root / folder / f"{c}_json", (".json",)) for c in CAMS}
        return [[read_openpose_json(files[c][t], 25) for c in CAMS] for t in range(10)]

    return rig, people("pose"), people("pose-associated")


def _body(centre, K: int = 17, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(K, 3, generator=g, dtype=F64) * torch.tensor([0.4, 0.3, 1.7], dtype=F64)
    return pts + torch.tensor(centre, dtype=F64) - torch.tensor([0.2, 0.15, 0.0], dtype=F64)


def _detect(rig, X: torch.Tensor, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """``(C, K, 3)`` detections of world points (confidence 0.8)."""
    g = torch.Generator().manual_seed(seed)
    pix = rig.project(X)[0] + noise * torch.randn(rig.num_cameras, X.shape[0], 2,
                                                   generator=g, dtype=F64)
    return torch.cat([pix, torch.full((*pix.shape[:2], 1), 0.8, dtype=F64)], -1)


class TestRealRecording:
    def test_feature_matches_the_associated_files(self, recording):
        rig, raw, assoc = recording
        joints, report = select_person(raw, rig)
        assert joints.shape == (10, 4, 25, 3)
        for t in range(10):
            for c in range(4):
                assert torch.equal(joints[t, c], assoc[t][c][0]), (t, CAMS[c])
        views = report["views"]
        for name, n in zip(rig.names, (2, 2, 1, 1)):
            assert views[name]["people"] == [n] * 10
            assert views[name]["frames_with_several_people"] == (list(range(10)) if n > 1
                                                                 else [])
            assert views[name]["rejected_frames"] == [] and views[name]["merged"] == []
            # the subject's triangulation reprojects within ~8-19 px per view (OpenPose noise
            # and calibration on 1920-pixel-high images); the bystander would be > 300 px off
            assert all(5 < a < 25 for a in views[name]["agreement_px"]), views[name]
        assert report["max_error_px"] == pytest.approx(0.03 * math.hypot(1088, 1920))

    def test_feature_bystander_alone_is_rejected(self, recording):
        """A view that sees only the bystander gets no detection, not the bystander."""
        rig, raw, _ = recording
        by = [[x.clone() for x in frame] for frame in raw]
        subject_in_cam01 = select_person(raw[:1], rig)[1]["views"]["cam_01"]["chosen"][0]
        by[0][0] = by[0][0][[1 - subject_in_cam01]]  # cam01, frame 0: the bystander only
        joints, report = select_person(by, rig)
        assert report["views"]["cam_01"]["rejected_frames"] == [0]
        assert report["views"]["cam_01"]["chosen"][0] == -1
        assert bool((joints[0, 0] == 0).all()) and bool((joints[1:, 0, :, 2] > 0).any())


class TestSynthetic:
    def test_feature_bystander_in_two_views(self):
        rig = make_ring_rig(4, image_size=(640, 480))
        subject, bystander = _body([0.0, 0.0, 0.0]), _body([1.2, 0.9, 0.0], seed=1)
        frames, truth = [], []
        for t in range(6):
            shift = torch.tensor([0.02 * t, 0.0, 0.0], dtype=F64)
            s, b = _detect(rig, subject + shift, 1.0, t), _detect(rig, bystander, 1.0, 10 + t)
            views = []
            for c in range(4):
                if c < 2:  # views 0 and 1 see both, in an order that changes with t
                    views.append(torch.stack([b[c], s[c]] if (t + c) % 2 else [s[c], b[c]]))
                else:
                    views.append(s[c][None])
            frames.append(views)
            truth.append(s)
        joints, report = select_person(frames, rig)
        for t in range(6):
            torch.testing.assert_close(joints[t], truth[t], atol=0, rtol=0)
        assert report["views"]["ring0"]["chosen"] == [0, 1, 0, 1, 0, 1]
        assert all(a < 3 for a in report["views"]["ring2"]["agreement_px"])

    def test_feature_split_body_is_merged(self):
        rig = make_ring_rig(4, image_size=(640, 480))
        s = _detect(rig, _body([0.0, 0.0, 0.0]), 0.5)
        upper, lower = s[0].clone(), s[0].clone()
        upper[:8] = 0
        lower[8:] = 0
        frames = [[torch.stack([lower, upper]), s[1][None], s[2][None], s[3][None]]]
        joints, report = select_person(frames, rig)
        torch.testing.assert_close(joints[0], s, atol=0, rtol=0)
        assert len(report["views"]["ring0"]["merged"]) == 1

    def test_feature_follows_the_first_choice(self):
        """Two people consistent in every view: the first frame's better agreement chooses,
        and continuity keeps that person when the other agrees better later."""
        rig = make_ring_rig(4, image_size=(640, 480))
        a, b = _body([-0.5, 0.0, 0.0]), _body([0.6, 0.3, 0.0], seed=2)
        frames = []
        for t in range(4):
            na, nb = (0.5, 4.0) if t == 0 else (4.0, 0.5)
            da, db = _detect(rig, a, na, t), _detect(rig, b, nb, 20 + t)
            frames.append([torch.stack([db[c], da[c]]) for c in range(4)])
        _, report = select_person(frames, rig)
        assert all(report["views"][n]["chosen"] == [1, 1, 1, 1] for n in rig.names)
        # without the first frame, the better-agreeing b is chosen
        _, later = select_person(frames[1:], rig)
        assert later["views"]["ring0"]["chosen"] == [0, 0, 0]

    def test_feature_min_confidence_and_empty_views(self):
        rig = make_ring_rig(3, image_size=(640, 480))
        s = _detect(rig, _body([0.0, 0.0, 0.0]))
        s[:, :3, 2] = 0.05
        empty = torch.zeros(0, 17, 3, dtype=F64)
        frames = [[s[0][None], s[1][None], s[2][None]], [empty, s[1][None], empty],
                  [empty, empty, empty]]
        joints, report = select_person(frames, rig, min_confidence=0.1)
        assert bool((joints[0, :, :3] == 0).all()) and bool((joints[0, :, 3:, 2] == 0.8).all())
        # one view only: nothing to triangulate, its single person is kept
        assert report["views"]["ring1"]["chosen"] == [0, 0, -1]
        assert report["views"]["ring1"]["agreement_px"][1] is None

    def test_exception(self):
        rig = make_ring_rig(2)
        x = torch.zeros(1, 17, 3, dtype=F64)
        with pytest.raises(ValueError, match=r"people: expected per frame 2 tensors"):
            select_person([[x, x, x]], rig)
        with pytest.raises(ValueError, match=r"people: expected per frame 2 tensors"):
            select_person([[x, torch.zeros(1, 25, 3, dtype=F64)]], rig)


class TestPersonAgreement:
    def test_feature(self):
        rig = make_ring_rig(4, image_size=(640, 480))
        d = _detect(rig, _body([0.0, 0.0, 0.0]))[None]  # exact projections
        err = person_agreement(d, rig)
        assert err.shape == (1, 4) and float(err.max()) < 1e-6
        d[0, 2] = 0  # a view without detections
        err = person_agreement(d, rig)
        assert math.isnan(float(err[0, 2])) and float(err[0, [0, 1, 3]].max()) < 1e-6
