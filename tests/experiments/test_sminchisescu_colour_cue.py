"""The colour-cue probe of experiments/sminchisescu2003: its three energies on a real render."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="module")
def probe_setup(load_script):
    from torchmocap.assembly import Runtime
    from torchmocap.data.synthetic.clips import synthesized_sequence
    from torchmocap.likelihoods.appearance import body_surface_pattern

    cc = load_script("sminchisescu2003/colour_cue.py")
    seq = synthesized_sequence({"name": "walk", "path": None, "frames": 2}, "monocular",
                               {"images.enabled": True, "joints2d.enabled": False}, seed=0)
    rt = Runtime.from_sequence(seq)
    pattern = body_surface_pattern(rt.body, 3, 4)
    return cc, seq, rt, pattern


def test_energies_against_the_reference_frame(probe_setup):
    """At the reference pose and image the per-point texture energy is exactly 0; a moved pose
    reads other colours; the coherence energy equals the pooled within-part variance computed
    part by part."""
    cc, seq, rt, pattern = probe_setup
    gt = seq.ground_truth.theta.to(torch.float32)
    img = seq.images[0, 0]
    ref_col, ref_ok = (x[0] for x in cc.surface_colours(rt, pattern, gt[:1], img))
    moved = gt[:1].clone()
    moved[0, :3] += torch.tensor([0.15, 0.0, 0.0])  # 15 cm sideways: other pixels
    col, ok = cc.surface_colours(rt, pattern, torch.cat([gt[:1], moved]), img)
    assert int(ok[0].sum()) > 20
    e = cc.energies(col, ok, ref_col, ref_ok)
    assert float(e["point colour"][0]) == 0.0
    assert float(e["point colour"][1]) > 1e-3 and float(e["part colour"][1]) > float(
        e["part colour"][0])
    # coherence of the true pose, part by part
    num = den = 0.0
    for b in range(col.shape[1]):
        c = col[0, b][ok[0, b]]
        if c.shape[0]:
            num += float(((c - c.mean(0)) ** 2).sum())
            den += c.shape[0]
    assert float(e["coherence"][0]) == pytest.approx(num / den, rel=1e-5)
