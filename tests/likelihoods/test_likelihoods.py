"""Silhouette, appearance and orientation likelihoods."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.geometry import matrix_to_quaternion, so3_exp
from torchmocap.ik import SensorManifold
from torchmocap.likelihoods import Poses
from torchmocap.likelihoods.appearance import AppearanceLikelihood
from torchmocap.likelihoods.orientation import OrientationLikelihood, orientation_energy
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    prepare_silhouettes,
    silhouette_energy,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from oracle import appearance_loop, capsule_masks, surface_point  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_elbow_flex")] = 1.2
    th[sk.dof_index("r_hip_flex")] = 0.6
    th[sk.dof_index("l_shoulder_abd")] = 0.5
    masks = capsule_masks(body, rig, th)
    return sk, body, rig, th, masks


def test_hard_silhouette_zero_at_truth_and_grows(scene):
    sk, body, rig, th, masks = scene
    lik = SilhouetteLikelihood(body, rig, fg_samples=200)
    obs = lik.prepare(Frame(index=0, time=0.0, silhouettes=masks))
    assert lik.energy(Poses(th[None], sk), obs).item() == pytest.approx(0.0, abs=1e-3)
    g = torch.Generator().manual_seed(0)
    energies = []
    for scale in (0.05, 0.15, 0.4):
        pert = th + scale * torch.randn(64, sk.num_dofs, generator=g)
        pert[:, :3] = th[:3]
        energies.append(lik.energy(Poses(pert, sk), obs).mean().item())
    assert 0 < energies[0] < energies[1] < energies[2] <= 1
    assert torch.equal(lik(Poses(th[None], sk), obs), lik.energy(Poses(th[None], sk), obs))
    assert lik.requires == ("silhouettes",)
    # a dropped view flagged in the frame is excluded by prepare()
    bad = masks.clone()
    bad[1] = torch.roll(bad[1], 40, dims=1)
    dropped = lik.prepare(Frame(index=0, time=0.0, silhouettes=bad,
                                view_dropped=torch.tensor([False, True, False, False])))
    assert lik.energy(Poses(th[None], sk), dropped).item() == pytest.approx(0.0, abs=1e-3)


def test_both_directions_count(scene):
    sk, body, rig, th, masks = scene
    # an empty model region (mask twice as wide) penalises image->model; a shifted body both
    wide = masks | torch.roll(masks, 15, dims=2)
    e_wide = silhouette_energy(body.endpoints(sk(th[None])), body.radii, rig,
                               prepare_silhouettes(wide, 200))
    assert e_wide.item() > 0.05
    shifted = th.clone()
    shifted[:2] += 1.5
    e_far = silhouette_energy(body.endpoints(sk(shifted[None])), body.radii, rig,
                              prepare_silhouettes(masks, 200))
    assert e_far.item() > 0.8  # little overlap left in any view


def test_dropped_view_ignored(scene):
    sk, body, rig, th, masks = scene
    bad = masks.clone()
    bad[2] = torch.roll(bad[2], 40, dims=1)
    valid = torch.tensor([True, True, False, True])
    e = silhouette_energy(body.endpoints(sk(th[None])), body.radii, rig,
                          prepare_silhouettes(bad, 200, view_valid=valid))
    assert e.item() == pytest.approx(0.0, abs=1e-3)


def test_smooth_silhouette_differentiable_and_descends(scene):
    sk, body, rig, th, masks = scene
    lik = SilhouetteLikelihood(body, rig, smooth=True, fg_samples=200)
    assert lik.blur == 1.5
    obs = lik.prepare(Frame(index=0, time=0.0, silhouettes=masks))
    x = th.clone()
    x[sk.dof_index("l_elbow_flex")] = 0.6
    x = x[None].requires_grad_(True)

    def V(t):
        return lik.energy(Poses(t, sk), obs)

    e = V(x)
    e.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # finite differences agree with autograd along the gradient direction
    d = -x.grad / x.grad.norm()
    h = 1e-3
    fd = (V(x.detach() + h * d) - V(x.detach() - h * d)) / (2 * h)
    assert fd.item() == pytest.approx(-x.grad.norm().item(), rel=0.1)
    assert fd.item() < 0  # a descent direction


def test_orientation_energy_closed_form():
    R = so3_exp(torch.tensor([[0.0, 0.0, 0.3], [0.1, 0.0, 0.0]]))
    measured = torch.eye(3).expand(2, 3, 3)
    offsets = torch.eye(3).expand(2, 3, 3)
    v = orientation_energy(R[None], offsets, measured)
    assert v.item() == pytest.approx((0.3**2 + 0.1**2) / 2, rel=1e-5)
    # the offset is applied on the right: R_TB R_BS vs R_TS
    off = so3_exp(torch.tensor([[0.0, 0.2, 0.0], [0.0, 0.0, 0.0]]))
    v = orientation_energy(torch.eye(3).expand(1, 2, 3, 3), off, off)
    assert v.item() == pytest.approx(0.0, abs=1e-10)
    with pytest.raises(ValueError, match="measured"):
        orientation_energy(R[None], offsets, torch.eye(3).expand(3, 3, 3))


def test_orientation_likelihood_module():
    sk = human31()
    m = SensorManifold(sk, {"a": "l_elbow", "b": "r_knee"})
    lik = OrientationLikelihood(m)
    th = sk.zero_pose((2,))
    th[1, sk.dof_index("l_elbow_flex")] = 0.5
    meas = sk(th[0]).rotations[[sk.joint_index("l_elbow"), sk.joint_index("r_knee")]]
    frame = Frame(index=0, time=0.0, imu=matrix_to_quaternion(meas))
    e = lik.energy(Poses(th, sk), lik.prepare(frame))
    assert e[0].item() == pytest.approx(0.0, abs=1e-6)
    assert e[1].item() == pytest.approx(0.5**2 / 2, rel=1e-4)
    # calibrated offsets R_SB are applied: sensors rotated on the bone read the same energy
    off = so3_exp(torch.tensor([[0.3, 0.0, 0.1], [0.0, -0.2, 0.0]]))
    m.calibrate(th[0], meas @ off.transpose(-1, -2))  # R_TS = R_TB R_SB^T
    frame = Frame(index=0, time=0.0, imu=matrix_to_quaternion(meas @ off.transpose(-1, -2)))
    e2 = lik.energy(Poses(th, sk), lik.prepare(frame))
    assert torch.allclose(e2, e, atol=1e-5)
    lin = OrientationLikelihood(m, power=1)
    assert lin.energy(Poses(th, sk), lin.prepare(frame))[1].item() == pytest.approx(
        0.5 / 2, rel=1e-4)
    assert lik.requires == ("imu",)
    with pytest.raises(ValueError, match="sensors"):
        lik.prepare(Frame(index=0, time=0.0, imu=torch.zeros(3, 4)))


def test_appearance_prefers_the_true_pose(scene):
    sk, body, rig, th, masks = scene
    # colour images: body parts coloured by their x coordinate sign, background striped
    C, H, W = masks.shape
    imgs = torch.zeros(C, H, W, 3, dtype=torch.uint8)
    stripes = ((torch.arange(W) // 8) % 2 * 200).to(torch.uint8)
    imgs[..., 1] = stripes
    imgs[..., 0] = torch.where(masks, torch.tensor(230, dtype=torch.uint8),
                               torch.tensor(0, dtype=torch.uint8))
    imgs[..., 1] = torch.where(masks, torch.tensor(40, dtype=torch.uint8), imgs[..., 1])
    lik = AppearanceLikelihood(body, rig, axial=4, around=6)
    obs = lik.prepare(Frame(index=0, time=0.0, images=imgs))
    e_true = lik.energy(Poses(th[None], sk), obs).item()
    far = th.clone()
    far[:2] += torch.tensor([0.3, -0.2])
    e_far = lik.energy(Poses(far[None], sk), obs).item()
    assert e_true < 0.02 < e_far
    assert lik.requires == ("images",)
    with pytest.raises(ValueError, match="images"):
        lik.prepare(Frame(index=0, time=0.0, images=imgs[..., 0]))


def test_prepare_exceptions():
    with pytest.raises(ValueError, match="masks"):
        prepare_silhouettes(torch.zeros(4, 4))
    obs = prepare_silhouettes(torch.zeros(2, 5, 5))
    assert not obs.view_valid.any()


def test_gradient_of_hard_energy_not_needed_but_float64_ok(scene):
    sk, body, rig, th, masks = scene
    obs = prepare_silhouettes(masks, 100, dtype=torch.float64)
    e = silhouette_energy(body.endpoints(sk.double()(th.double()[None])), body.radii,
                          rig.double(), obs)
    sk.float()
    rig.float()
    assert e.dtype == torch.float64 and math.isfinite(e.item())


def _stadium_oracle(rig, endpoints, radii, W, H):
    """Per-pixel loop: inside iff within r(t) of the projected axis segment (float64 numpy)."""
    import numpy as np

    pix, depth, _ = rig.double().project(endpoints.double().reshape(-1, 3))
    f = 0.5 * (rig.K[0, 0, 0] + rig.K[0, 1, 1]).item()
    out = np.zeros((H, W), dtype=bool)
    ys, xs = np.mgrid[0:H, 0:W]
    q = np.stack([xs, ys], -1).astype(np.float64)  # pixel centres at integer coordinates
    for b in range(endpoints.shape[0]):
        z = depth[0, 2 * b:2 * b + 2].numpy()
        if (z <= 1e-3).any():
            continue  # behind the camera: covers nothing
        a, e = pix[0, 2 * b].numpy(), pix[0, 2 * b + 1].numpy()
        r0, r1 = f * radii[b].item() / z[0], f * radii[b].item() / z[1]
        d = e - a
        t = np.clip(((q - a) @ d) / max(d @ d, 1e-12), 0, 1)
        dist = np.linalg.norm(q - (a + t[..., None] * d), axis=-1)
        out |= dist < r0 + t * (r1 - r0)
    return out


def test_stadium_coverage_matches_a_per_pixel_oracle():
    from torchmocap.cameras import CameraRig
    from torchmocap.likelihoods.silhouette import _coverage_margin, _stadiums

    W, H = 80, 60
    K = torch.tensor([[[90.0, 0, 40], [0, 90, 30], [0, 0, 1]]], dtype=torch.float64)
    rig = CameraRig(K, torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3,
                                                                            dtype=torch.float64),
                    (W, H))
    ep = torch.tensor([[[-0.3, -0.1, 2.0], [0.25, 0.15, 2.5]],   # tapered, oblique
                       [[0.1, 0.3, 1.5], [0.1, 0.3, 1.5]],       # point-like: a disc
                       [[0.0, 0.0, -2.0], [0.3, 0.0, -2.0]],     # behind the camera
                       [[0.5, -0.2, 3.0], [0.2, -0.5, 0.5]]],    # steep in depth
                      dtype=torch.float64)
    radii = torch.tensor([0.08, 0.1, 0.5, 0.05], dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    q = torch.stack([xs, ys], -1).reshape(1, -1, 2).double()
    for dt in (torch.float64, torch.float32):
        st = _stadiums(ep[None].to(dt), radii.to(dt), rig.to(dt))
        hard = (_coverage_margin(q.to(dt), st, smooth=False)[0, :, 0] > 0).reshape(H, W)
        smooth = (_coverage_margin(q.to(dt), st, smooth=True)[0, :, 0] > 0).reshape(H, W)
        oracle = torch.from_numpy(_stadium_oracle(rig.double(), ep, radii.double(), W, H))
        assert oracle.sum() > 300  # the test scene covers a good part of the image
        assert (hard != oracle).sum() <= 2 and (smooth != oracle).sum() <= 2
    rig.double()


def test_silhouette_energy_terms_closed_form():
    """One axis-aligned capsule against a hand-made mask: both terms have known values."""
    from torchmocap.cameras import CameraRig

    W, H = 100, 60
    K = torch.tensor([[[100.0, 0, 50], [0, 100, 30], [0, 0, 1]]])
    rig = CameraRig(K, torch.eye(3)[None], torch.zeros(1, 3), (W, H))
    # axis from pixel (30, 30) to (70, 30) at depth 2, radius 10 px (0.2 m * 100 / 2)
    ep = torch.tensor([[[[-0.4, 0.0, 2.0], [0.4, 0.0, 2.0]]]])
    radii = torch.tensor([0.2])
    model = torch.zeros(1, H, W, dtype=torch.bool)
    ys, xs = torch.meshgrid(torch.arange(H) * 1.0, torch.arange(W) * 1.0, indexing="ij")
    d = torch.where(xs < 30, torch.hypot(xs - 30, ys - 30),
                    torch.where(xs > 70, torch.hypot(xs - 70, ys - 30), (ys - 30).abs()))
    model[0] = d < 10
    e_exact = silhouette_energy(ep, radii, rig, prepare_silhouettes(model, 400))
    assert e_exact.item() == pytest.approx(0.0, abs=0.02)
    # keep only the left half of the mask: half the model lies on background (m2i = 1/2;
    # a dense axis sampling resolves it) and all remaining foreground is covered (i2m = 0)
    half = model.clone()
    half[0, :, 50:] = False
    e_half = silhouette_energy(ep, radii, rig, prepare_silhouettes(half, 400), axis_samples=41)
    assert e_half.item() == pytest.approx(0.25, abs=0.01)
    # with the default 5 axis samples, 2 of 5 sample columns (x = 30, 40 | 50, 60, 70) are on
    # the foreground: m2i = 3/5
    e_half5 = silhouette_energy(ep, radii, rig, prepare_silhouettes(half, 400))
    assert e_half5.item() == pytest.approx(0.3, abs=1e-6)
    # extra foreground the model does not cover: i2m = uncovered fraction, m2i = 0
    extra = model.clone()
    extra[0, 2:18, 2:98] = True
    frac_uncovered = int((extra & ~model).sum()) / int(extra.sum())
    e_extra = silhouette_energy(ep, radii, rig, prepare_silhouettes(extra, 600))
    assert 0.2 < frac_uncovered < 0.8
    assert e_extra.item() == pytest.approx(0.5 * frac_uncovered, abs=0.02)


def test_appearance_energy_matches_a_loop_oracle(scene):
    from torchmocap.likelihoods.appearance import (
        appearance_energy,
        body_surface_pattern,
        prepare_images,
    )

    sk, body, rig, th, _ = scene
    g = torch.Generator().manual_seed(3)
    C, (W, H) = rig.num_cameras, rig.image_size[0].tolist()
    imgs = torch.randint(0, 256, (C, H, W, 3), generator=g, dtype=torch.uint8)
    poses = th + 0.1 * torch.randn(3, sk.num_dofs, generator=g)
    pattern = body_surface_pattern(body, 2, 3)
    kin = sk(poses)
    got = appearance_energy(kin, body, pattern, rig, imgs)
    torch.testing.assert_close(appearance_energy(kin, body, pattern, rig, prepare_images(imgs)),
                               got)
    view_valid = torch.tensor([True, False, True, True])
    got_vv = appearance_energy(kin, body, pattern, rig, imgs, view_valid)
    for p in range(3):
        for vv, out in ((None, got), (view_valid, got_vv)):
            want, counted = appearance_loop(kin, body, pattern, rig, imgs, p, vv)
            assert counted > 10
            assert out[p].item() == pytest.approx(want, abs=1e-5)


def test_appearance_pattern_layout_checked(scene):
    from torchmocap.likelihoods.appearance import appearance_energy, body_surface_pattern

    sk, body, rig, th, _ = scene
    pattern = body_surface_pattern(body, 2, 2)
    shuffled = {k: v.flip(0) for k, v in pattern.items()}
    imgs = torch.zeros(rig.num_cameras, 240, 320, 3)
    with pytest.raises(ValueError, match="bone-major"):
        appearance_energy(sk(th[None]), body, shuffled, rig, imgs)
    with pytest.raises(ValueError, match="axial"):
        body_surface_pattern(body, 0, 2)


def test_capsule_model_matches_the_rasterised_capsule_body():
    """The likelihood's stadium model and the synthesis rasteriser share the pixel convention
    (pixel x covers [x - 0.5, x + 0.5)): observations rendered from the tracker's own capsule
    body agree with its stadium silhouettes (a half-pixel shift drops the IoU to ~0.89)."""
    from torchmocap.data.subjects.mocap import fit_subject
    from torchmocap.data.synthetic import load_scenario, synthesize
    from torchmocap.io import bundled_clip_path, load_motion
    from torchmocap.likelihoods.silhouette import render_capsule_silhouettes, silhouette_iou

    clip = load_motion(bundled_clip_path()).resample(25).slice(0, 1)
    sc = load_scenario("clean", body="capsules", **{"images.enabled": False,
                                                     "depth.enabled": False,
                                                     "joints2d.enabled": False})
    seq = synthesize(fit_subject(clip), sc, seed=0)
    gt = seq.ground_truth
    sk = gt.build_skeleton().double()
    body = CapsuleBody(sk).double()
    rig = seq.rig.double()
    masks = seq.frame(0).silhouettes
    model = render_capsule_silhouettes(body, rig, gt.theta[0].double())
    assert float(silhouette_iou(model, masks).min()) > 0.97
    obs = prepare_silhouettes(masks, 400, dtype=torch.float64)
    v = silhouette_energy(body.endpoints(sk(gt.theta[:1].double())), body.radii, rig, obs)
    assert v.item() < 0.005
    # the same pose shifted by one pixel's worth (~1 cm) sideways is clearly worse
    shifted = gt.theta[:1].double().clone()
    shifted[0, 0] += 0.01
    v1 = silhouette_energy(body.endpoints(sk(shifted)), body.radii, rig, obs)
    assert v1.item() > v.item() + 0.005


def test_orientation_energy_linear_and_squared():
    R = so3_exp(torch.tensor([[0.0, 0.0, 0.3], [0.1, 0.0, 0.0]], dtype=torch.float64))
    eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    lin = orientation_energy(R[None], eye, eye, power=1)
    assert lin.item() == pytest.approx((0.3 + 0.1) / 2, rel=1e-12)
    sq = orientation_energy(R[None], eye, eye)
    assert sq.item() == pytest.approx((0.09 + 0.01) / 2, rel=1e-12)
    valid = torch.tensor([True, False])
    assert orientation_energy(R[None], eye, eye, valid, power=1).item() == pytest.approx(0.3)
    # finite gradient of the linear cost at zero error (the atan2 geodesic angle)
    x = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    orientation_energy(so3_exp(x)[None], eye[:1], eye[:1], power=1).sum().backward()
    assert torch.isfinite(x.grad).all()
    with pytest.raises(ValueError, match="power"):
        orientation_energy(R[None], eye, eye, power=3)
    with pytest.raises(ValueError, match="power"):
        OrientationLikelihood(SensorManifold(human31()), power=0)


class TestMaskContract:
    """``prepare_silhouettes`` reads bool masks, any numeric dtype holding exactly {0, 1}, and
    uint8 holding exactly {0, 255}; everything else is a ValueError naming ``masks``."""

    @staticmethod
    def _ref():
        m = torch.zeros(2, 6, 7, dtype=torch.bool)
        m[0, 1:4, 2:5] = True
        m[1, 2:6, 0:3] = True
        return m

    @pytest.mark.parametrize("form", ["bool", "uint8_01", "uint8_255", "int64_01", "f32_01",
                                      "f64_01", "f16_01"])
    def test_feature_accepted_forms_agree(self, form):
        m = self._ref()
        x = {"bool": m, "uint8_01": m.to(torch.uint8), "uint8_255": m.to(torch.uint8) * 255,
             "int64_01": m.long(), "f32_01": m.float(), "f64_01": m.double(),
             "f16_01": m.half()}[form]
        ref = prepare_silhouettes(m, 10, dtype=torch.float64)
        obs = prepare_silhouettes(x, 10, dtype=torch.float64)
        assert torch.equal(obs.masks, ref.masks) and torch.equal(obs.fg_pixels, ref.fg_pixels)
        assert torch.equal(obs.blurred, ref.blurred)

    def test_feature_all_background_and_all_foreground(self):
        for v in (0, 1):
            for dt in (torch.uint8, torch.float32, torch.int32):
                obs = prepare_silhouettes(torch.full((1, 3, 3), v, dtype=dt), 4)
                assert float(obs.masks.sum()) == 9 * v
        obs = prepare_silhouettes(torch.full((1, 3, 3), 255, dtype=torch.uint8), 4)
        assert float(obs.masks.sum()) == 9

    @pytest.mark.parametrize("bad, shown", [
        (1.196, "1.196"), (2.0, "2"), (1.0001, "1.0001"), (0.5, "0.5"), (-1.0, "-1"),
        (float("nan"), "nan"), (float("inf"), "inf"), (float("-inf"), "-inf"),
        (255.0, "255"),  # 0/255 is a uint8 convention only
    ])
    def test_exception_values(self, bad, shown):
        m = self._ref().float()
        m[0, 0, 0] = bad
        with pytest.raises(ValueError, match=r"masks: expected .*found values \{.*") as e:
            prepare_silhouettes(m)
        assert shown in str(e.value)

    @pytest.mark.parametrize("dtype", [torch.uint8, torch.int16, torch.int64])
    def test_exception_integer_values(self, dtype):
        m = self._ref().to(dtype)
        m[0, 0, 0] = 2
        with pytest.raises(ValueError, match=r"masks: .*found values \{0, 1, 2\}"):
            prepare_silhouettes(m)
        if dtype != torch.uint8:  # 255 means foreground only in uint8 masks
            with pytest.raises(ValueError, match="masks"):
                prepare_silhouettes(self._ref().to(dtype) * 255)
        with pytest.raises(ValueError, match=r"masks: .*found values \{0, 1, 255\}"):
            m = self._ref().to(torch.uint8) * 255
            m[0, 0, 0] = 1
            prepare_silhouettes(m)

    def test_exception_complex(self):
        with pytest.raises(ValueError, match="masks"):
            prepare_silhouettes(self._ref().to(torch.complex64))


# ------------------------------------------------------------------------- gradient checks
@pytest.fixture(scope="module")
def tiny_scene():
    """float64 human31 capsules in a 2-camera 64x48 rig, masks of a nearby pose."""
    sk = human31().double()
    body = CapsuleBody(sk).double()
    rig = make_ring_rig(2, image_size=(64, 48)).double()
    th = sk.zero_pose(dtype=torch.float64)
    th[sk.dof_index("l_elbow_flex")] = 0.9
    th[sk.dof_index("r_hip_flex")] = 0.4
    masks = capsule_masks(body, rig, th)
    return sk, body, rig, th, masks


def _dofs(sk, names):
    return [sk.dof_index(n) for n in names]


def test_gradcheck_smooth_silhouette_energy(tiny_scene):
    """V_silh(smooth=True) w.r.t. pose angles (float64, finite differences vs autograd)."""
    sk, body, rig, th, masks = tiny_scene
    obs = prepare_silhouettes(masks, 40, blur=1.5, dtype=torch.float64)
    idx = _dofs(sk, ["l_elbow_flex", "l_shoulder_abd", "r_hip_flex", "spine_flex"])
    base = th.clone()
    base[idx] += torch.tensor([-0.3, 0.25, 0.2, 0.1], dtype=torch.float64)

    def V(x):
        t = base.expand(2, -1).clone()
        t[:, idx] = x
        return silhouette_energy(body.endpoints(sk(t)), body.radii, rig, obs, smooth=True)

    x = torch.stack([base[idx], base[idx] + 0.05]).requires_grad_()
    assert torch.autograd.gradcheck(V, (x,), eps=1e-6, atol=1e-6)
    (g,) = torch.autograd.grad(V(x).sum(), x)
    assert float(g.abs().sum()) > 0  # the energy does depend on these angles


def test_gradcheck_orientation_energy(tiny_scene):
    """V_ori (power 1 and 2) w.r.t. pose angles through the model's bone frames."""
    sk, _, _, th, _ = tiny_scene
    m = SensorManifold(sk, {"a": "l_elbow", "b": "r_knee", "c": "pelvis"}).double()
    meas = m.sensor_orientations(th)
    idx = _dofs(sk, ["l_elbow_flex", "l_shoulder_int", "r_knee_flex", "pelvis_rz"])
    x = (th[idx] + torch.tensor([0.2, -0.3, 0.25, 0.15], dtype=torch.float64))[None]
    x = x.expand(2, -1).clone()
    x[1] += 0.1
    x.requires_grad_()
    offsets = m.sensor_to_bone.transpose(-1, -2)

    for power in (1, 2):
        def V(x, power=power):
            t = th.expand(2, -1).clone()
            t[:, idx] = x
            return orientation_energy(m.bone_orientations(t), offsets, meas, power=power)

        assert torch.autograd.gradcheck(V, (x,), eps=1e-6, atol=1e-7)


