"""The trainable keypoint term: the confidence calibration is monotone for any parameters,
untrained the term has the hand-set term's energy, gradcheck in offsets, scales, calibration and
pixel biases, the biases shift the expected pixels, a weights file round trip, refusal of a file
of another map or setting, and a warning for cameras the file does not know."""

from __future__ import annotations

import pytest
import torch

from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import (
    ArchitectureMismatchError,
    FrameEnergy,
    KeypointLikelihood,
    LearnedKeypointLikelihood,
    Poses,
    WeightsError,
)
from torchmocap.likelihoods.keypoints_learned import identity_calibration, monotone_calibration
from torchmocap.skeleton import human31, keypoint_positions, load_keypoint_map


def _pose(sk, seed, scale=0.3):
    g = torch.Generator().manual_seed(seed)
    th = sk.zero_pose((1,))
    th[0, 6:] = scale * torch.randn(sk.num_dofs - 6, generator=g, dtype=th.dtype)
    return sk.clamp(th)


@pytest.fixture(scope="module")
def scene():
    """3 cameras, noisy detections of a pose with random confidences (some missed)."""
    sk = human31().double()
    rig = make_ring_rig(3, image_size=(640, 480))
    th = _pose(sk, 0)
    kmap = load_keypoint_map("body_25b", sk)
    kin = sk(th)
    pix = rig.project(keypoint_positions(kin.positions, kin.rotations, kmap)[0])[0]
    g = torch.Generator().manual_seed(3)
    pix = pix + 4.0 * torch.randn(pix.shape, generator=g, dtype=pix.dtype)
    conf = torch.rand(pix.shape[:-1], generator=g, dtype=pix.dtype)
    conf[conf < 0.15] = 0.0
    det = torch.cat([pix, conf[..., None]], -1)  # body_25b: every keypoint is mapped
    return sk, rig, th, det


def _randomise(term, seed):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p, f in ((term.offsets, 0.03), (term.log_scale_px, 0.3),
                     (term.log_keypoint_scale, 0.3), (term.calibration, 0.3),
                     (term.pixel_bias, 0.01)):
            p.add_(f * torch.randn(p.shape, generator=g, dtype=p.dtype))


class TestCalibration:
    @pytest.mark.parametrize("seed", range(5))
    def test_monotone_for_any_parameters(self, seed):
        g = torch.Generator().manual_seed(seed)
        params = 4.0 * torch.randn(11, generator=g, dtype=torch.float64)
        c = torch.linspace(-0.2, 1.2, 1401, dtype=torch.float64)
        w = monotone_calibration(c, params)
        assert bool((w[1:] >= w[:-1]).all())
        assert float(monotone_calibration(torch.zeros(1, dtype=torch.float64), params)) == 0.0
        assert float(w.max()) < 1.0
        inside = (c > 0) & (c <= 1)
        assert bool((w[inside] > 0).all())  # a detection of positive confidence keeps a weight

    def test_identity_untrained(self):
        c = torch.linspace(0, 1, 37, dtype=torch.float64)
        torch.testing.assert_close(monotone_calibration(c, identity_calibration(7)), c / (1 + 1e-6))


