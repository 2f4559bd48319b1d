"""The ``mediapipe`` keypoint source on the trimmed real recording (pose2sim_balancing: 4 views,
a bystander in cam01/cam02): MediaPipe run on the videos and on image folders, its cache, the
cross-view check (a bystander's detection replaced by a search in the subject's box, mirrored
detections relabelled or dropped), the person masks (``data.masks=detector``), and settings.

The subject's reference is Pose2Sim's association of OpenPose's detections
(``pose-associated/``); the bystander is the other person of ``pose/``. MediaPipe's body
keypoints lie a median 13-15 px from OpenPose's on these frames (docs/detectors.md); the
bystander is 260-440 px away.
"""

from __future__ import annotations

import importlib.util
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchmocap.data.recordings import load_recording
from torchmocap.data.recordings.keypoints import build_keypoint_source, keypoint_settings
from torchmocap.data.recordings.keypoints.mediapipe import (
    MediaPipeKeypoints,
    frame_consensus,
    mirror_permutations,
)
from torchmocap.io.openpose import KEYPOINT_FORMATS, KeypointFormatError, read_openpose_json

MP = KEYPOINT_FORMATS["mediapipe_33"]
OP = KEYPOINT_FORMATS["body_25b"]
CAMS = ("cam01", "cam02", "cam03", "cam04")
SHARED = ("LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
          "LKnee", "RKnee", "LAnkle", "RAnkle")
FRAMES = 3
SCALE = 0.25


def require_mediapipe() -> None:
    if importlib.util.find_spec("mediapipe") is None:
        msg = 'mediapipe is not installed: pip install -e ".[dev]" (Python 3.10-3.12)'
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)


def load(root, cache, **kw):
    kw.setdefault("stop", FRAMES)
    kw.setdefault("scale", SCALE)
    kw.setdefault("subject", {"frames": 2})
    kp = {"source": "mediapipe", "cache": str(cache), "progress": False,
          **kw.pop("keypoints", {})}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*codec's crop")
        return load_recording(root, keypoints=kp, **kw)


def openpose(root, kind: str, cam: str, t: int) -> torch.Tensor:
    return read_openpose_json(root / kind / f"{cam}_json" / f"{cam}.{t:04d}.json", 25)


def distance(kp: torch.Tensor, op: torch.Tensor) -> float:
    """Median pixel distance of MediaPipe's body keypoints ``(33, 3)`` (full-size pixels)
    from an OpenPose person's ``(25, 3)``."""
    d = [(kp[MP.index(n), :2] - op[OP.index(n), :2]).norm() for n in SHARED
         if op[OP.index(n), 2] > 0.1 and kp[MP.index(n), 2] > 0]
    return float(torch.stack(d).median()) if d else float("inf")


def full_size(seq, t: int, c: int) -> torch.Tensor:
    """The sequence's keypoints of frame ``t``, view ``c`` in full-size pixels."""
    j = seq.joints2d[t, c].double().clone()
    s = seq.meta.scale
    j[:, :2] = torch.where(j[:, 2:] > 0, (j[:, :2] + 0.5) / s - 0.5, j[:, :2])
    return j


def bystander(root, cam: str, t: int) -> torch.Tensor | None:
    """The person of ``pose/`` (everyone OpenPose found) that is not the subject."""
    sub = openpose(root, "pose-associated", cam, t)[0]
    people = openpose(root, "pose", cam, t)
    far = [p for p in people if distance_op(p, sub) > 100]
    return far[0] if far else None


def distance_op(a: torch.Tensor, b: torch.Tensor) -> float:
    ok = (a[:, 2] > 0.1) & (b[:, 2] > 0.1)
    return float((a[ok, :2] - b[ok, :2]).norm(dim=-1).median()) if int(ok.sum()) else 0.0


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("keypoint_cache")


@pytest.fixture(scope="module")
def run(pose2sim_root, cache):
    """The trimmed recording's first frames through the source, with detector masks."""
    require_mediapipe()
    return load(pose2sim_root, cache, masks="detector")