def test_appearance_energy_is_not_differentiable(tiny_scene):
    """V_app reads pixel colours by nearest-pixel lookup: piecewise constant in the pose. It
    carries no gradient (rather than a zero one that would silently stall an optimiser), and a
    sub-pixel move of the pose leaves it unchanged."""
    from torchmocap.likelihoods.appearance import appearance_energy, body_surface_pattern

    sk, body, rig, th, masks = tiny_scene
    C, H, W = masks.shape
    g = torch.Generator().manual_seed(0)
    imgs = (torch.rand(C, H, W, 3, generator=g) * 255).to(torch.uint8)
    pattern = body_surface_pattern(body, 3, 4)
    x = th[None].clone().requires_grad_()
    e = appearance_energy(sk(x), body, pattern, rig, imgs)
    assert torch.isfinite(e).all() and float(e) > 0
    assert not e.requires_grad and e.grad_fn is None
    e2 = appearance_energy(sk(th[None] + 1e-9), body, pattern, rig, imgs)
    assert torch.equal(e, e2)


@pytest.mark.parametrize("mode", ["rays", "outlier"])
def test_appearance_occlusion_modes_match_a_loop_oracle(scene, mode):
    """Self-occlusion handling against a per-point loop: ``rays`` drops the views whose line of
    sight passes within a radius of another capsule's axis (densely sampled here), ``outlier``
    drops the view farthest from the mean of the others when three or more views see a point."""
    from torchmocap.body import rays_blocked_by_capsules, segment_distance
    from torchmocap.likelihoods.appearance import appearance_energy, body_surface_pattern

    sk, body, rig, th, _ = scene
    g = torch.Generator().manual_seed(5)
    C, (W, H) = rig.num_cameras, rig.image_size[0].tolist()
    imgs = torch.randint(0, 256, (C, H, W, 3), generator=g, dtype=torch.uint8)
    poses = th + 0.1 * torch.randn(2, sk.num_dofs, generator=g)
    pattern = body_surface_pattern(body, 2, 3)
    kin = sk(poses)
    got = appearance_energy(kin, body, pattern, rig, imgs, occlusion=mode)
    plain = appearance_energy(kin, body, pattern, rig, imgs)
    centres = rig.camera_centers()
    ep = body.endpoints(kin)
    s = torch.linspace(0, 1, 2001)
    hidden_views = grazing = 0
    own = pattern["bone"]
    pts_all = torch.stack([torch.stack([surface_point(kin, body, pattern, ep, p, i)[1]
                                        for i in range(own.shape[0])]) for p in range(2)])
    blocked = rays_blocked_by_capsules(centres, pts_all, ep, body.radii, own)
    for p in range(2):
        variances = []
        for i in range(pattern["bone"].shape[0]):
            b, x, n = surface_point(kin, body, pattern, ep, p, i)
            cols = []
            for c in range(C):
                pix, _, vis = rig.project(x[None])
                if not (vis[c, 0] and float((centres[c] - x) @ n) > 0):
                    continue
                if mode == "rays":
                    d = x - centres[c]
                    end = centres[c] + d * (1 - 0.005 / d.norm())
                    ray = centres[c] + s[:, None] * (end - centres[c])
                    dist = segment_distance(ray, ep[p]).amin(0) - body.radii
                    dist[b] = float("inf")
                    hidden = bool((dist < 0).any())
                    if float(dist.abs().min()) < 1e-4:
                        # grazing (within the oracle's sampling error; happens where a point
                        # lies on the neighbouring capsule's skin): take the function's answer
                        grazing += 1
                        hidden = bool(blocked[c, p, i])
                    if hidden:
                        hidden_views += 1
                        continue
                u, v = (pix[c, 0] + 0.5).floor().long().tolist()
                cols.append(imgs[c, v, u].double() / 255)
            if mode == "outlier" and len(cols) >= 3:
                X = torch.stack(cols)
                others = (X.sum(0, keepdim=True) - X) / (len(cols) - 1)
                worst = int(((X - others) ** 2).sum(-1).argmax())
                cols = [col for j, col in enumerate(cols) if j != worst]
            if len(cols) >= 2:
                variances.append(torch.stack(cols).var(0, unbiased=False).mean())
        assert got[p].item() == pytest.approx(torch.stack(variances).mean().item(), abs=1e-5)
    assert not torch.allclose(got, plain)  # the mode changes the energy of these poses
    if mode == "rays":
        assert hidden_views > 0 and grazing <= 0.02 * blocked.numel()
    with pytest.raises(ValueError, match="occlusion"):
        appearance_energy(kin, body, pattern, rig, imgs, occlusion="zbuffer")
    with pytest.raises(ValueError, match="occlusion"):
        AppearanceLikelihood(body, rig, occlusion=True)


