"""Keypoint maps: the packaged formats load, keypoints follow their bones (against the skeleton's
own forward kinematics of the keypoints as fixed child joints), closed forms at rest,
gradients in poses and offsets, and errors that name what is wrong."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.skeleton import (
    KeypointMapError,
    Skeleton,
    human31,
    keypoint_positions,
    known_keypoint_formats,
    load_keypoint_map,
)

FORMATS = {"body_25b": (25, 25), "body_25": (25, 25), "coco_17": (17, 17), "halpe_26": (26, 26),
           "mediapipe_33": (33, 33)}


def _poses(sk, n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    lo = sk.lower.double().clamp(min=-math.pi)
    hi = sk.upper.double().clamp(max=math.pi)
    th = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=g, dtype=torch.float64)
    th[:, sk.translation_dofs] = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return th.to(dtype)


def _as_children(sk, kmap):
    """The skeleton with every keypoint as a fixed child joint (an independent evaluation:
    the skeleton's own forward kinematics)."""
    bones, off = kmap.attachment(sk)
    spec = sk.to_dict()
    for n, b, o in zip(kmap.names, bones, off.tolist()):
        spec["joints"].append({"name": "kp_" + n, "parent": sk.joint_names[b], "offset": o})
    aug = Skeleton.from_dict(spec).double()
    return aug, [aug.joint_index("kp_" + n) for n in kmap.names]


class TestKeypointMap:
    def test_smoke(self):
        assert set(FORMATS) <= set(known_keypoint_formats())
        sk = human31()
        for fmt, (k, mapped) in FORMATS.items():
            kmap = load_keypoint_map(fmt.upper(), sk)  # format names are case-insensitive
            assert kmap.format == fmt and len(kmap.format_keypoints) == k
            assert kmap.num_keypoints == mapped and kmap.offsets.shape == (mapped, 3)
            assert set(kmap.joints) <= set(sk.joint_names)

    def test_feature_rest_pose(self):
        """At the zero pose every bone frame is the world frame: a keypoint is its joint plus
        its offset, plus the riding joint's rest offset when the frame is the parent."""
        sk = human31().double()
        kmap = load_keypoint_map("body_25b", sk)
        kin = sk(sk.zero_pose((), dtype=torch.float64))
        x = keypoint_positions(kin.positions, kin.rotations, kmap)
        p = dict(zip(sk.joint_names, kin.positions))
        k = dict(zip(kmap.names, x))
        torch.testing.assert_close(k["LShoulder"], p["l_shoulder"] + torch.tensor(
            [0.0, 0.0, 0.04], dtype=torch.float64))
        torch.testing.assert_close(k["LAnkle"], p["l_ankle"])
        torch.testing.assert_close(k["Nose"], p["head"] + torch.tensor(
            [0.0, -0.105, -0.04], dtype=torch.float64))
        # anatomy: the nose ahead (-y) of the ears, left keypoints at +x, hips above the
        # hip joint centres and lateral of them, shoulders above the glenohumeral centres
        assert float(k["Nose"][1]) < float(k["LEar"][1]) - 0.05
        assert float(k["LEye"][0]) > 0 > float(k["REye"][0])
        assert float(k["LHip"][2]) > float(p["l_hip"][2]) and float(k["LHip"][0]) > float(
            p["l_hip"][0])
        assert float(k["RShoulder"][2]) > float(p["r_shoulder"][2])

    def test_feature_follows_the_bones(self):
        """At random poses, the keypoints equal the skeleton's forward kinematics of the
        keypoints as fixed children of their bones; a shoulder keypoint (trunk frame) ignores
        the arm, a wrist keypoint follows the elbow."""
        sk = human31().double()
        for fmt in FORMATS:
            kmap = load_keypoint_map(fmt, sk)
            th = _poses(sk, 16, seed=1)
            kin = sk(th)
            x = keypoint_positions(kin.positions, kin.rotations, kmap)
            aug, idx = _as_children(sk, kmap)
            # (the child joints' offsets are stored in float32)
            torch.testing.assert_close(x, aug(th).positions[:, idx], atol=1e-7, rtol=0)
        kmap = load_keypoint_map("body_25b", sk)
        th = _poses(sk, 1, seed=2)
        th2 = th.clone()
        th2[:, sk.dof_index("l_shoulder_flex")] += 0.7
        th2[:, sk.dof_index("l_elbow_flex")] += 0.5
        a, b = (keypoint_positions(k.positions, k.rotations, kmap) for k in (sk(th), sk(th2)))
        i = kmap.names.index
        torch.testing.assert_close(a[:, i("LShoulder")], b[:, i("LShoulder")])
        assert float((a[:, i("LWrist")] - b[:, i("LWrist")]).norm()) > 0.1

    def test_cardinality(self, dtype, device):
        sk = human31().to(dtype=dtype, device=device)
        kmap = load_keypoint_map("coco_17", sk)
        th = _poses(sk, 6, seed=3, dtype=dtype).to(device).reshape(2, 3, -1)
        kin = sk(th)
        x = keypoint_positions(kin.positions, kin.rotations, kmap)
        assert x.shape == (2, 3, 17, 3) and x.dtype == dtype and x.device == device
        # per-sample offsets broadcast against the batch
        off = torch.zeros(3, 17, 3, dtype=dtype, device=device)
        y = keypoint_positions(kin.positions, kin.rotations, kmap, off)
        torch.testing.assert_close(y, kin.positions[..., kmap.joint_index.to(device), :])

    def test_gradcheck(self):
        sk = human31().double()
        kmap = load_keypoint_map("body_25b", sk)
        th = _poses(sk, 2, seed=4).requires_grad_(True)
        off = kmap.offsets.clone().requires_grad_(True)

        def f(theta, offsets):
            kin = sk(theta)
            return keypoint_positions(kin.positions, kin.rotations, kmap, offsets)

        assert torch.autograd.gradcheck(f, (th, off))

    def test_module_bind(self):
        """A map bound to a rescaled skeleton follows its joints; a map bound to other joints
        is refused by the keypoint-as-child view."""
        sk = human31().double()
        big = sk.with_bone_lengths(scale=1.1)
        kmap = load_keypoint_map("body_25b", sk).bind(big)
        kin = big(big.zero_pose((), dtype=torch.float64))
        x = keypoint_positions(kin.positions, kin.rotations, kmap)
        assert float(x[kmap.names.index("Head"), 2]) == pytest.approx(1.1 * 1.75 - 0.01)
        small = Skeleton.from_dict({"name": "two", "joints": [
            {"name": "pelvis", "parent": None}, {"name": "head", "parent": "pelvis",
                                                 "offset": [0, 0, 1]}]})
        with pytest.raises(KeypointMapError, match="bound to joints"):
            load_keypoint_map("body_25b", sk).attachment(small)

    def test_module_dict_round_trip(self):
        """``to_dict`` is the YAML schema: read back (bound to a skeleton), the map equals the
        original, JSON survives it, and scaled offsets (a subject's fitted map) are kept."""
        import dataclasses
        import json

        sk = human31().double()
        kmap = load_keypoint_map("body_25b", sk)
        fitted = dataclasses.replace(kmap, offsets=kmap.offsets * 0.9)
        d = json.loads(json.dumps(fitted.to_dict()))
        back = load_keypoint_map(d, sk)
        assert back.names == kmap.names and back.frames == kmap.frames
        assert back.format_keypoints == kmap.format_keypoints and back.format == "body_25b"
        torch.testing.assert_close(back.offsets, kmap.offsets * 0.9)
        assert torch.equal(back.joint_index, kmap.joint_index)

    def test_exception(self, tmp_path):
        sk = human31()
        with pytest.raises(KeypointMapError, match="unknown keypoint format 'body_99'"):
            load_keypoint_map("body_99")
        with pytest.raises(KeypointMapError, match=r"unknown joints \['head_top', 'l_ankle'"):
            load_keypoint_map("body_25b", Skeleton.from_dict({"name": "two", "joints": [
                {"name": "pelvis", "parent": None},
                {"name": "head", "parent": "pelvis", "offset": [0, 0, 1]}]}))

        def write(text):
            p = tmp_path / "m.yaml"
            p.write_text(text)
            return p

        head = "format: f\nkeypoints: [A, B]\n"
        cases = [
            (head + "map:\n  A: {joint: l_elbw}\n", r"unknown joints \['l_elbw'\]"),
            (head + "map:\n  C: {joint: l_elbow}\n", r"unknown keypoints \['C'\]"),
            (head + "map:\n  A: {joint: l_elbow, offset: [0, 1]}\n", r"map.A.offset"),
            (head + "map:\n  A: {joint: l_elbow, offset: [0, .nan, 1]}\n", r"map.A.offset"),
            (head + "map:\n  A: {joint: l_wrist, frame: spine}\n", r"map.A: frame 'spine'"),
            (head + "map:\n  A: {joint: l_wrist, ofset: [0, 0, 0]}\n", r"unknown keys"),
            ("format: f\nkeypoints: [A, A]\nmap:\n  A: {joint: head}\n", "more than once"),
            ("format: f\nmap:\n  A: {joint: head}\n", "'keypoints' must list"),
            ("keypoints: [A]\nmap:\n  A: {joint: head}\n", "'format'"),
            (head + "skeleton: nope\nmap:\n  A: {joint: head}\n", "unknown preset 'nope'"),
            ("[1, 2", "not valid YAML"),
        ]
        for text, msg in cases:
            with pytest.raises(KeypointMapError, match=msg):
                load_keypoint_map(write(text))
        with pytest.raises(KeypointMapError, match="cannot read"):
            load_keypoint_map(tmp_path / "missing.yaml")
        # a user map from a path works, and unmapped format keypoints are left out
        kmap = load_keypoint_map(write(head + "map:\n  B: {joint: l_wrist}\n"), sk)
        assert kmap.names == ("B",) and kmap.format_keypoints == ("A", "B")
        with pytest.raises(KeypointMapError, match=r"needs keypoints \['B'\]"):
            kmap.columns(["A", "C"])
        assert kmap.columns(["C", "B", "A"]).tolist() == [1]
        kin = sk(sk.zero_pose((2,)))
        with pytest.raises(ValueError, match="positions"):
            keypoint_positions(kin.positions[..., :2], kin.rotations, kmap)
        with pytest.raises(ValueError, match="rotations"):
            keypoint_positions(kin.positions, kin.rotations[:1], kmap)
        with pytest.raises(ValueError, match="offsets"):
            keypoint_positions(kin.positions, kin.rotations, kmap, torch.zeros(2, 3))
