"""Synthesis from the Anny body: it differs from the MakeHuman render, follows its phenotype, is
reproducible from a seed, and its ground truth lies inside its own silhouettes."""

from __future__ import annotations

import pytest
import torch

from torchmocap.data.synthetic import load_scenario, synthesize
from torchmocap.data.synthetic.clips import bundled_clip_path
from torchmocap.io import read_bvh


@pytest.fixture(scope="module")
def clip():
    return read_bvh(bundled_clip_path())


def _seq(clip, frames=2, **kw):
    sc = load_scenario("clean", images={"enabled": False}, depth={"enabled": False},
                       imu={"enabled": False}, **kw)
    return synthesize(clip, sc, seed=0, frames=frames)


def _iou(a, b):
    return float((a & b).sum()) / float((a | b).sum())


def test_anny_render_differs_from_makehuman_and_follows_its_phenotype(anny_data, clip):
    mh = _seq(clip)
    default = _seq(clip, body="anny")
    heavy = _seq(clip, body="anny", phenotype="heavy")
    child = _seq(clip, body="anny", phenotype="child")
    assert mh.meta.body == "skinned" and mh.meta.phenotype is None
    assert heavy.meta.phenotype["weight"] == pytest.approx(0.92)
    # another body: the masks differ from the MakeHuman mesh's (same motion, same cameras)
    assert _iou(default.silhouettes, mh.silhouettes) < 0.9
    # heavier: more foreground; a child: smaller, and its skeleton is shorter
    assert heavy.silhouettes.sum() > 1.07 * default.silhouettes.sum()
    assert child.silhouettes.sum() < 0.85 * default.silhouettes.sum()
    assert child.meta.body_height < default.meta.body_height - 0.1
    top = lambda s: float(s.ground_truth.positions[..., 2].max())  # noqa: E731
    assert top(child) < top(default) - 0.1
    # the ground truth is the body's own skeleton: its joints project inside its silhouettes
    for seq in (heavy, child):
        pix, _, vis = seq.rig.project(seq.ground_truth.positions.float())  # (T, C, J, 2)
        x = pix[..., 0].round().long().clamp(0, 319)
        y = pix[..., 1].round().long().clamp(0, 239)
        T, C, J = x.shape
        t = torch.arange(T)[:, None, None].expand(T, C, J)
        c = torch.arange(C)[None, :, None].expand(T, C, J)
        inside = seq.silhouettes[t, c, y, x]
        assert float(inside[vis].float().mean()) > 0.9  # the MakeHuman render: 0.92


def test_random_phenotype_is_reproducible(anny_data, clip):
    a = _seq(clip, frames=1, body="anny", phenotype="random", phenotype_seed=5)
    b = _seq(clip, frames=1, body="anny", phenotype="random", phenotype_seed=5)
    c = _seq(clip, frames=1, body="anny", phenotype="random", phenotype_seed=6)
    assert a.meta.phenotype == b.meta.phenotype != c.meta.phenotype
    assert torch.equal(a.silhouettes, b.silhouettes)
    assert not torch.equal(a.silhouettes, c.silhouettes)
