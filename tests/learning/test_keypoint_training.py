"""Self-supervised training of the keypoint term: on synthetic detections made with known
offsets (several seeds) a few alternations recover them from the map's; with confidences that
tell outliers the calibration learns to weight them less; a camera's shifted detections give
it that bias when biases are trained; training twice gives the same parameters; bad settings
are named."""

from __future__ import annotations

import pytest
import torch

from torchmocap.cameras import make_ring_rig
from torchmocap.data import Sequence
from torchmocap.learning.keypoints import (
    KeypointTrainSettings,
    stack_detections,
    train_keypoint_term,
)
from torchmocap.likelihoods import LearnedKeypointLikelihood
from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map

#: keypoints moved from the map's offsets (metres, in their bone frames). Each rides on a bone
#: with other keypoints (pelvis, trunk, head), so its offset is identifiable; a lone keypoint's
#: offset across its limb (a knee's forward) trades off against the joint angles of every frame
#: and is learned slowly — the prior keeps it near the map's.
MOVED = {"LHip": (0.03, 0.0, 0.02), "RHip": (-0.03, 0.0, 0.02), "LShoulder": (0.0, 0.03, 0.0),
         "Nose": (0.0, -0.02, -0.03)}


def _poses(sk, T, seed):
    """A smooth motion: a random pose moving by a random walk (0.08 rad per DoF and frame)
    while turning (0.15 rad per frame)."""
    g = torch.Generator().manual_seed(seed)
    th = sk.zero_pose((T,))
    steps = 0.08 * torch.randn(T, sk.num_dofs - 6, generator=g, dtype=th.dtype)
    th[:, 6:] = 0.3 * torch.randn(sk.num_dofs - 6, generator=g, dtype=th.dtype) \
        + steps.cumsum(0)
    th[:, 5] = 0.15 * torch.arange(T, dtype=th.dtype)
    return sk.clamp(th)


def _recording(seed, T=12, outliers=0.0, shift=None):
    """Detections of ``T`` poses by 4 cameras, made with the map's offsets moved by MOVED
    (0.5 px noise); with ``shift = (camera, du, dv)`` that camera's shifted; with
    ``outliers`` that share of detections is replaced by random pixels and given confidences
    below 0.4 (the right ones above 0.5)."""
    sk = human31()
    rig = make_ring_rig(4, image_size=(640, 480)).float()
    kmap = load_keypoint_map("body_25b", sk)
    true = kmap.offsets.clone().float()
    for n, d in MOVED.items():
        true[kmap.names.index(n)] += torch.tensor(d)
    th = _poses(sk, T, seed)
    kin = sk(th)
    pix = rig.project(keypoint_positions(kin.positions, kin.rotations, kmap, true))[0]
    g = torch.Generator().manual_seed(100 + seed)
    pix = pix + 0.5 * torch.randn(pix.shape, generator=g)
    if shift is not None:  # a camera's detections shifted (pixels)
        pix[:, shift[0]] += torch.tensor(shift[1:])
    conf = 0.5 + 0.5 * torch.rand(pix.shape[:-1], generator=g)
    if outliers:
        bad = torch.rand(pix.shape[:-1], generator=g) < outliers
        rand = torch.rand(pix.shape, generator=g) * torch.tensor([640.0, 480.0])
        pix = torch.where(bad[..., None], rand, pix)
        conf = torch.where(bad, 0.1 + 0.3 * torch.rand(conf.shape, generator=g), conf)
    seq = Sequence(fps=30.0, scenario="recorded", rig=rig,
                   joints2d=torch.cat([pix, conf[..., None]], -1),
                   joint_names=list(kmap.format_keypoints))
    return sk, rig, seq, th, true


def _train(sk, rig, seq, th, **kw):
    term = LearnedKeypointLikelihood(rig, sk, scale_px=4.0, learn=True)
    det = stack_detections(term, seq)
    settings = KeypointTrainSettings(**{"rounds": 3, "pose_iterations": 30,
                                        "parameter_iterations": 40, "offset_prior_m": 0.05,
                                        **kw})
    res = train_keypoint_term(term, sk, det, th[0], settings)
    return term, res


