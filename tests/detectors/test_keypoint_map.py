"""The mediapipe_33 keypoint map: it loads with the project's loader, lists the format's
keypoints in the detector's order, maps all of them, and places them where the body has them
at human31's zero pose (+x left, -y forward, +z up) — relative to the joints and to OpenPose's
BODY_25B map as the 4-view triangulation of both detectors found."""

from __future__ import annotations

import torch

from torchmocap.io.openpose import KEYPOINT_FORMATS
from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map


def _rest(fmt: str) -> dict[str, torch.Tensor]:
    sk = human31().double()
    kmap = load_keypoint_map(fmt, sk)
    kin = sk(sk.zero_pose((), dtype=torch.float64))
    return dict(zip(kmap.names, keypoint_positions(kin.positions, kin.rotations, kmap)))


def test_smoke():
    kmap = load_keypoint_map("MediaPipe_33", human31())
    assert kmap.format == "mediapipe_33"
    assert kmap.format_keypoints == KEYPOINT_FORMATS["mediapipe_33"]
    assert kmap.names == kmap.format_keypoints and kmap.num_keypoints == 33


def test_feature_anatomy_at_rest():
    sk = human31().double()
    kin = sk(sk.zero_pose((), dtype=torch.float64))
    j = dict(zip(sk.joint_names, kin.positions))
    k, b = _rest("mediapipe_33"), _rest("body_25b")
    x, y, z = 0, 1, 2
    for s, side in (("L", 1.0), ("R", -1.0)):
        # hips: within 1 cm of the hip joint centre, lower and nearer the midline than OpenPose's
        assert float((k[s + "Hip"] - j[s.lower() + "_hip"]).norm()) < 0.01
        assert float(k[s + "Hip"][z]) < float(b[s + "Hip"][z]) - 0.015
        assert side * float(k[s + "Hip"][x]) < side * float(b[s + "Hip"][x]) - 0.01
        # shoulders: above the glenohumeral centre, below OpenPose's
        assert float(j[s.lower() + "_shoulder"][z]) < float(k[s + "Shoulder"][z]) < \
            float(b[s + "Shoulder"][z])
        # eyes: inner corner nearer the midline than the centre, the outer corner farther
        assert 0 < side * float(k[s + "EyeInner"][x]) < side * float(k[s + "Eye"][x]) < \
            side * float(k[s + "EyeOuter"][x])
        assert float(k[s + "Mouth"][z]) < float(k["Nose"][z]) < float(k[s + "Eye"][z])
        # feet: the heel behind and below the ankle, the foot index ahead of the ball of the foot
        ankle, toe = j[s.lower() + "_ankle"], j[s.lower() + "_toe"]
        assert float(k[s + "Heel"][y]) > float(ankle[y]) and float(k[s + "Heel"][z]) < float(
            ankle[z])
        assert float(k[s + "FootIndex"][y]) < float(toe[y]) - 0.03
        # hands: below the wrist; the thumb forward of the pinky
        wrist = j[s.lower() + "_wrist"]
        for n in ("Pinky", "Index", "Thumb"):
            assert float(k[s + n][z]) < float(wrist[z]) - 0.04
        assert float(k[s + "Thumb"][y]) < float(k[s + "Pinky"][y])
    for n in ("Nose", "LEye", "REye", "LEar", "REar", "LKnee", "RAnkle"):  # the same points
        torch.testing.assert_close(k[n], b[n])
