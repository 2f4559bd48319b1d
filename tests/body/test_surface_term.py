"""The surface silhouette term (SurfaceSilhouetteLikelihood): the posed surface points are the
body's vertices, the energy is lowest at the pose that rendered the masks (rendered from the
whole mesh, not from the points), gradcheck, bad inputs."""

from __future__ import annotations

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data.synthetic.render import rasterize_mask
from torchmocap.likelihoods import (
    Poses,
    SurfaceSilhouetteLikelihood,
    prepare_silhouettes,
    surface_samples,
    surface_silhouette_energy,
)
from torchmocap.skeleton import human31


class _Frame:
    def __init__(self, masks):
        self.silhouettes, self.view_dropped = masks, None


def _blob_masks(rig, centre, radius):
    W, H = (int(v) for v in rig.image_size[0].tolist())
    pix = rig.project(centre[None])[0][:, 0]  # (C, 2)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    d = ((xs[None] - pix[:, None, None, 0]) ** 2 + (ys[None] - pix[:, None, None, 1]) ** 2)
    return (d.sqrt() < radius).float()


def test_gradcheck_and_zero_at_agreement():
    rig = make_ring_rig(2, image_size=(24, 18), radius=3.0, height=1.0).double()
    masks = _blob_masks(rig, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 4.0)
    obs = prepare_silhouettes(masks, 12, blur=0.0, distance=True, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    pts = (torch.tensor([0.0, 0.0, 1.0]) + 0.3 * torch.randn(2, 5, 3, generator=g)).double()
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: surface_silhouette_energy(p, rig, obs, 1.5, 0.05), (pts,), eps=1e-6,
        atol=1e-5)
    # points spread over the blob's middle, each covering a lot: zero energy; far points: ~1
    inside = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(1, 1, 3)
    e_in = surface_silhouette_energy(inside, rig, obs, 1.0, 1.0)
    far = inside + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    e_far = surface_silhouette_energy(far, rig, obs, 1.0, 1.0)
    assert float(e_in) < 1e-6 and float(e_far) > 0.9


def test_samples_cover_the_points():
    pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    idx, cover = surface_samples(pts, 50)
    assert idx.unique().numel() == 50
    d = torch.cdist(pts, pts[idx]).amin(1)
    assert float(d.max()) == pytest.approx(cover)
    _, cover2 = surface_samples(pts, 200)
    assert cover2 < cover


def test_bad_inputs():
    rig = make_ring_rig(2).double()
    obs = prepare_silhouettes(torch.ones(2, 240, 320), 8, blur=0.0, dtype=torch.float64)
    with pytest.raises(ValueError, match="points: expected shape"):
        surface_silhouette_energy(torch.zeros(4, 3, dtype=torch.float64), rig, obs, 1.0, 0.1)
    with pytest.raises(ValueError, match="distance=True"):
        surface_silhouette_energy(torch.zeros(1, 4, 3, dtype=torch.float64), rig, obs, 1.0,
                                  0.1)
    with pytest.raises(ValueError, match="num: expected"):
        surface_samples(torch.zeros(5, 3), 6)
    sk = human31()
    body = CapsuleBody(sk)
    for kw, name in (({"num_points": 0}, "num_points"), ({"fg_samples": 1.5}, "fg_samples"),
                     ({"distance": -1.0}, "distance"), ({"reference_width": 0}, "reference_width"),
                     ({"phenotype": 0.3}, "phenotype")):
        with pytest.raises(ValueError, match=name):
            SurfaceSilhouetteLikelihood(body, make_ring_rig(2), **kw)


def test_lowest_at_the_rendering_pose(anny_body):
    """Masks rendered from the whole skin of a heavy body; the term (400 points) scores the true
    pose below perturbed ones (several seeds) and its points are the body's vertices."""
    sk = human31().double()
    body = CapsuleBody(sk).double()
    rig = make_ring_rig(4, image_size=(160, 120)).double()
    phen = torch.tensor([0.5, 0.6, 0.5, 0.8, 0.5, 0.5], dtype=torch.float64)
    body.surface_phenotype = phen
    term = SurfaceSilhouetteLikelihood(body, rig, num_points=400, fg_samples=64)
    g = torch.Generator().manual_seed(0)
    theta = sk.zero_pose(dtype=torch.float64)
    theta = theta + 0.2 * torch.randn(theta.shape, generator=g, dtype=torch.float64) * (
        torch.arange(theta.shape[-1]) >= 6)
    pb = term._rest(torch.float64)[0]
    with torch.no_grad():
        verts = pb(theta, phen, offsets=sk.offsets).vertices
    pix, depth, _ = rig.project(verts)
    masks = rasterize_mask(pix, depth, pb.faces, 160, 120).double()
    obs = term.prepare(_Frame(masks))
    idx = surface_samples(pb.rest_surface(phen, sk.offsets, dtype=torch.float64).rest, 400)[0]
    poses = Poses(theta[None], sk)
    assert torch.allclose(term.points(poses)[0], verts[idx], atol=1e-9)
    e_true = float(term.energy(poses, obs)[0])
    wrong = theta + 0.15 * torch.randn((8,) + theta.shape, generator=g, dtype=torch.float64)
    e_wrong = term.energy(Poses(wrong, sk), obs)
    assert bool((e_wrong > e_true).all()), (e_true, e_wrong)
    # differentiable in the pose
    th = theta[None].clone().requires_grad_(True)
    term.energy(Poses(th, sk), obs).sum().backward()
    assert th.grad is not None and bool(th.grad.abs().sum() > 0)