@pytest.mark.parametrize("seed,joint", [(0, True), (1, False), (2, True)])
def test_known_offsets_are_recovered(seed, joint):
    sk, rig, seq, th, true = _recording(seed)
    term, res = _train(sk, rig, seq, th, joint=joint)
    moved = [term.kmap.names.index(n) for n in MOVED]
    before = (term.base_offsets - true).norm(dim=-1)[moved]
    after = (term.offsets.detach() - true).norm(dim=-1)[moved]
    assert float(before.min()) > 0.029
    assert bool((after < 0.7 * before).all()), (before, after)
    assert float(after.mean()) < 0.4 * float(before.mean()), (before, after)
    # the keypoints the detections did not move stay near the map's
    still = [i for i in range(term.kmap.num_keypoints) if i not in moved]
    assert float((term.offsets.detach() - true).norm(dim=-1)[still].median()) < 0.006
    nll = [h["nll_per_detection"] for h in res["history"]]
    assert nll[-1] < nll[0]
    # the poses fitted with the learned parameters are those that made the detections
    joint_err = (sk(res["theta"]).positions - sk(th).positions).norm(dim=-1).mean()
    assert float(joint_err) < 0.02


@pytest.mark.parametrize("seed", [0, 1])
def test_calibration_learns_that_low_confidences_are_outliers(seed):
    sk, rig, seq, th, true = _recording(seed, outliers=0.25)
    term, _ = _train(sk, rig, seq, th)
    w = term.calibrated(torch.tensor([0.2, 0.3, 0.7, 0.9]))
    # untrained g(c) = c: 0.2 / 0.9 = 0.22; the outliers' confidences now weigh far less
    w = w.detach()
    assert float(w[0] / w[3]) < 0.1 and float(w[1] / w[3]) < 0.1
    assert float(w[2] / w[3]) > 0.8
    assert bool((w[1:] >= w[:-1]).all())


def test_a_camera_bias_is_learned_only_when_asked():
    """One camera's detections shifted by (8, -6) px: with bias_prior > 0 its learned bias is
    that shift (the others' stay near 0); with the default 0 the biases stay 0."""
    sk, rig, seq, th, true = _recording(3, shift=(2, 8.0, -6.0))
    term, _ = _train(sk, rig, seq, th, bias_prior=0.02)
    bias = term.pixel_bias.detach() * rig.image_size
    assert float((bias[2] - torch.tensor([8.0, -6.0])).norm()) < 1.5, bias
    assert float(bias[[0, 1, 3]].norm(dim=-1).max()) < 1.5, bias
    fixed, _ = _train(sk, rig, seq, th)
    assert float(fixed.pixel_bias.detach().abs().max()) == 0.0


def test_training_is_reproducible():
    sk, rig, seq, th, true = _recording(5, T=6)
    a, _ = _train(sk, rig, seq, th, rounds=2)
    b, _ = _train(sk, rig, seq, th, rounds=2)
    for n in ("offsets", "log_scale_px", "log_keypoint_scale", "calibration", "pixel_bias"):
        assert torch.equal(getattr(a, n), getattr(b, n)), n


@pytest.mark.parametrize("kw,match", [({"rounds": 0}, "training.rounds"),
                                      ({"bias_prior": -0.1}, "training.bias_prior"),
                                      ({"pose_iterations": 1.5}, "training.pose_iterations"),
                                      ({"offset_prior_m": 0.0}, "training.offset_prior_m"),
                                      ({"scale_prior": float("nan")}, "training.scale_prior")])
def test_bad_settings_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        KeypointTrainSettings(**kw).check()


def test_no_detection_is_refused():
    sk, rig, seq, th, true = _recording(0, T=3)
    term = LearnedKeypointLikelihood(rig, sk, learn=True, on_empty="uninformative")
    det = stack_detections(term, seq)
    det.conf.zero_()
    with pytest.raises(ValueError, match="no valid keypoint detection"):
        train_keypoint_term(term, sk, det, th[0], KeypointTrainSettings())