class TestLearnedKeypointLikelihood:
    def test_untrained_energy_is_the_hand_set_terms(self, scene):
        sk, rig, th, det = scene
        frame = Frame(0, 0.0, joints2d=det)
        theta = torch.cat([th, _pose(sk, 4), _pose(sk, 5)])
        for kw in ({}, {"scale_px": [4.0, 6.0, 9.0], "robust": "geman_mcclure",
                        "min_confidence": 0.3}, {"reduction": "mean"}):
            hand = KeypointLikelihood(rig, sk, **kw).double()
            learned = LearnedKeypointLikelihood(rig, sk, **kw).double()
            a = FrameEnergy(hand, hand.prepare(frame), sk)(theta)
            b = FrameEnergy(learned, learned.prepare(frame), sk)(theta)
            torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-9)

    def test_trained_parameters_change_the_energy(self, scene):
        sk, rig, th, det = scene
        frame = Frame(0, 0.0, joints2d=det)
        hand = KeypointLikelihood(rig, sk).double()
        learned = LearnedKeypointLikelihood(rig, sk).double()
        _randomise(learned, 1)
        a = FrameEnergy(hand, hand.prepare(frame), sk)(th)
        b = FrameEnergy(learned, learned.prepare(frame), sk)(th)
        assert abs(float(a - b)) > 1e-3

    def test_gradcheck(self, scene):
        sk, rig, th, det = scene
        term = LearnedKeypointLikelihood(rig, sk, scale_px=[4.0, 5.0, 6.0]).double()
        _randomise(term, 2)
        obs = term.prepare(Frame(0, 0.0, joints2d=det))
        theta = torch.cat([th, _pose(sk, 9)])
        names = ("offsets", "log_scale_px", "log_keypoint_scale", "calibration", "pixel_bias")

        def f(*params):
            return torch.func.functional_call(term, dict(zip(names, params)),
                                              (Poses(theta, sk), obs))

        args = tuple(getattr(term, n).detach().clone().requires_grad_(True) for n in names)
        assert torch.autograd.gradcheck(f, args)

    def test_weights_round_trip(self, scene, tmp_path):
        sk, rig, th, det = scene
        term = LearnedKeypointLikelihood(rig, sk, scale_px=[4.0, 5.0, 6.0]).double()
        _randomise(term, 3)
        path = term.save_weights(tmp_path / "k.pt", training={"note": "x"})
        back = LearnedKeypointLikelihood(rig, sk, scale_px=[4.0, 5.0, 6.0],
                                         weights=str(path)).double()
        for n in ("offsets", "log_scale_px", "log_keypoint_scale", "calibration", "pixel_bias"):
            torch.testing.assert_close(getattr(back, n), getattr(term, n))
        frame = Frame(0, 0.0, joints2d=det)
        torch.testing.assert_close(FrameEnergy(back, back.prepare(frame), sk)(th),
                                   FrameEnergy(term, term.prepare(frame), sk)(th))
        # another configured scale: the learned factors apply on top of it
        other = LearnedKeypointLikelihood(rig, sk, scale_px=8.0, weights=str(path)).double()
        torch.testing.assert_close(other.scale_px / 8.0, term.scale_px
                                   / torch.tensor([4.0, 5.0, 6.0], dtype=torch.float64))
        # a subset of the cameras (a held-out run) takes the scales of its cameras by name
        sub = LearnedKeypointLikelihood(rig.subset([2, 0]), sk, scale_px=[6.0, 4.0],
                                        weights=str(path)).double()
        torch.testing.assert_close(sub.scale_px, term.scale_px[[2, 0]])
        torch.testing.assert_close(sub.pixel_bias, term.pixel_bias[[2, 0]])

    def test_mismatched_files_are_refused(self, scene, tmp_path):
        sk, rig, th, det = scene
        path = LearnedKeypointLikelihood(rig, sk).save_weights(tmp_path / "k.pt")
        with pytest.raises(ArchitectureMismatchError, match="format: file 'body_25b', "
                                                            "config 'coco_17'"):
            LearnedKeypointLikelihood(rig, sk, keypoint_map="coco_17",
                                      keypoint_names=load_keypoint_map("body_25b")
                                      .format_keypoints, weights=str(path))
        with pytest.raises(ArchitectureMismatchError, match="calibration_knots"):
            LearnedKeypointLikelihood(rig, sk, calibration_knots=5, weights=str(path))
        with pytest.raises(ArchitectureMismatchError, match="robust"):
            LearnedKeypointLikelihood(rig, sk, robust="huber", weights=str(path))
        renamed = make_ring_rig(3, image_size=(640, 480))
        renamed.names = ["a", "ring1", "b"]
        with pytest.warns(UserWarning, match=r"no scale or bias for cameras \['a', 'b'\]"):
            partial = LearnedKeypointLikelihood(renamed, sk, weights=str(path))
        torch.testing.assert_close(partial.scale_px, torch.full((3,), 8.0))
        (tmp_path / "junk.pt").write_text("not weights")
        with pytest.raises(WeightsError, match="not a torchmocap weights file"):
            LearnedKeypointLikelihood(rig, sk, weights=str(tmp_path / "junk.pt"))
        with pytest.raises(FileNotFoundError, match="weights: no such file"):
            LearnedKeypointLikelihood(rig, sk, weights=str(tmp_path / "none.pt"))

    def test_bundled_weights_load(self, scene):
        """The shipped pose2sim_balancing parameters load by name onto that recording's
        cameras (any subset) and change the map's offsets by a few centimetres at most."""
        sk, rig, th, det = scene
        named = make_ring_rig(3, image_size=(640, 480))
        named.names = ["cam01", "cam03", "cam04"]
        term = LearnedKeypointLikelihood(named, sk, weights="bundled")
        change = (term.offsets - term.base_offsets).norm(dim=-1)
        assert 0.005 < float(change.max()) < 0.06
        assert term.weights_path.endswith("keypoints_pose2sim_balancing.pt")
        w = term.calibrated(torch.linspace(0, 1, 21))
        assert bool((w[1:] >= w[:-1]).all()) and not torch.equal(term.scale_px,
                                                                  torch.full((3,), 8.0))

    def test_bad_settings_are_named(self, scene):
        sk, rig, th, det = scene
        for kw, msg in ((dict(calibration_knots=0), "calibration_knots"),
                        (dict(calibration_knots=2.5), "calibration_knots"),
                        (dict(scale_px=-1.0), "scale_px"), (dict(weights=3), "weights")):
            with pytest.raises(ValueError, match=msg):
                LearnedKeypointLikelihood(rig, sk, **kw)

    def test_learn_makes_the_parameters_trainable(self, scene):
        sk, rig, th, det = scene
        frozen = LearnedKeypointLikelihood(rig, sk)
        assert not any(p.requires_grad for p in frozen.parameters())
        term = LearnedKeypointLikelihood(rig, sk, learn=True)
        assert {n for n, p in term.named_parameters() if p.requires_grad} == {
            "offsets", "log_scale_px", "log_keypoint_scale", "calibration", "pixel_bias"}

    def test_bias_shifts_the_expected_pixels(self, scene):
        """A bias of (1 %, -2 %) of the image moves every expected pixel of that camera by
        (6.4, -9.6) px on 640x480 images; a detection shifted alike scores as the unshifted."""
        sk, rig, th, det = scene
        term = LearnedKeypointLikelihood(rig, sk).double()
        x = term.keypoints(Poses(th, sk))
        plain = term.project(x)
        with torch.no_grad():
            term.pixel_bias[1] = torch.tensor([0.01, -0.02])
        shift = term.project(x) - plain
        torch.testing.assert_close(shift[0, 1], torch.tensor([6.4, -9.6], dtype=torch.float64)
                                   .expand_as(shift[0, 1]))
        assert float(shift[0, [0, 2]].abs().max()) == 0.0
        moved = det.clone()
        moved[1, :, :2] += torch.tensor([6.4, -9.6], dtype=det.dtype)
        hand = KeypointLikelihood(rig, sk).double()
        torch.testing.assert_close(
            FrameEnergy(term, term.prepare(Frame(0, 0.0, joints2d=moved)), sk)(th),
            FrameEnergy(hand, hand.prepare(Frame(0, 0.0, joints2d=det)), sk)(th))

    def test_fitted_map_carries_the_offsets(self, scene):
        sk, rig, th, det = scene
        term = LearnedKeypointLikelihood(rig, sk).double()
        _randomise(term, 4)
        kmap = term.fitted_map()
        kin = sk(th)
        torch.testing.assert_close(keypoint_positions(kin.positions, kin.rotations, kmap),
                                   term.keypoints(Poses(th, sk)))