class TestSettings:
    def test_smoke(self):
        s = keypoint_settings({"source": "mediapipe"})
        assert s["cache"] == "outputs/keypoint_cache" and s["max_disagreement"] == 0.1
        src = build_keypoint_source("mediapipe", {**s, "margin": 0.4})
        assert isinstance(src, MediaPipeKeypoints) and src.name == "mediapipe"
        assert src.detector.margin == 0.4 and src.detector.segmentation
        assert not src.available(None)  # computed keypoints: never chosen by source=auto

    @pytest.mark.parametrize("key, value, match", [
        ("max_disagreement", 0.0, r"data\.keypoints\.max_disagreement: expected a number in "
                                  r"\(0, 1\]"),
        ("max_disagreement", "x", r"data\.keypoints\.max_disagreement"),
        ("min_visibility", 1.0, r"data\.keypoints\.min_visibility: expected a number in "
                                r"\[0, 1\)"),
        ("min_detection_confidence", 2.0, r"data\.keypoints\.min_detection_confidence: "
                                          r"expected a number in \[0, 1\]"),
        ("margin", -0.1, r"data\.keypoints\.margin: expected a fraction >= 0"),
        ("cache", "", r"data\.keypoints\.cache: expected the folder"),
        ("cache", None, r"data\.keypoints\.cache: expected the folder"),
        ("relabel", "yes", r"data\.keypoints\.relabel: expected true or false"),
        ("progress", 1, r"data\.keypoints\.progress: expected true or false"),
    ])
    def test_exception(self, key, value, match):
        s = keypoint_settings({"source": "mediapipe", key: value})
        with pytest.raises(ValueError, match=match):
            build_keypoint_source("mediapipe", s)

    def test_exception_unknown_setting(self):
        with pytest.raises(ValueError, match=r"unknown setting\(s\) \['folder'\].*'mediapipe'"):
            keypoint_settings({"source": "mediapipe", "folder": "raw"})

    def test_exception_format_and_masks(self, pose2sim_root, tmp_path):
        with pytest.raises(KeypointFormatError, match=r"data\.keypoints\.format: the mediapipe "
                                                      r"source detects 'mediapipe_33'"):
            load(pose2sim_root, tmp_path, keypoints={"format": "body_25b"}, masks="none")
        for kp, what in (({"source": "openpose"}, "'openpose' reads files"),
                         ({"source": "none"}, "no keypoint source is loaded")):
            with pytest.raises(ValueError, match=rf"data\.masks: detector .*{what}"):
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", message=".*codec's crop")
                    load_recording(pose2sim_root, keypoints=kp, masks="detector", stop=2)
        assert not any(tmp_path.iterdir())  # refused before anything was detected


