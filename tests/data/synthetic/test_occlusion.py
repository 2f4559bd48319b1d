"""Self-occlusion of joints (mesh z-buffer) and the detector's behaviour on hidden joints."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.data.synthetic import ScenarioError, load_scenario, synthesize
from torchmocap.data.synthetic.joints2d import synthesize_joints2d
from torchmocap.data.synthetic.occlusion import joint_occlusion
from torchmocap.data.synthetic.synthesis import body_surface
from torchmocap.io import bundled_clip_path, load_motion
from torchmocap.likelihoods.joints2d import predicted_hidden
from torchmocap.skeleton import human31


def _wall(y: float, size: float = 1.0):
    """A triangle in the plane ``y`` facing the ring rig's camera 0 at (0, -4, 2.5)."""
    return torch.tensor([[[-size, y, -size], [size, y, -size], [0.0, y, 2 * size]]])


@pytest.fixture(scope="module")
def rig():
    return make_ring_rig(1).float()


class TestJointOcclusion:
    def test_feature_other_parts_in_front_hide_own_parts_do_not(self, rig):
        f = torch.tensor([[0, 1, 2]])
        pos = torch.zeros(1, 3, 3)
        parents = [-1, 0, 1]
        hidden = joint_occlusion(pos, _wall(-1.0), f, torch.tensor([2]), parents, rig)[0, 0]
        assert hidden.tolist() == [True, False, False]  # 2 is joint 1's child, joint 2's own
        behind = joint_occlusion(pos, _wall(1.0), f, torch.tensor([2]), parents, rig)[0, 0]
        assert not bool(behind.any())

    def test_feature_margin(self, rig):
        f, part = torch.tensor([[0, 1, 2]]), torch.tensor([0])
        pos = torch.zeros(1, 2, 3)
        pos[0, 1, 1] = 0.04  # joint 1 ~4.5 cm behind the wall at y = 0; joint 0 on it
        parents = [-1, -1]
        w = _wall(0.0)
        tight = joint_occlusion(pos, w, f, part, parents, rig, margin=0.01)[0, 0]
        loose = joint_occlusion(pos, w, f, part, parents, rig, margin=0.2)[0, 0]
        assert tight.tolist() == [False, True] and loose.tolist() == [False, False]

    def test_feature_agrees_with_the_capsule_ray_test(self):
        """Independent implementations: the z-buffer of the meshed capsule body against the
        analytic line-of-sight test of the tracker's capsules, on random poses seen by four
        cameras (they differ only by tessellation, grazing rays and joints inside another
        capsule)."""
        sk = human31()
        g = torch.Generator().manual_seed(0)
        T = 24
        th = sk.zero_pose((T,))
        th[:, 6:] = 0.8 * torch.randn(T, sk.num_dofs - 6, generator=g, dtype=th.dtype)
        th = sk.clamp(th)
        th[:, 5] = 6.28 * torch.rand(T, generator=g, dtype=th.dtype)
        rig = make_ring_rig(4, image_size=(320, 240)).float()
        surf = body_surface(sk.float(), th.float(), "capsules")
        pos = sk(th).positions.float()
        mesh = joint_occlusion(pos, surf.vertices, surf.faces, surf.face_part, sk.parents, rig)
        caps = predicted_hidden(pos, torch.arange(sk.num_joints), CapsuleBody(sk).float(), rig)
        assert 0.05 < float(mesh.float().mean()) < 0.3  # not a vacuous comparison
        assert float((mesh == caps).float().mean()) > 0.93

    def test_exception(self, rig):
        f, part = torch.tensor([[0, 1, 2]]), torch.tensor([0])
        pos = torch.zeros(1, 2, 3)
        with pytest.raises(ValueError, match="positions"):
            joint_occlusion(pos[0], _wall(0.0), f, part, [-1, 0], rig)
        with pytest.raises(ValueError, match="vertices"):
            joint_occlusion(pos, _wall(0.0)[0], f, part, [-1, 0], rig)
        with pytest.raises(ValueError, match="face_part"):
            joint_occlusion(pos, _wall(0.0), f, torch.tensor([0, 1]), [-1, 0], rig)
        with pytest.raises(ValueError, match="face_part"):
            joint_occlusion(pos, _wall(0.0), f, torch.tensor([5]), [-1, 0], rig)
        with pytest.raises(ValueError, match="parents"):
            joint_occlusion(pos, _wall(0.0), f, part, [-1], rig)
        with pytest.raises(ValueError, match="margin"):
            joint_occlusion(pos, _wall(0.0), f, part, [-1, 0], rig, margin=-1.0)

    def test_feature_cameras_of_different_image_sizes(self):
        """A rig mixing 320x240 and 160x120 cameras answers, per camera, what a rig of that
        camera alone answers."""
        from torchmocap.cameras import CameraRig

        sk = human31()
        g = torch.Generator().manual_seed(1)
        th = sk.zero_pose((12,))
        th[:, 6:] = 0.8 * torch.randn(12, sk.num_dofs - 6, generator=g, dtype=th.dtype)
        th = sk.clamp(th)
        full = make_ring_rig(4, image_size=(320, 240)).float()
        half = full.scaled_images(0.5)
        pick = [full, half, full, half]
        mixed = CameraRig(torch.stack([r.K[c] for c, r in enumerate(pick)]), full.R, full.t,
                          torch.stack([r.image_size[c] for c, r in enumerate(pick)]))
        surf = body_surface(sk.float(), th.float(), "capsules")
        pos = sk(th).positions.float()
        args = (pos, surf.vertices, surf.faces, surf.face_part, sk.parents)
        got = joint_occlusion(*args, mixed)
        for c, r in enumerate(pick):
            alone = joint_occlusion(*args, r.subset([c]))[:, 0]
            assert torch.equal(got[:, c], alone), c
            assert bool(alone.any())  # not a vacuous comparison