def test_self_occlusion_handling_lowers_the_true_pose_energy():
    """Images z-buffered from a capsule mesh (flat colour per body part, an arm across the
    chest): a surface point hidden in a view reads the arm there, so without occlusion handling
    the true pose pays a colour variance; ``rays`` and ``outlier`` remove a large part of it and
    every mode still prefers the true pose to a perturbed one."""
    from torchmocap.data.synthetic.render import rasterize_zbuffer
    from torchmocap.data.synthetic.synthesis import body_surface

    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("r_shoulder_flex")] = 1.2   # right arm raised forward across the body
    th[sk.dof_index("r_shoulder_abd")] = -0.9
    th[sk.dof_index("r_elbow_flex")] = 1.6
    th[sk.dof_index("l_elbow_flex")] = 1.0
    surf = body_surface(sk, th[None].double(), kind="capsules")
    g = torch.Generator().manual_seed(0)
    part_colour = torch.rand(sk.num_joints, 3, generator=g)
    C, (W, H) = rig.num_cameras, rig.image_size[0].tolist()
    pix, z, _ = rig.double().project(surf.vertices[0])
    zb = rasterize_zbuffer(pix, z, surf.faces, W, H)
    imgs = torch.zeros(C, H, W, 3)
    imgs[..., 1] = ((torch.arange(W) // 6) % 2).float()[None, None, :] * 0.8  # striped floor
    face = zb.face.clamp_min(0)
    imgs = torch.where(zb.mask[..., None], part_colour[surf.face_part[face]], imgs)
    imgs = (imgs * 255).round().to(torch.uint8)
    obs = Frame(index=0, time=0.0, images=imgs)
    far = th.clone()
    far[sk.dof_index("r_shoulder_flex")] -= 0.4
    far[sk.dof_index("spine_twist")] += 0.2
    e = {}
    for mode in ("none", "rays", "outlier"):
        lik = AppearanceLikelihood(body, rig, axial=4, around=6, occlusion=mode)
        e[mode] = lik.energy(Poses(torch.stack([th, far]), sk), lik.prepare(obs))
        assert e[mode][0] < e[mode][1]
    # measured: none 0.0127 (far 0.0164), rays 0.0055 (0.0134), outlier 0.0085 (0.0112); what
    # rays leaves is part-boundary pixels (nearest-pixel reads, the mesh's facets)
    assert e["none"][0] > 0.008  # hidden points pay a variance at the truth
    assert e["rays"][0] < 0.6 * e["none"][0]
    assert e["outlier"][0] < 0.8 * e["none"][0]
    assert e["rays"][1] / e["rays"][0] > 1.5 * e["none"][1] / e["none"][0]


def test_first_max_mask_equals_argmax_with_ties():
    """The outlier mode's view mask: the first maximum of every column, as ``argmax(0)``
    (quantised colours make exact ties between views common)."""
    from torchmocap.likelihoods.appearance import _first_max

    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 3, (4, 500), generator=g).float()  # many ties
    x[:, :5] = -1.0
    mask = _first_max(x)
    assert torch.equal(mask, torch.arange(4)[:, None] == x.argmax(0))
    assert torch.equal(mask.sum(0), torch.ones(500, dtype=torch.long))


def test_rendered_silhouettes_of_views_of_different_sizes():
    """Views of different sizes share one array (the sequences' layout): each view is its own
    camera's rendering in the top-left corner, False beyond it."""
    from torchmocap.cameras import CameraRig
    from torchmocap.likelihoods.silhouette import render_capsule_silhouettes

    sk = human31()
    body = CapsuleBody(sk)
    base = make_ring_rig(2, image_size=(64, 48)).float()
    rig = CameraRig(base.K, base.R, base.t, [[64, 48], [60, 46]], base.dist)
    th = sk.zero_pose()
    out = render_capsule_silhouettes(body, rig, th)
    assert out.shape == (2, 48, 64) and bool(out[0].any())
    small = render_capsule_silhouettes(body, rig.subset([1]), th)
    assert small.shape == (1, 46, 60)
    assert torch.equal(out[1, :46, :60], small[0])
    assert not bool(out[1, 46:].any()) and not bool(out[1, :, 60:].any())
    assert torch.equal(out[0], render_capsule_silhouettes(body, rig.subset([0]), th)[0])
