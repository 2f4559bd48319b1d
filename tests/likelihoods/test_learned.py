"""Learned likelihood terms: features term, render-CNN term, soft renderer, weights files."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import (
    ArchitectureMismatchError,
    LearnedFeatureLikelihood,
    LearnedRenderLikelihood,
    Poses,
    WeightsError,
    soft_render_capsules,
)
from torchmocap.likelihoods.learned import bilinear_lookup, bundled_weights_path, pool_views
from torchmocap.likelihoods.silhouette import render_capsule_silhouettes
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from oracle import capsule_masks  # noqa: E402

TERMS = {
    "features": lambda body, rig, **kw: LearnedFeatureLikelihood(body, rig, **kw),
    "render": lambda body, rig, **kw: LearnedRenderLikelihood(body, rig, size=(32, 24), **kw),
}


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk).float()
    rig = make_ring_rig(4).float()
    th = sk.zero_pose()
    th[sk.dof_index("l_elbow_flex")] = 1.2
    th[sk.dof_index("r_hip_flex")] = 0.6
    masks = capsule_masks(body, rig, th)
    g = torch.Generator().manual_seed(0)
    images = torch.randint(0, 256, (*masks.shape, 3), generator=g, dtype=torch.uint8)
    frame = Frame(index=0, time=0.0, silhouettes=masks, images=images,
                  view_dropped=torch.zeros(4, dtype=torch.bool))
    return sk, body, rig, th, frame


def _poses(sk, th, n=6, std=0.1, seed=1):
    g = torch.Generator().manual_seed(seed)
    return th[None] + std * torch.randn(n, th.shape[0], generator=g)


@pytest.mark.parametrize("kind", sorted(TERMS))
class TestLearnedTerms:
    def test_smoke(self, scene, kind):
        sk, body, rig, th, frame = scene
        term = TERMS[kind](body, rig)
        v = term.energy(Poses(_poses(sk, th), sk), term.prepare(frame))
        assert v.shape == (6,) and bool(torch.isfinite(v).all())
        assert term.evidence(term.prepare(frame))

    def test_gradients_reach_every_parameter(self, scene, kind):
        sk, body, rig, th, frame = scene
        term = TERMS[kind](body, rig)
        x = _poses(sk, th).requires_grad_(True)
        v = term.energy(Poses(x, sk), term.prepare(frame))
        (v * torch.linspace(0.5, 2.0, 6)).sum().backward()
        for name, p in term.net.named_parameters():
            assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
            assert float(p.grad.abs().sum()) > 0, name
        assert float(x.grad.abs().sum()) > 0

    def test_dropped_views(self, scene, kind):
        """A dropped view's content is ignored; with all views dropped every particle gets the
        same energy (no evidence)."""
        sk, body, rig, th, frame = scene
        term = TERMS[kind](body, rig)
        x = _poses(sk, th)
        drop = torch.tensor([False, True, False, False])
        f1 = Frame(index=0, time=0.0, silhouettes=frame.silhouettes, images=frame.images,
                   view_dropped=drop)
        other = frame.silhouettes.clone()
        other[1] = ~other[1]
        f2 = Frame(index=0, time=0.0, silhouettes=other, images=frame.images, view_dropped=drop)
        v1 = term.energy(Poses(x, sk), term.prepare(f1))
        v2 = term.energy(Poses(x, sk), term.prepare(f2))
        torch.testing.assert_close(v1, v2)
        f3 = Frame(index=0, time=0.0, silhouettes=frame.silhouettes, images=frame.images,
                   view_dropped=torch.ones(4, dtype=torch.bool))
        obs = term.prepare(f3)
        assert not term.evidence(obs)
        v3 = term.energy(Poses(x, sk), obs).detach()
        assert bool(torch.isfinite(v3).all()) and float(v3.max() - v3.min()) == 0.0

    def test_weights_round_trip(self, scene, kind, tmp_path):
        sk, body, rig, th, frame = scene
        torch.manual_seed(3)
        term = TERMS[kind](body, rig)
        path = term.save_weights(tmp_path / "w.pt")
        assert not (tmp_path / "w.pt.tmp").exists()
        torch.manual_seed(4)  # another initialisation, replaced by the file
        again = TERMS[kind](body, rig, weights=str(path))
        x = _poses(sk, th)
        with torch.no_grad():
            a = term.energy(Poses(x, sk), term.prepare(frame))
            b = again.energy(Poses(x, sk), again.prepare(frame))
        assert torch.equal(a, b)
        assert again.weights_path == str(path)

    def test_exception(self, scene, kind, tmp_path):
        sk, body, rig, th, frame = scene
        term = TERMS[kind](body, rig)
        path = term.save_weights(tmp_path / "w.pt")
        other = {"features": {"hidden": 4}, "render": {"hidden": 4}}[kind]
        file_h = term.config["hidden"]
        with pytest.raises(ArchitectureMismatchError, match=f"hidden: file {file_h}, config 4"):
            TERMS[kind](body, rig, weights=str(path), **other)
        wrong = TERMS["render" if kind == "features" else "features"]
        with pytest.raises(WeightsError, match="network, not a"):
            wrong(body, rig, weights=str(path))
        junk = tmp_path / "junk.pt"
        junk.write_text("not a weights file")
        with pytest.raises(WeightsError, match="not a torchmocap weights file"):
            TERMS[kind](body, rig, weights=str(junk))
        with pytest.raises(FileNotFoundError, match="weights: no such file"):
            TERMS[kind](body, rig, weights=str(tmp_path / "missing.pt"))


def test_feature_term_without_colour(scene):
    sk, body, rig, th, frame = scene
    term = LearnedFeatureLikelihood(body, rig, use_colour=False)
    assert term.requires == ("silhouettes",)
    f = Frame(index=0, time=0.0, silhouettes=frame.silhouettes)
    v = term.energy(Poses(_poses(sk, th), sk), term.prepare(f))
    assert v.shape == (6,)


def test_bind_shares_the_network(scene):
    sk, body, rig, th, frame = scene
    term = LearnedFeatureLikelihood(body, rig)
    other = term.bind(CapsuleBody(sk).float(), make_ring_rig(3).float())
    assert other.net is term.net and other.config == term.config


def test_bilinear_lookup_matches_grid_sample():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 7, 9, generator=g, dtype=torch.float64)
    px = torch.rand(2, 40, generator=g, dtype=torch.float64) * 12 - 1.5
    py = torch.rand(2, 40, generator=g, dtype=torch.float64) * 10 - 1.5
    grid = torch.stack([(px + 0.5) / 9 * 2 - 1, (py + 0.5) / 7 * 2 - 1], -1)[:, None]
    ref = F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros",
                        align_corners=False)[:, :, 0]
    torch.testing.assert_close(bilinear_lookup(img, px, py), ref)
    # the gradient in the pixel coordinates is differentiable in the image (an unrolled
    # optimiser needs that second-order path; grid_sample's backward does not provide it)
    img.requires_grad_(True)
    px.requires_grad_(True)
    (gx,) = torch.autograd.grad(bilinear_lookup(img, px, py).sum(), px, create_graph=True)
    (gx * gx).sum().backward()
    assert img.grad is not None and float(img.grad.abs().sum()) > 0


def test_pool_views_ignores_dropped_views():
    v = torch.randn(3, 4, 5)
    valid = torch.tensor([True, False, True, True])
    a = pool_views(v, valid)
    v2 = v.clone()
    v2[:, 1] = 100.0
    torch.testing.assert_close(a, pool_views(v2, valid))
    assert torch.equal(pool_views(v, torch.zeros(4, dtype=torch.bool)), torch.zeros(3, 10))


class TestSoftRender:
    def test_gradcheck(self):
        """float64 gradcheck of the soft renderer in the capsule endpoints and radii."""
        sk = human31().double()
        body = CapsuleBody(sk).double()
        rig = make_ring_rig(2).double()
        th = sk.zero_pose(dtype=torch.float64)
        ends = body.endpoints(sk(th[None]))[:, :3].clone().requires_grad_(True)
        radii = body.radii[:3].clone().requires_grad_(True)
        fn = lambda e, r: soft_render_capsules(e, r, rig, size=(8, 6), tau=2.0)
        assert torch.autograd.gradcheck(fn, (ends, radii), eps=1e-6, atol=1e-5)

    def test_matches_hard_rendering(self, scene):
        """With a sharp edge the cells equal the exact capsule silhouette at their centres."""
        sk, body, rig, th, frame = scene
        body64, rig64, sk64 = CapsuleBody(sk.double()).double(), rig.double(), sk.double()
        th64 = th.double()
        soft = soft_render_capsules(body64.endpoints(sk64(th64[None])), body64.radii, rig64,
                                    size=(80, 60), tau=1e-3)[0]
        hard = render_capsule_silhouettes(body64, rig64, th64)  # (C, 240, 320)
        centres = hard[:, 1::4, 1::4]  # cell (i, j) centre = pixel (4 j + 1.5, 4 i + 1.5)
        agree = ((soft > 0.5) == centres).double().mean()
        assert float(agree) > 0.98
        sk.float()

    def test_exception(self, scene):
        sk, body, rig, th, frame = scene
        ends = body.endpoints(sk(th[None]))
        with pytest.raises(ValueError, match="endpoints"):
            soft_render_capsules(ends[0], body.radii, rig)
        with pytest.raises(ValueError, match="tau"):
            soft_render_capsules(ends, body.radii, rig, tau=0.0)


def test_render_term_on_the_real_bodytrack_frame(shared_data):
    from torchmocap.assembly import Runtime
    from torchmocap.data.recordings.bodytrack import load_bodytrack_sequence

    root = shared_data / "multiview" / "bodytrack_sequenceB_1"
    seq = load_bodytrack_sequence(root, scale=0.5, headings=4)
    rt = Runtime.from_sequence(seq)
    term = LearnedRenderLikelihood(rt.body, rt.rig, size=(40, 30))
    obs = term.prepare(seq.frame(0))
    assert obs.observed.shape == (4, 30, 40) and float(obs.observed.max()) > 0
    cand = torch.as_tensor(seq.meta.initial_poses, dtype=torch.float32)
    v = term.energy(Poses(cand, rt.skeleton), obs)
    assert v.shape == (cand.shape[0],) and bool(torch.isfinite(v).all())


@pytest.mark.parametrize("name", ["learned_features.pt", "learned_render.pt"])
def test_bundled_weights_load(scene, name):
    """The shipped weights match the packaged term configs."""
    from torchmocap.assembly import Runtime, build
    from torchmocap.likelihoods.learned import read_weights

    sk, body, rig, th, frame = scene
    path = bundled_weights_path(name)
    assert path.is_file() and path.stat().st_size < 200_000
    payload = read_weights(path)
    assert "optimizer" not in payload  # weights only
    import yaml

    conf = Path(__import__("torchmocap").__file__).parent / "conf" / "term"
    cfg = yaml.safe_load((conf / name.replace(".pt", ".yaml")).read_text())
    term = build(cfg, Runtime(skeleton=sk, body=body, rig=rig))
    assert term.weights_path == str(path)