class TestDetectorOnHiddenJoints:
    def _detect(self, occluded, **kw):
        rig = make_ring_rig(2, image_size=(320, 240)).float()
        pos = torch.zeros(400, 21, 3)
        pos[..., 2] = torch.linspace(0.1, 1.7, 21)
        return rig, synthesize_joints2d(pos, rig, torch.Generator().manual_seed(0),
                                        pixel_noise=1.0, miss_prob=0.05, outlier_prob=0.0,
                                        confidence=(0.6, 1.0), occluded=occluded, **kw)

    def test_feature_hidden_joints_are_missed_noisier_and_less_confident(self):
        occ = torch.zeros(400, 2, 21, dtype=torch.bool)
        occ[:, :, ::2] = True
        rig, det = self._detect(occ, occluded_miss_prob=0.5, occluded_pixel_noise=4.0,
                                occluded_confidence=(0.1, 0.5))
        pos = torch.zeros(400, 21, 3)
        pos[..., 2] = torch.linspace(0.1, 1.7, 21)
        pix = rig.project(pos)[0]
        conf = det[..., 2]
        seen = conf > 0
        h, v = seen & occ, seen & ~occ
        assert abs(float(1 - seen[occ].float().mean()) - 0.5) < 0.03  # miss rates
        assert abs(float(1 - seen[~occ].float().mean()) - 0.05) < 0.015
        assert float(conf[h].max()) <= 0.5 and float(conf[h].min()) >= 0.1
        assert float(conf[v].min()) >= 0.6
        err = (det[..., :2] - pix).norm(dim=-1)
        # Rayleigh means: sigma sqrt(pi / 2)
        assert abs(float(err[h].mean()) / 4.0 - 1.2533) < 0.05
        assert abs(float(err[v].mean()) / 1.0 - 1.2533) < 0.05

    def test_feature_nothing_hidden_is_the_plain_detector(self):
        _, a = self._detect(None)
        _, b = self._detect(torch.zeros(400, 2, 21, dtype=torch.bool))
        assert torch.equal(a, b)

    def test_exception(self):
        with pytest.raises(ValueError, match="occluded"):
            self._detect(torch.zeros(400, 2, 20, dtype=torch.bool))


class TestScenario:
    def test_feature_monocular_occlusion_extends_monocular(self):
        base, sc = load_scenario("monocular"), load_scenario("monocular_occlusion")
        assert sc.name == "monocular_occlusion" and sc.joints2d.occlusion
        assert not base.joints2d.occlusion
        assert sc.rig == base.rig and sc.image_size == base.image_size
        assert sc.joints2d.pixel_noise == base.joints2d.pixel_noise

    def test_feature_synthesis_hides_real_joints(self):
        clip = load_motion(bundled_clip_path()).resample(25)
        subject = fit_subject(clip.slice(0, 3))
        plain = synthesize(subject, "monocular", seed=0, frames=3)
        occ = synthesize(subject, "monocular_occlusion", seed=0, frames=3)
        frac = occ.meta.joints2d_occluded_fraction
        assert 0.0 < frac < 0.5 and plain.meta.joints2d_occluded_fraction is None
        low = (occ.joints2d[..., 2] > 0) & (occ.joints2d[..., 2] <= 0.5)
        assert bool(low.any())

    def test_exception(self, tmp_path):
        a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
        a.write_text(f"base: {b}\n")
        b.write_text(f"base: {a}\n")
        with pytest.raises(ScenarioError, match="extends itself"):
            load_scenario(str(a))
        with pytest.raises(ScenarioError, match="base"):
            load_scenario(str(_write(tmp_path / "c.yaml", "base: 3\n")))
        for key, bad in (("joints2d.occlusion_margin", -0.1), ("joints2d.occluded_miss_prob", 2),
                         ("joints2d.occluded_confidence", [0.5, 0.2]),
                         ("joints2d.occluded_pixel_noise", -1.0)):
            with pytest.raises(ScenarioError, match=key.split(".")[1]):
                load_scenario("monocular_occlusion", **{key: bad})


def _write(path, text):
    path.write_text(text)
    return path