@pytest.mark.slow
class TestSource:
    def test_smoke(self, run, cache):
        seq = run
        assert seq.joints2d.shape == (FRAMES, 4, 33, 3) and seq.joint_names == list(MP)
        assert seq.meta.keypoint_source == "mediapipe"
        assert seq.meta.keypoint_format == "mediapipe_33"
        rep = seq.meta.keypoint_report
        assert rep["cache"] == str(cache) and rep["computed"] == {c: FRAMES for c in CAMS}
        for cam in CAMS:
            entry = Path(rep["entries"][cam]["image"])
            assert entry.parent == cache / "image" and (entry / "manifest.json").is_file()
            view = rep["views"][cam]
            assert view["frames"] == list(range(FRAMES)) and view["box"] == ["image"] * FRAMES
            assert view["frames_dropped"] == [] and all(a is not None and 0 < a < 60
                                                        for a in view["agreement_px"])
            assert Path(seq.meta.path) not in entry.parents  # never the recording's folder

    def test_feature_the_subject_in_every_view(self, run, pose2sim_root):
        """Every kept detection is the man's (near Pose2Sim's association of OpenPose's
        detections), in cam01/cam02 far from the bystander OpenPose also found."""
        for c, cam in enumerate(CAMS):
            for t in range(FRAMES):
                kp = full_size(run, t, c)
                assert distance(kp, openpose(pose2sim_root, "pose-associated", cam, t)[0]) < 35
                other = bystander(pose2sim_root, cam, t)
                if cam in ("cam01", "cam02"):
                    assert other is not None and distance(kp, other) > 200

    def test_feature_cache_hit(self, run, pose2sim_root, cache, monkeypatch):
        """A second load reads every frame from the cache: the detector is never built, and
        keypoints and masks are those of the first load."""
        import torchmocap.detectors.cache as cache_module

        class Refused(cache_module.MediaPipePoseDetector):
            def __init__(self, *a, **k):
                raise AssertionError("the detector was built on a cached load")

        monkeypatch.setattr(cache_module, "MediaPipePoseDetector", Refused)
        again = load(pose2sim_root, cache, masks="detector")
        assert again.meta.keypoint_report["computed"] == {c: 0 for c in CAMS}
        assert torch.equal(again.joints2d, run.joints2d)
        assert torch.equal(again.silhouettes, run.silhouettes)

    def test_feature_image_folders(self, run, pose2sim_root, cache, tmp_path):
        """The same frames as image folders (lossless copies of the decoded frames) give the
        videos' detections."""
        import shutil

        from PIL import Image

        from torchmocap.io.frames import open_frames

        rec = tmp_path / "rec"
        shutil.copytree(pose2sim_root / "calibration", rec / "calibration")
        for cam in ("cam03", "cam04"):
            (rec / "images" / cam).mkdir(parents=True)
            src = open_frames(pose2sim_root / "videos" / f"{cam}.mp4")
            for t, frame in enumerate(src.frames(0, 2)):
                Image.fromarray(frame).save(rec / "images" / cam / f"{t:06d}.png")
        seq = load(rec, cache, stop=2, fps=60.0, masks="none", subject={"frames": 1})
        assert seq.meta.keypoint_report["computed"] == {"cam03": 2, "cam04": 2}
        torch.testing.assert_close(seq.joints2d, run.joints2d[:2, 2:], atol=1e-4, rtol=0)

    def test_feature_one_camera_unchecked(self, run, pose2sim_root, cache):
        """One camera: nothing to check against; its detections are kept and reported
        unchecked (not dropped)."""
        seq = load(pose2sim_root, cache, cameras=["cam03"], masks="detector")
        view = seq.meta.keypoint_report["views"]["cam03"]
        assert view["frames_unchecked"] == list(range(FRAMES)) and view["frames_dropped"] == []
        assert view["agreement_px"] == [None] * FRAMES
        torch.testing.assert_close(seq.joints2d[:, 0], run.joints2d[:, 2])
        assert seq.silhouettes.any((-1, -2)).all()

    def test_feature_heldout_camera(self, run, pose2sim_root, cache):
        """With a camera held out, the tracked views are checked without it (their report),
        and the held-out view's detections and masks come from the check with every view."""
        seq = load(pose2sim_root, cache, masks="detector", heldout_camera="cam02")
        rep = seq.meta.keypoint_report
        assert set(rep["views"]) == {"cam01", "cam03", "cam04"}
        assert set(rep["with_heldout_view"]["views"]) == set(CAMS)
        torch.testing.assert_close(seq.joints2d[:, 1], run.joints2d[:, 1])
        assert torch.equal(seq.silhouettes[:, 1], run.silhouettes[:, 1])
        assert seq.silhouettes[:, [0, 2, 3]].any((-1, -2)).all()


