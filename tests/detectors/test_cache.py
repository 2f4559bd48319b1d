"""The detection cache on a real trimmed video: files the project's readers read back, a second
run that never builds the detector, keys by content and settings, boxes per frame, damaged
entries rebuilt, and a crash mid-write that leaves nothing that reads as cached."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from torchmocap.detectors import (
    DetectorInputError,
    MediaPipePoseDetector,
    cached_detections,
    keypoint_box,
    source_digest,
)
from torchmocap.detectors import cache as cache_mod
from torchmocap.io.frames import numbered_files, open_frames, read_mask
from torchmocap.io.openpose import read_openpose_json

from .conftest import require_mediapipe

FRAMES = range(0, 3)


@pytest.fixture(scope="module")
def video(pose2sim_root):
    return pose2sim_root / "videos" / "cam03.mp4"


@pytest.fixture
def no_model(monkeypatch):
    """Building a detector fails: what runs under it reads the cache only."""
    def refuse(self, *args, **kwargs):
        raise AssertionError("the detector was built")

    monkeypatch.setattr(MediaPipePoseDetector, "__init__", refuse)


class TestCachedDetections:
    def test_smoke_round_trip(self, detector, video, tmp_path, capsys):
        """The files are OpenPose JSON and mask PNGs in the recording layout; what they hold is
        what the detector returns for the frames."""
        out = cached_detections(video, detector, tmp_path, frames=FRAMES)
        assert out.computed == (0, 1, 2) and out.rebuilt == () and out.frames == (0, 1, 2)
        assert out.path.parent == tmp_path and out.path.name.startswith("mediapipe_pose-")
        assert "detect cam03.mp4" in capsys.readouterr().err  # the progress bar
        assert sorted(numbered_files(out.keypoints_dir, (".json",))) == [0, 1, 2]
        assert sorted(numbered_files(out.masks_dir, (".png",))) == [0, 1, 2]
        frames = list(open_frames(video).frames(0, 3))
        for t, rgb in zip(FRAMES, frames):
            want = detector(rgb)
            got = read_openpose_json(out.keypoint_file(t))  # the project's reader
            assert got.shape == (1, 33, 3) and torch.equal(got, want.keypoints)
            torch.testing.assert_close(out.mask(t), want.mask, atol=0.5 / 255 + 1e-6, rtol=0)
            assert torch.equal(torch.from_numpy(read_mask(out.mask_file(t), out.size)),
                               out.mask(t) > 0.5)
        manifest = json.loads((out.path / "manifest.json").read_text())
        assert manifest["source"]["sha256"] == source_digest(video)
        assert manifest["detector"] == detector.identity()
        assert manifest["keypoint_format"] == "mediapipe_33"
        assert not list(out.path.rglob("*.tmp*"))

    def test_feature_second_run_reads_the_cache(self, detector, video, tmp_path, monkeypatch):
        first = cached_detections(video, detector, tmp_path, frames=FRAMES, progress=False)
        calls = []
        monkeypatch.setattr(MediaPipePoseDetector, "detect",
                            lambda *a, **k: calls.append(1))
        monkeypatch.setattr(MediaPipePoseDetector, "__init__",
                            lambda *a, **k: calls.append(1))
        # settings alone (here the defaults) key the same entry as the detector built with them
        again = cached_detections(video, {}, tmp_path, frames=FRAMES, progress=False)
        assert again.computed == () and not calls and again.path == first.path
        assert torch.equal(again.keypoints(2), first.keypoints(2))
        # the same content under another name is the same entry
        copy = tmp_path / "renamed.mp4"
        shutil.copy(video, copy)
        assert cached_detections(copy, {}, tmp_path, frames=[1], progress=False).computed == ()

    def test_feature_key_by_settings_and_region(self, detector, video, tmp_path, pose2sim_frames):
        a = cached_detections(video, detector, tmp_path, frames=[0], progress=False)
        b = cached_detections(video, {"min_detection_confidence": 0.4}, tmp_path, frames=[0],
                              progress=False)
        assert a.path != b.path and b.computed == (0,)
        # a box is another region: that frame is recomputed (not damage), others stay cached
        box = keypoint_box(pose2sim_frames["cam03"][1], 0.1)
        c = cached_detections(video, detector, tmp_path, frames=[0], boxes={0: box},
                              progress=False)
        assert c.path == a.path and c.computed == (0,) and c.rebuilt == ()
        assert c.region(0) is not None
        assert cached_detections(video, detector, tmp_path, frames=[0], boxes={0: box},
                                 progress=False).computed == ()

    def test_feature_boxes_from_the_previous_frame(self, detector, video, tmp_path,
                                                   pose2sim_frames):
        """A box function sees the previous frame's keypoints (None at the first frame)."""
        start = keypoint_box(pose2sim_frames["cam03"][1], 0.1)
        seen = []

        def follow(t, prev):
            seen.append((t, None if prev is None else tuple(prev.shape)))
            return start if prev is None else keypoint_box(prev, 0.5)

        out = cached_detections(video, detector, tmp_path, frames=FRAMES, boxes=follow,
                                progress=False)
        assert seen == [(0, None), (1, (1, 33, 3)), (2, (1, 33, 3))]
        assert all(out.region(t) is not None for t in FRAMES)
        seen.clear()
        again = cached_detections(video, detector, tmp_path, frames=FRAMES, boxes=follow,
                                  progress=False)
        assert again.computed == () and len(seen) == 3

    def test_feature_damaged_entries_are_rebuilt(self, detector, video, tmp_path):
        out = cached_detections(video, detector, tmp_path, frames=FRAMES, progress=False)
        good = [read_openpose_json(out.keypoint_file(t)) for t in FRAMES]
        out.keypoint_file(0).write_text('{"version": 1.3, "people": [')  # truncated JSON
        m = out.mask_file(1).read_bytes()
        out.mask_file(1).write_bytes(m[:-20] + bytes(20))  # altered mask
        out.mask_file(2).unlink()  # a mask lost
        with pytest.warns(UserWarning, match=r"3 frame\(s\) \(first: 0\) were damaged"):
            again = cached_detections(video, detector, tmp_path, frames=FRAMES,
                                      progress=False)
        assert again.computed == (0, 1, 2) and again.rebuilt == (0, 1, 2)
        for t in FRAMES:
            assert torch.equal(read_openpose_json(again.keypoint_file(t)), good[t])
        assert cached_detections(video, detector, tmp_path, frames=FRAMES,
                                 progress=False).computed == ()

    def test_feature_crash_leaves_no_cached_frame(self, detector, video, tmp_path,
                                                  monkeypatch):
        """A crash while frame 1 is written (its mask done, its JSON not): frame 0 stays
        cached, frame 1 is not taken from the cache, and no temporary file is left."""
        real = cache_mod.write_openpose_json

        def crash(path, people, extra=None):
            if path.name == "000001.json":
                raise KeyboardInterrupt
            return real(path, people, extra)

        monkeypatch.setattr(cache_mod, "write_openpose_json", crash)
        with pytest.raises(KeyboardInterrupt):
            cached_detections(video, detector, tmp_path, frames=FRAMES, progress=False)
        monkeypatch.undo()
        entry = next(tmp_path.glob("mediapipe_pose-*"))
        assert (entry / "masks" / "000001.png").exists()
        assert not (entry / "keypoints" / "000001.json").exists()
        assert not list(entry.rglob("*.tmp*"))
        with pytest.warns(UserWarning, match=r"1 frame\(s\) \(first: 1\)"):
            out = cached_detections(video, detector, tmp_path, frames=FRAMES, progress=False)
        assert out.computed == (1, 2) and out.rebuilt == (1,)

    def test_exception(self, video, tmp_path, no_model):
        require_mediapipe()
        with pytest.raises(DetectorInputError, match=r"source: .*no such video file"):
            cached_detections(tmp_path / "missing.mp4", {}, tmp_path)
        with pytest.raises(DetectorInputError, match=r"frames: expected frame indices in "
                                                     r"\[0, 10\)"):
            cached_detections(video, {}, tmp_path, frames=[3, 10])
        with pytest.raises(DetectorInputError, match=r"frames: expected increasing"):
            cached_detections(video, {}, tmp_path, frames=[3, 3])
        with pytest.raises(ValueError, match=r"stop: expected an integer in"):
            cached_detections(video, {}, tmp_path, frames=range(0, 11))
        with pytest.raises(DetectorInputError, match=r"boxes: expected None, a mapping"):
            cached_detections(video, {}, tmp_path, frames=[0], boxes=[(0, 0, 5, 5)])
        with pytest.raises(DetectorInputError, match=r"detector: expected a "
                                                     r"MediaPipePoseDetector"):
            cached_detections(video, "mediapipe", tmp_path)
        with pytest.raises(DetectorInputError, match=r"source: .* neither a video file"):
            source_digest(tmp_path)
