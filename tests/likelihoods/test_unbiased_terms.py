"""Image terms whose minimum sits at the generating pose: the distance version of V_silh and the
appearance term without grazing views.

The observations are rendered by a different model than the one under test: the masks and
colour images below come from the z-buffered triangle mesh of the capsules
(:func:`torchmocap.data.synthetic.render.capsule_mesh`), the energies read projected stadiums
and surface
points.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.data.synthetic.render import capsule_mesh, rasterize_zbuffer
from torchmocap.likelihoods import Poses
from torchmocap.likelihoods.appearance import (
    AppearanceLikelihood,
    appearance_energy,
    body_surface_pattern,
)
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    _lookup_distance,
    prepare_silhouettes,
    silhouette_energy,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from oracle import appearance_loop  # noqa: E402


def _pose(sk):
    th = sk.zero_pose()
    th[sk.dof_index("l_elbow_flex")] = 1.2
    th[sk.dof_index("r_hip_flex")] = 0.6
    th[sk.dof_index("l_shoulder_abd")] = 0.5
    th[sk.dof_index("r_shoulder_flex")] = -0.7
    return th


def _mesh_views(body, rig, th):
    """Masks ``(C, H, W)`` and flat per-capsule colour images ``(C, H, W, 3)`` uint8 from the
    z-buffer of the capsule mesh (striped background)."""
    ep = body.endpoints(body.skeleton(th[None]))[0].double()
    verts, faces, face_cap = capsule_mesh(ep, body.radii.double(), sections=24, rings=6)
    u, v, depth, _ = rig.double().project_planar(verts)
    C = u.shape[0]
    W, H = (int(x) for x in rig.image_size[0].tolist())
    zb = rasterize_zbuffer(torch.stack([u, v], -1), depth, faces, W, H)
    face = zb.face.view(C, H, W)
    g = torch.Generator().manual_seed(7)
    albedo = torch.randint(30, 226, (body.radii.shape[0], 3), generator=g, dtype=torch.uint8)
    stripes = ((torch.arange(W) // 6) % 2 * 180 + 40).to(torch.uint8)
    imgs = torch.zeros(C, H, W, 3, dtype=torch.uint8)
    imgs[..., 2] = stripes
    hit = face >= 0
    imgs[hit] = albedo[face_cap[face[hit]]]
    return hit, imgs


@pytest.fixture(scope="module")
def mesh_scene():
    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(4).float()
    th = _pose(sk)
    masks, imgs = _mesh_views(body, rig, th)
    return sk, body, rig, th, masks, imgs


def _perturbed(sk, th, scale, n, seed):
    g = torch.Generator().manual_seed(seed)
    pert = th + scale * torch.randn(n, sk.num_dofs, generator=g)
    pert[:, :3] = th[:3]
    return pert


# ---------------------------------------------------------------- distance silhouette


def test_distance_lookup_is_the_distance_to_the_nearest_foreground_pixel():
    g = torch.Generator().manual_seed(0)
    masks = torch.rand(2, 17, 23, generator=g) > 0.93
    masks[1] = False
    masks[1, 4, 5] = True
    obs = prepare_silhouettes(masks, 10, distance=True, dtype=torch.float64)
    fy, fx = torch.nonzero(masks[1], as_tuple=True)
    # pixel centres inside the image: exact; outside: the border's value plus the distance to
    # the border (continuous, an upper bound of the Euclidean distance, exact straight out)
    xs = torch.tensor([0.0, 5.0, 22.0, -3.0, 30.0, 11.0, 22.5], dtype=torch.float64)
    ys = torch.tensor([0.0, 4.0, 16.0, 4.0, 20.0, -6.0, 16.0], dtype=torch.float64)
    got = _lookup_distance(obs.outside, xs.expand(2, -1), ys.expand(2, -1))[1]
    want = torch.hypot(xs - 5.0, ys - 4.0)
    torch.testing.assert_close(got[:4], want[:4])
    assert bool((got[4:] >= want[4:] - 1e-9).all())
    assert got[5].item() == pytest.approx(math.hypot(6.0, 4.0) + 6.0)
    assert got[6].item() == pytest.approx(got[2].item() + 0.5)
    # an independent implementation (scipy) on larger random masks, and an empty view
    from scipy.ndimage import distance_transform_edt

    big = torch.rand(3, 61, 83, generator=g) > 0.995
    big[2] = False
    got = prepare_silhouettes(big, 10, distance=True, dtype=torch.float64).outside[:, 0]
    for c in range(2):
        ref = torch.from_numpy(distance_transform_edt(~big[c].numpy()))
        torch.testing.assert_close(got[c], ref)
    assert bool((got[2] == 61 + 83).all())
    # exact far from the foreground too (a long image, one foreground pixel), float64 roots
    one = torch.zeros(1, 130, 12, dtype=torch.bool)
    one[0, 3, 2] = True
    far = prepare_silhouettes(one, 4, distance=True, dtype=torch.float64).outside[0, 0]
    yy, xx = torch.meshgrid(torch.arange(130.0, dtype=torch.float64),
                            torch.arange(12.0, dtype=torch.float64), indexing="ij")
    torch.testing.assert_close(far, torch.hypot(yy - 3, xx - 2))
    for c in range(2):
        fy, fx = torch.nonzero(masks[c], as_tuple=True)
        yy, xx = torch.meshgrid(torch.arange(17.0), torch.arange(23.0), indexing="ij")
        brute = torch.hypot(xx[..., None] - fx.double(), yy[..., None] - fy.double()).amin(-1)
        torch.testing.assert_close(obs.outside[c, 0], brute.to(obs.outside.dtype))


def test_distance_silhouette_is_minimal_at_the_generating_pose(mesh_scene):
    sk, body, rig, th, masks, _ = mesh_scene
    frame = Frame(index=0, time=0.0, silhouettes=masks)
    dist = SilhouetteLikelihood(body, rig, smooth=True, distance=1.0, fg_samples=200)
    blur = SilhouetteLikelihood(body, rig, smooth=True, fg_samples=200)
    od, ob = dist.prepare(frame), blur.prepare(frame)
    e_true = dist.energy(Poses(th[None], sk), od).item()
    # the mesh and the stadiums differ by the tessellation only: a near-zero floor
    assert e_true < 0.01
    # the blurred version pays along every edge even at the truth
    assert blur.energy(Poses(th[None], sk), ob).item() > 10 * e_true
    means = []
    for scale in (0.03, 0.1, 0.3):
        e = dist.energy(Poses(_perturbed(sk, th, scale, 48, 1), sk), od)
        assert bool((e > e_true).all())
        means.append(e.mean().item())
    assert means[0] < means[1] < means[2] < 1


def test_distance_silhouette_closed_form_for_a_shifted_model():
    """A model lying wholly ``d`` pixels to one side of a one-pixel-wide mask column costs
    ``rho(d)`` for every model point (model -> image)."""
    from torchmocap.likelihoods.silhouette import _robust

    obs = prepare_silhouettes(torch.zeros(1, 40, 60, dtype=torch.bool).index_fill_(
        2, torch.tensor([10]), True), 40, distance=True, dtype=torch.float64)
    d = torch.linspace(0.0, 3.0, 13, dtype=torch.float64)
    # points at x = 10 + d on every row: the nearest foreground pixel is d away
    px = (10.0 + d)[None, :].expand(1, -1)
    py = torch.full_like(px, 20.0)
    torch.testing.assert_close(_lookup_distance(obs.outside, px, py)[0], d)
    assert _robust(torch.tensor(2.0), 2.0).item() == pytest.approx(0.5)


def test_distance_silhouette_gradient(mesh_scene):
    sk, body, rig, th, masks, _ = mesh_scene
    obs = prepare_silhouettes(masks, 60, distance=True, dtype=torch.float64)
    rig64 = rig.double()
    ep = body.endpoints(sk(_perturbed(sk, th, 0.2, 2, 5).double())).detach()
    radii = body.radii.double()
    ep.requires_grad_(True)

    def f(x):
        return silhouette_energy(x, radii, rig64, obs, smooth=True, distance=1.5)

    # piecewise smooth (bilinear cells, the max over stadiums): a tiny step stays in one piece
    assert torch.autograd.gradcheck(f, (ep,), eps=1e-7, atol=1e-5, rtol=1e-3)
    f(ep).sum().backward()
    assert ep.grad.abs().sum() > 0


def test_distance_silhouette_settings_are_checked(mesh_scene):
    sk, body, rig, th, masks, _ = mesh_scene
    for bad in (0.0, -1.0, float("nan"), True, "3"):
        with pytest.raises(ValueError, match="distance"):
            SilhouetteLikelihood(body, rig, smooth=True, distance=bad)
    with pytest.raises(ValueError, match="smooth"):
        SilhouetteLikelihood(body, rig, smooth=False, distance=2.0)
    plain = prepare_silhouettes(masks, 10)
    with pytest.raises(ValueError, match="distance=True"):
        silhouette_energy(body.endpoints(sk(th[None])), body.radii, rig, plain, smooth=True,
                          distance=2.0)
    lik = SilhouetteLikelihood(body, rig, smooth=True, distance=2.0)
    empty = lik.prepare(Frame(index=0, time=0.0, silhouettes=torch.zeros_like(masks)))
    assert lik.energy(Poses(th[None], sk), empty).item() == 1.0  # no evidence is not a match


def test_descent_accepts_the_distance_term():
    from torchmocap.filters.inference import LocalInference
    from torchmocap.filters.tracking.tracker import _check_descent_energy

    sk = human31()
    body = CapsuleBody(sk)
    rig = make_ring_rig(2).float()
    _check_descent_energy(LocalInference(sk, iterations=2),
                          SilhouetteLikelihood(body, rig, smooth=True, distance=2.0))


# ---------------------------------------------------------------- grazing views


def test_min_facing_matches_a_loop_oracle(mesh_scene):
    sk, body, rig, th, _, _ = mesh_scene
    g = torch.Generator().manual_seed(3)
    C, (W, H) = rig.num_cameras, rig.image_size[0].tolist()
    imgs = torch.randint(0, 256, (C, H, W, 3), generator=g, dtype=torch.uint8)
    poses = th + 0.1 * torch.randn(2, sk.num_dofs, generator=g)
    pattern = body_surface_pattern(body, 2, 5)
    kin = sk(poses)
    got = appearance_energy(kin, body, pattern, rig, imgs, min_facing=0.5)
    assert not torch.allclose(got, appearance_energy(kin, body, pattern, rig, imgs))
    for p in range(2):
        want, counted = appearance_loop(kin, body, pattern, rig, imgs, p, min_facing=0.5)
        assert counted > 10
        assert got[p].item() == pytest.approx(want, abs=1e-5)


def test_grazing_views_bias_the_true_pose(mesh_scene):
    """Seen at a grazing angle a surface point's pixel lies on its limb's outline and reads the
    background or the part behind: the true pose pays for it. With exact visibility (``rays``)
    and no view within 60 degrees of grazing, the truth's colour variance on flat-coloured
    images is zero; with grazing views it is not, and without occlusion handling dropping
    them still halves it."""
    sk, body, rig, th, masks, imgs = mesh_scene
    frame = Frame(index=0, time=0.0, images=imgs)
    pert = _perturbed(sk, th, 0.03, 32, 2)

    def truth(occlusion, mf):
        lik = AppearanceLikelihood(body, rig, axial=3, around=6, occlusion=occlusion,
                                   min_facing=mf)
        obs = lik.prepare(frame)
        e = lik.energy(Poses(th[None], sk), obs).item()
        assert bool((lik.energy(Poses(pert, sk), obs) > e).float().mean() > 0.9)
        return e

    assert truth("rays", 0.5) < 1e-4 < 0.005 < truth("rays", 0.0)
    assert truth("none", 0.3) < 0.6 * truth("none", 0.0)


def test_min_facing_is_checked(mesh_scene):
    _, body, rig, *_ = mesh_scene
    for bad in (-0.1, 1.0, math.nan, True, "0.5"):
        with pytest.raises(ValueError, match="min_facing"):
            AppearanceLikelihood(body, rig, min_facing=bad)