@pytest.mark.slow
class TestBystander:
    def test_feature_bystander_replaced(self, pose2sim_root, tmp_path, monkeypatch):
        """A landmarker that locks on the bystander in cam01 and cam02 (the whole-image search
        made to return her: it runs in her box) is overruled: those views disagree with cam03
        and cam04, are searched again in the box of the others' triangulation, and the
        detections kept are the man's."""
        require_mediapipe()
        import torchmocap.detectors as detectors

        real = detectors.cached_detections
        by_box = {}
        for cam in ("cam01", "cam02"):
            for t in range(2):
                b = bystander(pose2sim_root, cam, t)
                seen = b[b[:, 2] > 0.1, :2]
                by_box[(cam, t)] = (*seen.min(0).values.tolist(), *seen.max(0).values.tolist())

        def patched(source, detector, cache_dir, frames=None, boxes=None, **kw):
            cam = Path(source).stem
            if Path(cache_dir).name == "image" and cam in ("cam01", "cam02"):
                boxes = {t: by_box[(cam, t)] for t in frames}  # her, not the whole image
            return real(source, detector, cache_dir, frames=frames, boxes=boxes, **kw)

        monkeypatch.setattr(detectors, "cached_detections", patched)
        seq = load(pose2sim_root, tmp_path, stop=2, masks="detector")
        rep = seq.meta.keypoint_report
        for c, cam in enumerate(CAMS):
            view = rep["views"][cam]
            want = "triangulation" if cam in ("cam01", "cam02") else "image"
            assert view["box"] == [want, want] and view["frames_dropped"] == []
            for t in range(2):
                kp = full_size(seq, t, c)
                assert distance(kp, openpose(pose2sim_root, "pose-associated", cam, t)[0]) < 35
                if cam in ("cam01", "cam02"):
                    assert distance(kp, bystander(pose2sim_root, cam, t)) > 200
                    # the whole-image search did find the bystander (what was overruled)
                    entry = Path(rep["entries"][cam]["image"])
                    first = read_openpose_json(entry / "keypoints" / f"{t:06d}.json", 33)[0]
                    assert distance(first, bystander(pose2sim_root, cam, t)) < 60
        # the masks are the man's: nothing inside the bystander's box
        for c, cam in ((0, "cam01"), (1, "cam02")):
            u0, v0, u1, v1 = (int(round(x * SCALE)) for x in by_box[(cam, 0)])
            assert not bool(seq.silhouettes[0, c, v0:v1, u0:u1].any())
            assert bool(seq.silhouettes[0, c].any())


@pytest.fixture(scope="module")
def frame(run, pose2sim_calibrated_rig):
    """``(detections (4, 33, 3), rig)``: MediaPipe's kept detections of frame 0 (full-size
    pixels) and the calibration."""
    return torch.stack([full_size(run, 0, c) for c in range(4)]), pose2sim_calibrated_rig


