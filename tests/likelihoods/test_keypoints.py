"""The keypoint reprojection energy: zero at the pose that generated noiseless detections (lens
distortion included), worse elsewhere, equal to the 2D-joint energy when keypoints are the
joints, column order by name, missed / low-confidence / dropped-view detections ignored, empty
frames, per-view scales, gradcheck in poses and offsets, trainable parameters, and the term built
from its config with the runtime's keypoint names."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.assembly import Runtime, build
from torchmocap.cameras import CameraRig, make_ring_rig
from torchmocap.data import Frame, Sequence
from torchmocap.likelihoods import (
    EmptyEvidenceError,
    FrameEnergy,
    Joints2DLikelihood,
    KeypointLikelihood,
    Poses,
)
from torchmocap.skeleton import KeypointMapError, human31, keypoint_positions, load_keypoint_map


def _rig(C=3):
    base = make_ring_rig(C, image_size=(640, 480))  # float64
    dist = torch.tensor([[-0.15, 0.03, 1e-3, -5e-4, 0.0]] * C, dtype=torch.float64)
    return CameraRig(base.K, base.R, base.t, base.image_size, dist)


def _pose(sk, seed, scale=0.3):
    g = torch.Generator().manual_seed(seed)
    th = sk.zero_pose((1,))
    th[0, 6:] = scale * torch.randn(sk.num_dofs - 6, generator=g, dtype=th.dtype)
    return sk.clamp(th)


def _detections(sk, rig, th, fmt="body_25b"):
    """Noiseless (C, K, 3) detections of the mapped keypoints of ``th``, confidence 1 (0 for
    the format's unmapped keypoints)."""
    kmap = load_keypoint_map(fmt, sk)
    kin = sk(th)
    x = keypoint_positions(kin.positions, kin.rotations, kmap)[0]
    pix = rig.project(x)[0]  # (C, K', 2)
    C, K = rig.num_cameras, len(kmap.format_keypoints)
    det = torch.zeros(C, K, 3, dtype=pix.dtype)
    cols = kmap.columns(kmap.format_keypoints)
    det[:, cols, :2] = pix
    det[:, cols, 2] = 1.0
    return det


@pytest.fixture(scope="module")
def scene():
    sk = human31().double()
    rig = _rig()
    th = _pose(sk, 0)
    return sk, rig, th, _detections(sk, rig, th)


def _energy(term, frame, sk, th):
    return FrameEnergy(term, term.prepare(frame), sk)(th)


class TestKeypointLikelihood:
    def test_smoke(self, scene):
        sk, rig, th, det = scene
        term = KeypointLikelihood(rig, sk).double()
        obs = term.prepare(Frame(0, 0.0, joints2d=det))
        assert obs.uv.shape == (3, 25, 2) and obs.num_valid == 75 and term.evidence(obs)
        assert term.energy(Poses(th.expand(4, -1), sk), obs).shape == (4,)
        assert "body_25b" in repr(term)

    def test_feature_zero_at_the_generating_pose_and_worse_elsewhere(self, scene):
        sk, rig, th, det = scene
        term = KeypointLikelihood(rig, sk, scale_px=4.0).double()
        frame = Frame(0, 0.0, joints2d=det)
        wrong = th.clone()
        wrong[0, sk.dof_index("l_elbow_flex")] += 0.4
        shifted = th.clone()
        shifted[0, 0] += 0.02  # 2 cm
        v = _energy(term, frame, sk, torch.cat([th, wrong, shifted]))
        assert float(v[0]) < 1e-12
        assert float(v[1]) > 1.0 and float(v[2]) > 0.1
        # the joint centres are not the keypoints: the skeleton's joints projected as if
        # they were keypoints score worse than the keypoints themselves
        kmap = load_keypoint_map("body_25b", sk)
        joints = det.clone()
        cols = kmap.columns(kmap.format_keypoints)
        joints[:, cols, :2] = rig.project(sk(th).positions[0, kmap.joint_index])[0]
        assert float(_energy(term, Frame(0, 0.0, joints2d=joints), sk, th)[0]) > 1.0

    def test_feature_equals_the_joints2d_energy_for_joint_keypoints(self, tmp_path):
        """With a map whose keypoints are the joints themselves (zero offsets), the term is
        the 2D-joint energy."""
        sk = human31().double()
        rig = _rig(2)
        lines = ["format: joints", f"keypoints: [{', '.join(sk.joint_names)}]", "map:"]
        lines += [f"  {n}: {{joint: {n}}}" for n in sk.joint_names]
        path = tmp_path / "joints.yaml"
        path.write_text("\n".join(lines) + "\n")
        g = torch.Generator().manual_seed(1)
        th = _pose(sk, 1)
        pix = rig.project(sk(th).positions[0])[0]
        det = torch.cat([pix + 3 * torch.randn(pix.shape, generator=g, dtype=pix.dtype),
                         torch.rand(2, 21, 1, generator=g, dtype=pix.dtype)], -1)
        det[1, 4, 2] = 0.0
        frame = Frame(0, 0.0, joints2d=det)
        poses = torch.cat([th, _pose(sk, 2)])
        for robust in ("cauchy", "huber"):
            a = KeypointLikelihood(rig, sk, keypoint_map=path, scale_px=5.0, robust=robust,
                                   min_confidence=0.2).double()
            b = Joints2DLikelihood(rig, sk, scale_px=5.0, robust=robust, min_confidence=0.2)
            torch.testing.assert_close(_energy(a, frame, sk, poses), _energy(b, frame, sk, poses))

    def test_feature_columns_follow_the_keypoint_names(self, scene):
        sk, rig, th, det = scene
        names = list(load_keypoint_map("body_25b").format_keypoints)
        perm = torch.randperm(25, generator=torch.Generator().manual_seed(3))
        shuffled = KeypointLikelihood(rig, sk, keypoint_names=[names[i] for i in perm]).double()
        plain = KeypointLikelihood(rig, sk).double()
        poses = torch.cat([th, _pose(sk, 4)])
        torch.testing.assert_close(
            _energy(shuffled, Frame(0, 0.0, joints2d=det[:, perm]), sk, poses),
            _energy(plain, Frame(0, 0.0, joints2d=det), sk, poses))
        # extra columns the map does not use are ignored; a missing mapped keypoint is an error
        extra = KeypointLikelihood(rig, sk, keypoint_names=names + ["LPinky"]).double()
        det2 = torch.cat([det, torch.full((3, 1, 3), 7.0, dtype=det.dtype)], 1)
        torch.testing.assert_close(_energy(extra, Frame(0, 0.0, joints2d=det2), sk, poses),
                                   _energy(plain, Frame(0, 0.0, joints2d=det), sk, poses))
        with pytest.raises(KeypointMapError, match=r"needs keypoints \['LHeel'\]"):
            KeypointLikelihood(rig, sk, keypoint_names=[n for n in names if n != "LHeel"])

    def test_feature_ignored_detections(self, scene):
        """A keypoint of confidence 0, below min_confidence, non-finite, or in a view the frame
        drops is ignored: corrupting it changes nothing."""
        sk, rig, th, det = scene
        poses = torch.cat([th, _pose(sk, 5)])
        term = KeypointLikelihood(rig, sk, min_confidence=0.3).double()
        ref = det.clone()
        ref[0, 7, 2] = 0.0
        ref[1, 3, 2] = 0.2
        base = _energy(term, Frame(0, 0.0, joints2d=ref), sk, poses)
        bad = ref.clone()
        bad[0, 7, :2] += 300.0
        bad[1, 3, :2] -= 300.0
        torch.testing.assert_close(_energy(term, Frame(0, 0.0, joints2d=bad), sk, poses), base)
        bad[2, 10, :2] = float("nan")
        ref2 = ref.clone()
        ref2[2, 10, 2] = 0.0
        torch.testing.assert_close(_energy(term, Frame(0, 0.0, joints2d=bad), sk, poses),
                                   _energy(term, Frame(0, 0.0, joints2d=ref2), sk, poses))
        dropped = torch.tensor([False, False, True])
        moved = det.clone()
        moved[2, :, :2] += 50.0
        only2 = det.clone()
        only2[2, :, 2] = 0.0
        torch.testing.assert_close(
            _energy(term, Frame(0, 0.0, joints2d=moved, view_dropped=dropped), sk, poses),
            _energy(term, Frame(0, 0.0, joints2d=only2), sk, poses))

    def test_feature_empty_frames(self, scene):
        sk, rig, th, det = scene
        empty = det.clone()
        empty[..., 2] = 0.0
        with pytest.raises(EmptyEvidenceError, match="frame 7 has no valid keypoint"):
            KeypointLikelihood(rig, sk).prepare(Frame(7, 0.0, joints2d=empty))
        term = KeypointLikelihood(rig, sk, on_empty="uninformative").double()
        obs = term.prepare(Frame(7, 0.0, joints2d=empty))
        assert not term.evidence(obs)
        v = term.energy(Poses(torch.cat([th, _pose(sk, 6)]), sk), obs)
        # as the 2D-joint term: rho(1) per slot, the same for every pose, never 0
        torch.testing.assert_close(v, torch.full((2,), 3 * 25 * math.log(2.0),
                                                 dtype=v.dtype))

    def test_feature_per_view_scales(self, scene):
        sk, rig, th, det = scene
        noisy = det.clone()
        noisy[..., :2] += 2.0
        frame = Frame(0, 0.0, joints2d=noisy)
        poses = torch.cat([th, _pose(sk, 7)])
        same = KeypointLikelihood(rig, sk, scale_px=[3.0, 3.0, 3.0]).double()
        one = KeypointLikelihood(rig, sk, scale_px=3.0).double()
        torch.testing.assert_close(_energy(same, frame, sk, poses), _energy(one, frame, sk, poses))
        # Gaussian cost, mean reduction, unit confidences: V = mean_ck |r|^2 / s_c^2, and the
        # generating pose's residual is exactly (2, 2) px everywhere (8 px^2)
        for scales in ([1.0, 2.0, 4.0], [2.0, 2.0, 2.0]):
            t = KeypointLikelihood(rig, sk, scale_px=scales, robust="gaussian",
                                   reduction="mean").double()
            expect = sum(25 * 8.0 / s ** 2 for s in scales) / 75
            # (rel 1e-6: the offsets parameter was created in float32)
            assert float(_energy(t, frame, sk, th)[0]) == pytest.approx(expect, rel=1e-6)

    def test_gradcheck(self, scene):
        sk, rig, th, det = scene
        noisy = det.clone()
        noisy[..., :2] += 3.0 * torch.randn(det[..., :2].shape,
                                            generator=torch.Generator().manual_seed(8),
                                            dtype=det.dtype)
        term = KeypointLikelihood(rig, sk, scale_px=[4.0, 5.0, 6.0], learn_offsets=True,
                                  learn_scale=True).double()
        obs = term.prepare(Frame(0, 0.0, joints2d=noisy))
        theta = torch.cat([th, _pose(sk, 9)]).requires_grad_(True)

        def f(theta, offsets, log_scale):
            return torch.func.functional_call(
                term, {"offsets": offsets, "log_scale_px": log_scale}, (Poses(theta, sk), obs))

        assert torch.autograd.gradcheck(f, (theta, term.offsets.detach().clone()
                                            .requires_grad_(True),
                                            term.log_scale_px.detach().clone()
                                            .requires_grad_(True)))

    def test_module_parameters(self, scene):
        """Offsets and scales are parameters, frozen by default; made trainable, the energy's
        gradient reaches them."""
        sk, rig, th, det = scene
        frozen = KeypointLikelihood(rig, sk)
        assert not frozen.offsets.requires_grad and not frozen.log_scale_px.requires_grad
        assert {n for n, _ in frozen.named_parameters()} == {"offsets", "log_scale_px"}
        term = KeypointLikelihood(rig, sk, learn_offsets=True, learn_scale=True).double()
        noisy = det.clone()
        noisy[..., :2] += 1.5
        v = _energy(term, Frame(0, 0.0, joints2d=noisy), sk, th)
        v.sum().backward()
        assert float(term.offsets.grad.abs().sum()) > 0
        assert float(term.log_scale_px.grad.abs().sum()) > 0
        torch.testing.assert_close(term.scale_px, torch.full((3,), 8.0, dtype=torch.float64))

    def test_module_built_from_its_config(self, scene):
        """conf/term/keypoints.yaml builds with the runtime's keypoint names, which
        Runtime.from_sequence takes from the sequence's joint names."""
        from hydra import compose, initialize_config_module
        from hydra.core.global_hydra import GlobalHydra

        sk, rig, th, det = scene
        names = list(load_keypoint_map("body_25b").format_keypoints)
        perm = torch.arange(24, -1, -1)
        seq = Sequence(fps=60.0, scenario="recorded", rig=rig,
                       joints2d=det[:, perm][None].float(), joint_names=[names[i] for i in perm])
        runtime = Runtime.from_sequence(seq, skeleton=sk)
        assert runtime.keypoint_names == seq.joint_names
        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
            cfg = compose(config_name="track", overrides=["+term@probe=keypoints"]).probe
        term = build(cfg, runtime, _path="probe")
        assert isinstance(term, KeypointLikelihood)
        assert term.keypoint_names == seq.joint_names and term.rig is runtime.rig
        v = _energy(term, seq.frame(0), runtime.skeleton, th.float())
        assert float(v[0]) < 1e-3

    def test_exception(self, scene):
        sk, rig, th, det = scene
        for kw, msg in ((dict(scale_px=0.0), "scale_px"), (dict(scale_px=[1.0, 2.0]), "scale_px"),
                        (dict(robust="l1"), "robust"), (dict(reduction="max"), "reduction"),
                        (dict(on_empty="skip"), "on_empty"),
                        (dict(min_confidence=1.5), "min_confidence"),
                        (dict(keypoint_map="body_99"), "unknown keypoint format")):
            with pytest.raises(ValueError, match=msg):
                KeypointLikelihood(rig, sk, **kw)
        with pytest.raises(ValueError, match="rig"):
            KeypointLikelihood(None, sk)
        term = KeypointLikelihood(rig, sk)
        with pytest.raises(ValueError, match=r"expected shape \(3, 25, 3\)"):
            term.prepare(Frame(0, 0.0, joints2d=det[:2]))
        with pytest.raises(ValueError, match="no 2D keypoint detections"):
            term.prepare(Frame(0, 0.0))
        neg = det.clone()
        neg[0, 0, 2] = -1.0
        with pytest.raises(ValueError, match="confidences must be >= 0"):
            term.prepare(Frame(0, 0.0, joints2d=neg))
