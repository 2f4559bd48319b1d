"""Pixel settings of V_silh given for a reference width (``reference_width``): the term reads
the same at any image resolution.

Masks are rendered by the z-buffered triangle mesh of the capsules (another model than the
projected stadiums the energy reads) at 320 x 240 and at 640 x 480 with the same field of view.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import Poses
from torchmocap.likelihoods.silhouette import (
    SilhouetteLikelihood,
    prepare_silhouettes,
    silhouette_energy,
)
from torchmocap.skeleton import human31

sys.path.insert(0, str(Path(__file__).parent))
from test_unbiased_terms import _mesh_views, _perturbed, _pose  # noqa: E402


@pytest.fixture(scope="module")
def two_resolutions():
    sk = human31()
    body = CapsuleBody(sk)
    th = _pose(sk)
    out = {}
    for w, h in ((320, 240), (640, 480)):
        rig = make_ring_rig(4, image_size=(w, h)).float()
        masks, _ = _mesh_views(body, rig, th)
        out[w] = (rig, Frame(index=0, time=0.0, silhouettes=masks))
    return sk, body, th, out


@pytest.mark.parametrize("kind,spread,tol,sign", [
    (dict(smooth=True, distance=1.0), 0.08, 0.10, 1.0),
    (dict(smooth=True), 0.04, 0.05, -1.0)])
def test_reference_width_makes_the_energy_resolution_independent(two_resolutions, kind, spread,
                                                                 tol, sign):
    """The same poses against the same scene at twice the resolution: with the pixel settings
    scaled per view the energies match those at 320 pixels up to the pixel quantisation (which
    is half as large at 640); in raw pixels the distance version charges every misfit more (it
    spans twice as many pixels, > 18 % on average) and the blurred one less (its blur and
    sigmoid are half as wide relative to the body, > 20 %)."""
    sk, body, th, views = two_resolutions
    poses = Poses(_perturbed(sk, th, spread, 24, seed=3), sk)
    e = {}
    for w, ref in ((320, 320), (640, 320), (640, None)):
        rig, frame = views[w]
        lik = SilhouetteLikelihood(body, rig, fg_samples=128, reference_width=ref, **kind)
        e[(w, ref)] = lik.energy(poses, lik.prepare(frame))
    base = e[(320, 320)]
    scaled = ((e[(640, 320)] - base).abs() / base).mean()
    raw = sign * ((e[(640, None)] - base) / base).mean()
    assert scaled < tol, (scaled, raw)
    assert raw > 2 * tol and raw > 2 * scaled, (scaled, raw)


def test_per_view_scales_act_on_their_own_view(two_resolutions):
    """A per-view ``(C,)`` robust scale and coverage width: V_silh is the mean over views of each
    view's energy with its own scalar setting."""
    sk, body, th, views = two_resolutions
    rig, frame = views[320]
    poses = _perturbed(sk, th, 0.15, 6, seed=5)
    ep = body.endpoints(sk(poses))
    k = torch.tensor([1.0, 2.0, 0.5, 3.0])
    for distance in (True, False):
        obs = prepare_silhouettes(frame.silhouettes, 64, blur=1.5 * k if not distance else 0.0,
                                  distance=distance)
        tau, dist = 1.5 * k, (0.8 * k if distance else None)
        got = silhouette_energy(ep, body.radii, rig, obs, True, tau=tau, distance=dist)
        per_view = []
        for c in range(4):
            only = dataclasses.replace(obs, view_valid=torch.arange(4) == c)
            if not distance:  # that view's blur alone
                only = dataclasses.replace(only, blurred=prepare_silhouettes(
                    frame.silhouettes, 64, blur=1.5 * float(k[c])).blurred)
            per_view.append(silhouette_energy(ep, body.radii, rig, only, True,
                                              tau=1.5 * float(k[c]),
                                              distance=0.8 * float(k[c]) if distance else None))
        torch.testing.assert_close(got, torch.stack(per_view).mean(0), rtol=1e-5, atol=1e-6)


def test_view_scale_and_bad_reference_width(two_resolutions):
    sk, body, th, views = two_resolutions
    rig, _ = views[640]
    lik = SilhouetteLikelihood(body, rig, smooth=True, distance=1.0, reference_width=320)
    assert lik.view_scale().tolist() == [2.0] * 4
    assert SilhouetteLikelihood(body, rig).view_scale() == 1.0
    assert "reference_width=320" in repr(lik)
    for bad in (0, -320, float("nan"), True, "320"):
        with pytest.raises(ValueError, match="reference_width"):
            SilhouetteLikelihood(body, rig, reference_width=bad)
    with pytest.raises(ValueError, match="blur"):
        prepare_silhouettes(torch.ones(4, 8, 8, dtype=torch.bool), 4, blur=[1.0, 2.0])


def test_soft_silhouettes_of_views_of_different_sizes():
    """One rig with a 320 x 240 and a 160 x 120 camera (the same field of view): the grid is
    the largest view's; the smaller view fills its top-left corner, as rendered alone, and is
    0 outside its own image (a sequence's padding)."""
    from torchmocap.cameras import CameraRig
    from torchmocap.likelihoods import soft_capsule_silhouettes

    sk = human31()
    body = CapsuleBody(sk).double()
    big = make_ring_rig(2, image_size=(320, 240)).double()
    small = make_ring_rig(2, image_size=(160, 120)).double()
    rig = CameraRig(torch.stack([big.K[0], small.K[1]]), big.R, big.t,
                    [(320, 240), (160, 120)], big.dist, ["a", "b"])
    ends = body.endpoints(sk(sk.zero_pose((1,), dtype=torch.float64)))
    both = soft_capsule_silhouettes(ends, body.radii, rig, stride=2)
    assert both.shape == (1, 2, 120, 160)
    alone = soft_capsule_silhouettes(ends, body.radii, small.subset([1]), stride=2)[0, 0]
    torch.testing.assert_close(both[0, 1, :60, :80], alone)
    assert float(alone.sum()) > 50 and float(both[0, 1, 60:].abs().sum()) == 0.0
    assert float(both[0, 1, :, 80:].abs().sum()) == 0.0
    first = soft_capsule_silhouettes(ends, body.radii, big.subset([0]), stride=2)[0, 0]
    torch.testing.assert_close(both[0, 0], first)
