"""Scenarios (loading, overrides, rigs) and the corruptions: silhouette noise, holes, clutter,
shadows, dropped views, 2D-joint noise, colour images and illumination."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.subjects.mocap import fit_subject
from torchmocap.data.synthetic import ScenarioError, build_rig, load_scenario, synthesize
from torchmocap.data.synthetic.images import illumination_gain
from torchmocap.data.synthetic.joints2d import synthesize_joints2d
from torchmocap.data.synthetic.scenario import known_scenarios
from torchmocap.data.synthetic.silhouettes import (
    add_boundary_noise,
    add_clutter,
    dilate,
    drop_views,
    punch_holes,
    shadow_points,
)
from torchmocap.io import bundled_clip_path, load_motion

SMALL = {"image_size": [160, 120]}


@pytest.fixture(scope="module")
def subject():
    return fit_subject(load_motion(bundled_clip_path()).resample(25).slice(0, 3))


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _disc_masks(B: int = 6, H: int = 60, W: int = 80, r: float = 15.0) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    m = ((xs - 40) ** 2 + (ys - 30) ** 2) <= r * r
    return m.expand(B, H, W).clone()


class TestScenario:
    def test_bundled_compose(self):
        assert {"clean", "studio", "outdoor"} <= set(known_scenarios())
        for name in known_scenarios():
            sc = load_scenario(name)
            assert sc.name == name and sc.image_size == [320, 240] and sc.fps == 25.0
            assert sc.body == "skinned"
            rig = build_rig(sc.rig, sc.image_size)
            assert rig.num_cameras == (1 if name in ("monocular", "monocular_occlusion", "stereo")
                                       else 4)
        clean, studio, outdoor = (load_scenario(n) for n in ("clean", "studio", "outdoor"))
        assert clean.imu.noise == "none" and clean.silhouettes.holes == 0
        assert studio.imu.kappa == 1000.0 and studio.imu.misalignment_deg == 2.0
        assert outdoor.silhouettes.shadow and outdoor.silhouettes.clutter > 0
        assert outdoor.silhouettes.drop_view > 0 and outdoor.images.illumination_change > 0
        lo, hi = outdoor.imu.misalignment_deg
        assert 5 <= lo <= hi <= 10 and 0 < outdoor.imu.desync_frames < 1
        assert outdoor.imu.drift_deg_per_min > 0 and outdoor.imu.drop_prob > 0

    def test_overrides(self, tmp_path):
        sc = load_scenario("outdoor", fps=30, imu={"kappa": 300}, **{"silhouettes.holes": 0})
        assert sc.fps == 30.0 and sc.imu.kappa == 300.0 and sc.silhouettes.holes == 0.0
        assert sc.imu.drift_deg_per_min == 20.0  # untouched keys keep the file's values
        p = tmp_path / "mine.yaml"
        p.write_text("rig: ceiling4\nbody: capsules\nimu:\n  noise: tangent\n")
        mine = load_scenario(p)
        assert mine.name == "mine" and mine.body == "capsules" and mine.imu.noise == "tangent"
        assert load_scenario(mine, fps=50).fps == 50.0

    def test_rig_resolution(self):
        rig = build_rig("ring4", [640, 480])
        assert rig.image_size[0].tolist() == [640, 480]
        base = build_rig("ring4")
        # same cameras, intrinsics scaled with the image
        assert torch.allclose(rig.K[:, 0, 0], 2 * base.K[:, 0, 0])
        assert torch.allclose(rig.R, base.R)
        inline = build_rig({"_target_": "torchmocap.cameras.make_ring_rig", "num": 3},
                           [160, 120])
        assert inline.num_cameras == 3 and inline.image_size[0].tolist() == [160, 120]
        from torchmocap.cameras import rig_to_dict

        calib = build_rig(rig_to_dict(base), [160, 120])  # calibration dict, rescaled
        assert torch.allclose(calib.K[:, 0, 0], base.K[:, 0, 0] / 2)
        with pytest.raises(ScenarioError, match="aspect"):
            build_rig(rig_to_dict(base), [100, 100])
        with pytest.raises(ScenarioError, match="unknown rig"):
            build_rig("ring99")

    def test_exception(self, tmp_path):
        with pytest.raises(ScenarioError, match="unknown scenario 'nope'"):
            load_scenario("nope")
        with pytest.raises(ScenarioError, match="imu.kapa"):
            load_scenario("studio", imu={"kapa": 3})
        with pytest.raises(ScenarioError, match="fps"):
            load_scenario("studio", fps="fast")
        with pytest.raises(ScenarioError, match="imu.noise"):
            load_scenario("studio", imu={"noise": "laplace"})
        with pytest.raises(ScenarioError, match="silhouettes.drop_view"):
            load_scenario("studio", silhouettes={"drop_view": 2})
        for bad in ({"dof": 0}, {"dof": float("inf")}, {"heading_walk_deg": -1.0}):
            with pytest.raises(ScenarioError, match=f"imu.{next(iter(bad))}"):
                load_scenario("studio", imu=bad)
        with pytest.raises(ScenarioError, match="imu.misalignment_deg"):
            load_scenario("studio", imu={"misalignment_deg": [10, 5]})
        with pytest.raises(ScenarioError, match="light_direction"):
            load_scenario("studio", light_direction=[0, 0, 1])
        with pytest.raises(ScenarioError, match="imu.tracking"):
            load_scenario("studio", imu={"tracking": ["antenna"]})
        with pytest.raises(ScenarioError, match="file not found"):
            load_scenario(tmp_path / "missing.yaml")


class TestSilhouetteCorruptions:
    def test_dilate_matches_max_pool(self):
        m = torch.rand(5, 40, 50, generator=_gen()) < 0.05
        for w in (1, 2, 3):
            ref = torch.nn.functional.max_pool2d(m.float()[:, None], 2 * w + 1, 1, w)[:, 0] > 0
            assert torch.equal(dilate(m, w), ref)

    def test_boundary_noise_stays_at_the_contour(self):
        m = _disc_masks()
        n = add_boundary_noise(m, 0.5, 1, _gen())
        diff = n ^ m
        assert int(diff.sum()) > 50
        ys, xs = diff.nonzero()[:, 1], diff.nonzero()[:, 2]
        rad = ((xs - 40.0) ** 2 + (ys - 30.0) ** 2).sqrt()
        assert bool(((rad > 15 - 2.5) & (rad < 15 + 2.5)).all())
        assert torch.equal(add_boundary_noise(m, 0.0, 1, _gen()), m)

    def test_holes_inside_the_foreground(self):
        m = _disc_masks()
        h = punch_holes(m.clone(), 3.0, (2.0, 3.0), _gen())
        assert not bool((h & ~m).any())  # holes only remove
        lost = (m & ~h).sum((-1, -2))
        assert int(lost.sum()) > 0
        empty = punch_holes(torch.zeros(3, 10, 10, dtype=torch.bool), 5.0, (1.0, 2.0), _gen())
        assert not bool(empty.any())

    def test_clutter_adds_blobs(self):
        m = torch.zeros(200, 60, 80, dtype=torch.bool)
        c = add_clutter(m.clone(), 1.5, (3.0, 6.0), _gen())
        per = c.flatten(1).any(-1).float().mean()
        # P(at least one blob) = 1 - exp(-1.5) ≈ 0.78 (blobs are inside the image)
        assert 0.68 < float(per) < 0.88

    def test_drop_views(self):
        m = _disc_masks(B=400)
        d, flag = drop_views(m, 0.25, _gen())
        assert 0.18 < float(flag.float().mean()) < 0.32
        assert not bool(d[flag].any()) and torch.equal(d[~flag], m[~flag])

    def test_shadow_points_on_the_floor(self):
        p = torch.tensor([[0.0, 0, 1.0], [1.0, 2.0, 0.0]])
        s = shadow_points(p, torch.tensor([0.5, 0.0, -1.0]))
        assert torch.allclose(s, torch.tensor([[0.5, 0, 0.0], [1.0, 2.0, 0.0]]))
        with pytest.raises(ValueError, match="light_direction"):
            shadow_points(p, torch.tensor([0.0, 0.0, 1.0]))

    def test_outdoor_shadow_attached_to_feet(self, subject):
        base = dict(SMALL, images={"enabled": False}, depth={"enabled": False},
                    imu={"enabled": False}, joints2d={"enabled": False})
        clean = synthesize(subject, load_scenario("clean", **base), seed=0, frames=2)
        shadow = synthesize(subject, load_scenario("clean", **base,
                                                   silhouettes={"shadow": True}), seed=0,
                            frames=2)
        extra = shadow.silhouettes & ~clean.silhouettes
        assert not bool((clean.silhouettes & ~shadow.silhouettes).any())
        assert int(extra.sum()) > 20
        # the shadow region touches the body (attached at the stance foot) in most views (a
        # swing foot's shadow may be the only visible part when the body hides the rest)
        dil = torch.nn.functional.max_pool2d(clean.silhouettes.flatten(0, 1).float()[:, None], 3,
                                             1, 1)[:, 0] > 0
        touch = (extra.flatten(0, 1) & dil).flatten(1).any(-1)
        has = extra.flatten(0, 1).flatten(1).any(-1)
        assert float(touch[has].float().mean()) >= 0.75
        # and it lies below the hips in the image (towards the floor)
        pix, _, _ = clean.rig.project(clean.ground_truth.positions.float())
        hip_v = pix[..., clean.ground_truth.joint_names.index("pelvis"), 1]  # (T, C)
        rows = extra.nonzero()
        assert float((rows[:, 2].float() > hip_v[rows[:, 0], rows[:, 1]]).float().mean()) > 0.95

    def test_outdoor_has_every_corruption(self, subject):
        clean = synthesize(subject, load_scenario("clean", **SMALL), seed=2, frames=3)
        out = synthesize(subject, load_scenario("outdoor", **SMALL, silhouettes={
            "drop_view": 0.3}), seed=2, frames=3)
        assert out.view_dropped.any() and not clean.view_dropped.any()
        d = out.view_dropped
        assert not bool(out.silhouettes[d].any()) and not bool(out.images[d].any())
        assert bool((out.joints2d[..., 2][d] == 0).all())
        keep = ~d
        a, b = clean.silhouettes[keep], out.silhouettes[keep]
        assert int((b & ~a).sum()) > 0 and int((a & ~b).sum()) > 0  # added and removed pixels
        iou = (a & b).sum() / (a | b).sum()
        assert 0.3 < float(iou) < 0.95


class TestJoints2D:
    def test_noise_outliers_misses(self):
        rig = build_rig("ring4", [320, 240])
        g = _gen(0)
        pos = torch.randn(300, 21, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor(
            [0, 0, 1.0], dtype=torch.float64)
        exact = synthesize_joints2d(pos, rig, _gen(1))
        assert bool((exact[..., 2] == 1).all())
        pix = rig.project(pos)[0]
        assert torch.allclose(exact[..., :2], pix)
        noisy = synthesize_joints2d(pos, rig, _gen(1), pixel_noise=2.0, outlier_prob=0.1,
                                    miss_prob=0.2, confidence=(0.6, 1.0))
        conf = noisy[..., 2]
        miss = conf == 0
        assert 0.17 < float(miss.float().mean()) < 0.23
        assert bool((noisy[miss][:, :2] == 0).all())
        err = (noisy[..., :2] - pix).norm(dim=-1)
        good = conf >= 0.6
        outl = (conf > 0) & (conf < 0.6)
        assert 0.06 < float(outl.float().mean()) < 0.1  # 0.1 · 0.8
        # Rayleigh(σ=2): median = σ √(2 ln 2) ≈ 2.35 px
        assert abs(float(err[good].median()) - 2.355) < 0.1
        assert float(err[outl].median()) > 20
        drop = torch.zeros(300, 4, dtype=torch.bool)
        drop[:, 1] = True
        dd = synthesize_joints2d(pos, rig, _gen(1), dropped=drop)
        assert bool((dd[:, 1] == 0).all()) and bool((dd[:, 0, :, 2] == 1).all())

    def test_out_of_view_joints_have_zero_confidence(self):
        rig = build_rig("ring4", [320, 240])
        pos = torch.tensor([[[0.0, 0, 1.0], [0.0, 0, 50.0]]], dtype=torch.float64)  # overhead
        j = synthesize_joints2d(pos, rig, _gen())
        assert bool((j[0, :, 0, 2] == 1).all()) and bool((j[0, :, 1, 2] == 0).all())


class TestImages:
    def test_illumination_gain(self):
        g = illumination_gain(100, 25.0, 0.3, 2.0, _gen())
        assert abs(float(g.max()) - 1.3) < 0.01 and abs(float(g.min()) - 0.7) < 0.01
        assert torch.equal(illumination_gain(5, 25.0, 0.0, 2.0, _gen()), torch.ones(5))

    def test_images_follow_illumination_and_parts(self, subject):
        sc = load_scenario("clean", **SMALL, images={"illumination_change": 0.3,
                                                     "illumination_period_s": 0.16},
                           depth={"enabled": False}, imu={"enabled": False})
        seq = synthesize(subject, sc, seed=0, frames=3)
        img = seq.images.float()
        gain = illumination_gain(3, seq.fps, 0.3, 0.16, __import__(
            "torchmocap.data.synthetic.synthesis", fromlist=["x"]).subgenerator(0, "images"))
        mean = img.mean((1, 2, 3, 4))
        ratio = mean / mean[0]
        assert torch.allclose(ratio, gain / gain[0], rtol=0.03)
        # body pixels differ from the background and carry several part colours
        body = seq.silhouettes[0, 0]
        cols = seq.images[0, 0][body].float()
        assert cols.shape[0] > 100 and float(cols.std(0).mean()) > 10
        bg = seq.images[0, 0][~body].float()
        assert float((cols.mean(0) - bg.mean(0)).abs().max()) > 10
        # the background is textured (not flat), views differ
        assert float(bg.std(0).mean()) > 5
        assert not torch.equal(seq.images[0, 0], seq.images[0, 1])
