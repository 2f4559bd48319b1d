"""MediaPipe Pose on real frames: landmarks on the person (inside bodytrack's FG masks, near the
OpenPose detections of pose2sim_balancing), the person mask against the shipped FG masks, the
box steering detection to the subject or the bystander, determinism, no download, and errors.

Measured on these frames (docs/detectors.md): IoU 0.865, 0.857, 0.773, 0.781 against FG1..4;
33/33 landmarks inside FG1..3, 31/33 inside FG4 (the FG masks are background subtraction:
FG3/FG4 hold noise far from the person); median 6-19 px from OpenPose's body keypoints in
1080x1920 frames.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
import torch

from torchmocap.detectors import (
    MEDIAPIPE_33,
    DetectorInputError,
    DetectorSettingsError,
    DetectorUnavailableError,
    MediaPipePoseDetector,
    MediaPipePoseSettings,
    keypoint_box,
    landmarks_to_keypoints,
)
from torchmocap.io.openpose import KEYPOINT_FORMATS

from .conftest import CAMERAS, require_mediapipe

OP = KEYPOINT_FORMATS["body_25b"]
BODY = ("LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist", "LHip", "RHip",
        "LKnee", "RKnee", "LAnkle", "RAnkle")


def body_distance(kp: torch.Tensor, openpose: torch.Tensor) -> float:
    """Median pixel distance between MediaPipe's and OpenPose's body keypoints of one person
    (the names they share: shoulders to ankles)."""
    d = [(kp[MEDIAPIPE_33.index(n), :2] - openpose[OP.index(n), :2]).norm() for n in BODY
         if openpose[OP.index(n), 2] > 0.1]
    return float(torch.stack(d).median())


class TestMediaPipePose:
    def test_smoke(self, detector, bodytrack_views):
        rgb, _ = bodytrack_views[0]
        out = detector(rgb)
        assert out.keypoints.shape == (1, 33, 3) and out.keypoints.dtype == torch.float64
        assert out.mask.shape == (480, 640) and out.mask.dtype == torch.float32
        assert float(out.mask.min()) >= 0 and float(out.mask.max()) <= 1 and out.region is None
        c = out.keypoints[0, :, 2]
        assert bool(((c >= 0) & (c <= 1)).all()) and float(c.median()) > 0.9

    def test_feature_landmarks_and_mask_on_the_person(self, detector, bodytrack_views):
        """bodytrack (ceiling cameras, grey, the person seen from above): the landmarks lie in
        the shipped FG mask and the mask overlaps it."""
        ious = []
        for c, (rgb, fg) in enumerate(bodytrack_views, 1):
            out = detector(rgb)
            assert out.keypoints.shape[0] == 1, f"CAM{c}: nobody found"
            uv = out.keypoints[0, :, :2].round().long()
            u, v = uv[:, 0].clamp(0, 639), uv[:, 1].clamp(0, 479)
            inside = float(torch.from_numpy(fg)[v, u].float().mean())
            assert inside >= 0.9, f"CAM{c}: {inside:.2f} of the landmarks in the FG mask"
            pm = out.mask.numpy() > 0.5
            ious.append((pm & fg).sum() / (pm | fg).sum())
        assert min(ious) > 0.72 and np.mean(ious) > 0.78, ious

    def test_feature_openpose_agreement(self, detector, pose2sim_frames):
        """pose2sim_balancing frame 0, every view: MediaPipe's body keypoints within 30 px
        (median) of OpenPose's detections of the subject, searched in the whole image and in
        the subject's box."""
        for cam in CAMERAS:
            rgb, sub, _ = pose2sim_frames[cam]
            for box in (None, keypoint_box(sub, 0.1)):
                out = detector(rgb, box)
                assert out.keypoints.shape == (1, 33, 3)
                d = body_distance(out.keypoints[0], sub)
                assert d < 30, f"{cam} box={box}: {d:.1f} px from OpenPose"

    def test_feature_box_finds_the_subject_not_the_bystander(self, detector, pose2sim_frames):
        """cam01 and cam02 show a bystander: in the subject's box the detector finds the
        subject (far from the bystander), in the bystander's box the bystander, and the result
        is in the full frame's pixels."""
        for cam in ("cam01", "cam02"):
            rgb, sub, raw = pose2sim_frames[cam]
            assert raw.shape[0] == 2
            spread = [float((p[:, :2] - sub[:, :2]).norm(dim=-1).median()) for p in raw]
            bystander = raw[int(np.argmax(spread))]
            on_sub = detector(rgb, keypoint_box(sub, 0.1))
            assert body_distance(on_sub.keypoints[0], sub) < 25
            assert body_distance(on_sub.keypoints[0], bystander) > 200
            x0, y0, x1, y1 = on_sub.region
            assert float(on_sub.mask[:, :x0].abs().sum() + on_sub.mask[:, x1:].abs().sum()) == 0
            on_bys = detector(rgb, keypoint_box(bystander, 0.1))
            assert body_distance(on_bys.keypoints[0], bystander) < 25
            assert body_distance(on_bys.keypoints[0], sub) > 200

    def test_feature_deterministic(self, detector, bodytrack_views):
        rgb, _ = bodytrack_views[1]
        a, b = detector(rgb), detector(rgb.copy())
        assert torch.equal(a.keypoints, b.keypoints) and torch.equal(a.mask, b.mask)
        with MediaPipePoseDetector() as other:
            c = other(torch.from_numpy(rgb.copy()))  # a tensor works too
        assert torch.equal(a.keypoints, c.keypoints) and torch.equal(a.mask, c.mask)

    def test_feature_nobody(self, detector, bodytrack_views):
        rgb, _ = bodytrack_views[0]
        blank = detector(np.full((240, 320, 3), 127, np.uint8))
        assert blank.keypoints.shape == (0, 33, 3) and blank.mask.shape == (240, 320)
        assert float(blank.mask.abs().sum()) == 0
        outside = detector(rgb, (700.0, 10.0, 800.0, 100.0))  # a box beyond the image
        assert outside.keypoints.shape == (0, 33, 3) and float(outside.mask.sum()) == 0

    def test_feature_landmarks_to_keypoints(self):
        """Normalised coordinates to pixel centres, the crop's corner added, confidence 0
        outside the full image."""
        lm = np.array([[0.0, 0.0, 0.9], [0.5, 0.25, 0.8], [1.2, 0.5, 0.7]])
        kp = landmarks_to_keypoints(lm, (100, 200), (10, 20, 110, 220), (640, 480))
        assert kp.tolist() == [[9.5, 19.5, 0.9], [59.5, 69.5, 0.8], [129.5, 119.5, 0.7]]
        kp = landmarks_to_keypoints(lm, (100, 200))
        assert kp[:, 2].tolist() == [0.9, 0.8, 0.0]  # x = 1.2: beyond the right edge

    def test_no_download(self, monkeypatch, bodytrack_views):
        """With networking and mediapipe's model download made to fail, the detector builds
        and runs: its models are the wheel's files."""
        require_mediapipe()
        from mediapipe.python.solutions import download_utils

        def refuse(*args, **kwargs):
            raise AssertionError(f"a download was attempted: {args}")

        monkeypatch.setattr(socket.socket, "connect", refuse)
        monkeypatch.setattr(urllib.request, "urlopen", refuse)
        monkeypatch.setattr(download_utils, "download_oss_model", refuse)
        with MediaPipePoseDetector() as det:
            assert det(bodytrack_views[2][0]).keypoints.shape == (1, 33, 3)
        for complexity in (0, 2):  # mediapipe would download these models
            with pytest.raises(DetectorSettingsError, match=r"model_complexity: only 1"):
                MediaPipePoseDetector(model_complexity=complexity)

    def test_no_download_without_network(self, data_file):
        """In a process without a network (its own network namespace), the detector builds
        and finds the person: nothing it runs, Python or C++, needs the internet."""
        require_mediapipe()
        exe = shutil.which("unshare")
        if exe is None or subprocess.run([exe, "-n", "true"], capture_output=True).returncode:
            pytest.skip("no network namespace here (unshare -n is not permitted)")
        image = data_file("multiview/bodytrack_sequenceB_1/CAM1/image0000.png")
        code = ("import numpy as np; from PIL import Image; "
                "from torchmocap.detectors import MediaPipePoseDetector; "
                f"rgb = np.asarray(Image.open({str(image)!r}).convert('RGB')); "
                "print('found', MediaPipePoseDetector()(rgb).keypoints.shape[0])")
        env = dict(os.environ, OMP_NUM_THREADS="1")
        probe = subprocess.run([exe, "-n", sys.executable, "-c", "import socket; "
                                "socket.create_connection(('1.1.1.1', 80), timeout=1)"],
                               capture_output=True, text=True, timeout=60)
        assert probe.returncode != 0 and "unreachable" in probe.stderr  # really offline
        r = subprocess.run([exe, "-n", sys.executable, "-c", code], capture_output=True,
                           text=True, env=env, timeout=120)
        assert r.returncode == 0 and "found 1" in r.stdout, r.stderr[-2000:]

    def test_exception_model_files(self, monkeypatch, tmp_path):
        """Missing or altered model files are refused before a graph is built."""
        require_mediapipe()
        from torchmocap.detectors import mediapipe_pose

        monkeypatch.setattr(mediapipe_pose, "_CHECKED", {})
        monkeypatch.setattr(mediapipe_pose, "_package_root", lambda: tmp_path)
        with pytest.raises(DetectorUnavailableError, match=r"pose_detection.tflite: missing"):
            MediaPipePoseDetector()
        for rel in mediapipe_pose.MODEL_FILES:
            (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / rel).write_bytes(b"not the model")
        with pytest.raises(DetectorUnavailableError, match=r"SHA-256 .* differs from mediapipe"):
            MediaPipePoseDetector()

    def test_exception(self, detector, bodytrack_views):
        img = np.zeros((48, 64, 3), np.uint8)
        with pytest.raises(DetectorInputError, match=r"image: expected dtype uint8"):
            detector(img.astype(np.float32))
        with pytest.raises(DetectorInputError, match=r"image: expected shape \(H, W, 3\).*grey"):
            detector(img[..., 0])
        with pytest.raises(DetectorInputError, match=r"image: expected shape \(H, W, 3\)"):
            detector(np.zeros((48, 64, 4), np.uint8))
        with pytest.raises(DetectorInputError, match=r"image: the image is empty"):
            detector(np.zeros((0, 64, 3), np.uint8))
        with pytest.raises(DetectorInputError, match=r"image: expected an \(H, W, 3\) uint8"):
            detector([[0, 0, 0]])
        with pytest.raises(DetectorInputError, match=r"box: expected u_min < u_max"):
            detector(img, (50.0, 0.0, 10.0, 40.0))
        with pytest.raises(DetectorSettingsError, match=r"unknown \['smooth'\]; expected some"):
            MediaPipePoseDetector(smooth=True)
        with pytest.raises(DetectorSettingsError, match=r"min_detection_confidence: expected"):
            MediaPipePoseSettings(min_detection_confidence=1.5)
        with pytest.raises(DetectorSettingsError, match=r"margin: expected a fraction"):
            MediaPipePoseSettings(margin=-1)
        with pytest.raises(DetectorSettingsError, match=r"segmentation: expected true"):
            MediaPipePoseSettings(segmentation="yes")
        with pytest.raises(DetectorSettingsError, match=r"settings: expected"):
            MediaPipePoseDetector(settings=3)
        det = MediaPipePoseDetector(segmentation=False)
        out = det(bodytrack_views[0][0])
        assert out.keypoints.shape == (1, 33, 3) and float(out.mask.abs().sum()) == 0
        det.close()
        with pytest.raises(RuntimeError, match=r"detect\(\) after close\(\)"):
            det(img)