class TestSwaps:
    """The cross-view check on real detections of one frame (MediaPipe's, from the run),
    with one view's labels altered."""

    def test_smoke(self, frame):
        det, rig = frame
        r = frame_consensus(det, rig)
        assert bool(r.agrees.all()) and r.relabelled == [()] * 4
        assert float(r.agreement_px.max()) < 60 and bool((r.limit_px > 40).all())

    @pytest.mark.parametrize("groups", [("arms", "legs", "face"), ("arms",), ("legs",)])
    def test_feature_mirrored_view_relabelled(self, frame, groups):
        det, rig = frame
        perms = mirror_permutations(MP)
        base = frame_consensus(det, rig)
        for c in range(4):
            bad = det.clone()
            for g in groups:
                bad[c] = bad[c][perms[g]]
            r = frame_consensus(bad, rig)
            assert bool(r.agrees.all()), (c, groups)
            assert set(r.relabelled[c]) >= set(groups) - {"face"}, (c, r.relabelled)
            assert all(r.relabelled[o] == () for o in range(4) if o != c)
            kept = bad[c][r.permutation[c]]
            body = [MP.index(n) for n in SHARED]
            torch.testing.assert_close(kept[body], det[c][body])
            assert abs(float(r.agreement_px[c]) - float(base.agreement_px[c])) < 1.0

    def test_feature_mirrored_view_dropped_without_relabelling(self, frame):
        det, rig = frame
        perms = mirror_permutations(MP)
        bad = det.clone()
        bad[2] = bad[2][perms["arms"]][perms["legs"]]
        r = frame_consensus(bad, rig, relabel=False)
        assert r.agrees.tolist() == [True, True, False, True]
        assert float(r.agreement_px[2]) > float(r.limit_px[2])

    def test_feature_someone_else_dropped(self, frame):
        """A view whose detection is another person (the man's moved by 300 px) disagrees;
        the others still agree."""
        det, rig = frame
        bad = det.clone()
        bad[0, :, 0] += 300.0
        r = frame_consensus(bad, rig)
        assert r.agrees.tolist() == [False, True, True, True]

    def test_exception(self, frame):
        det, rig = frame
        with pytest.raises(ValueError, match=r"detections: expected shape \(4, 33, 3\)"):
            frame_consensus(det[:3], rig)
        with pytest.raises(ValueError, match="needs the body keypoints"):
            frame_consensus(det[:, :25], rig, names=OP)

    @pytest.mark.slow
    def test_feature_source_drops_what_it_cannot_fix(self, pose2sim_root, run, cache,
                                                     monkeypatch):
        """cam04's detections all mirrored (whole image and box) with relabelling off: the
        view is dropped in every frame — no keypoints, no mask — and the report says why;
        with relabelling on, the same detections are relabelled and kept."""
        import torchmocap.detectors as detectors

        real = detectors.cached_detections
        perm = mirror_permutations(MP)
        full = perm["arms"][perm["legs"]][perm["face"]]

        class Mirrored:
            def __init__(self, out):
                self._out = out

            def __getattr__(self, name):
                return getattr(self._out, name)

            def keypoints(self, t):
                x = self._out.keypoints(t)
                return x[:, full] if x.shape[0] else x

        def patched(source, *a, **kw):
            out = real(source, *a, **kw)
            return Mirrored(out) if Path(source).stem == "cam04" else out

        monkeypatch.setattr(detectors, "cached_detections", patched)
        seq = load(pose2sim_root, cache, masks="detector", keypoints={"relabel": False})
        view = seq.meta.keypoint_report["views"]["cam04"]
        assert view["frames_dropped"] == list(range(FRAMES))
        assert all(d.startswith("disagrees with the other views") and
                   d.endswith("searched again in the subject's box (triangulation)")
                   for d in view["dropped"])
        assert view["box"] == ["triangulation"] * FRAMES
        assert not bool(seq.joints2d[:, 3, :, 2].any()) and not bool(seq.silhouettes[:, 3].any())
        assert seq.meta.mask_report["empty_frames"]["cam04"] == list(range(FRAMES))
        fixed = load(pose2sim_root, cache, masks="none")
        view = fixed.meta.keypoint_report["views"]["cam04"]
        assert view["frames_dropped"] == [] and view["frames_relabelled"] == list(range(FRAMES))
        assert all({"arms", "legs"} <= set(r) for r in view["relabelled"])
        body = [MP.index(n) for n in SHARED]
        torch.testing.assert_close(fixed.joints2d[:, 3][:, body], run.joints2d[:, 3][:, body])


@pytest.mark.slow
class TestDetectorMasks:
    def test_feature_masks_of_the_kept_detections(self, run, pose2sim_root):
        """The person masks cover the kept detections' body keypoints and leave the bystander
        out; they are the sequence's silhouettes at the working scale."""
        seq = run
        assert seq.meta.mask_source == "detector"
        assert seq.silhouettes.shape == (FRAMES, 4, *seq.images.shape[2:4])
        body = [MP.index(n) for n in SHARED]
        for c, cam in enumerate(CAMS):
            for t in range(FRAMES):
                m = seq.silhouettes[t, c]
                frac = float(m.float().mean())
                assert 0.02 < frac < 0.15, (cam, t, frac)
                uv = seq.joints2d[t, c, body, :2].round().long()
                inside = m[uv[:, 1].clamp(0, m.shape[0] - 1), uv[:, 0].clamp(0, m.shape[1] - 1)]
                assert float(inside.float().mean()) >= 0.75, (cam, t)
                other = bystander(pose2sim_root, cam, t)
                if other is not None:
                    seen = other[other[:, 2] > 0.1, :2] * SCALE
                    u0, v0 = (int(x) for x in seen.min(0).values.tolist())
                    u1, v1 = (int(x) + 1 for x in seen.max(0).values.tolist())
                    assert not bool(m[v0:v1, u0:u1].any()), (cam, t)
        from torchmocap.io.frames import scaled_size

        assert seq.meta.mask_report["source"] == "mediapipe"
        for c, cam in enumerate(CAMS):  # the fraction of each view's own pixels
            w, h = scaled_size(seq.meta.image_sizes[cam], SCALE)
            frac = seq.meta.mask_report["mask_fraction"][cam]
            assert np.isclose(frac * FRAMES * w * h, float(seq.silhouettes[:, c].sum()),
                              rtol=1e-3)
