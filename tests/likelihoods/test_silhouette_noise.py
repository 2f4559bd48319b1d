"""The mask noise model: masks corrupted with known per-view false-positive and false-negative
rates give those rates back when fitted under the true pose (several seeds); the true pose has
a lower energy than a perturbed one; gradcheck in the rates and widths; dropped views are not
scored; bad settings are named."""

from __future__ import annotations

import copy

import pytest
import torch

from torchmocap.body import CapsuleBody
from torchmocap.cameras import make_ring_rig
from torchmocap.data import Frame
from torchmocap.likelihoods import (
    FrameEnergy,
    Poses,
    SilhouetteNoiseLikelihood,
    fit_noise_model,
    render_capsule_silhouettes,
)
from torchmocap.skeleton import human31


@pytest.fixture(scope="module")
def scene():
    sk = human31()
    body = CapsuleBody(sk).float()
    rig = make_ring_rig(2, image_size=(160, 120)).float()
    g = torch.Generator().manual_seed(0)
    theta = sk.zero_pose((3,))
    theta[:, 6:] = 0.2 * torch.randn(3, sk.num_dofs - 6, generator=g)
    return sk, body, rig, sk.clamp(theta)


def _noisy(body, rig, theta, fp, fn, seed):
    """Rendered masks with background flipped on at rate fp[c] and body flipped off at fn[c]."""
    g = torch.Generator().manual_seed(seed)
    frames = []
    for t in range(theta.shape[0]):
        m = render_capsule_silhouettes(body, rig, theta[t])
        u = torch.rand(m.shape, generator=g)
        rate_on = torch.tensor(fp)[:, None, None]
        rate_off = torch.tensor(fn)[:, None, None]
        noisy = torch.where(m, u >= rate_off, u < rate_on)
        frames.append(Frame(t, t / 30.0, silhouettes=noisy))
    return frames


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_rates_are_recovered(scene, seed):
    sk, body, rig, theta = scene
    fp, fn = [0.02, 0.15], [0.25, 0.05]
    frames = _noisy(body, rig, theta, fp, fn, seed)
    term = SilhouetteNoiseLikelihood(body, rig, stride=2)
    before = fit_noise_model(SilhouetteNoiseLikelihood(body, rig, stride=2), sk, frames, theta,
                             iterations=0)
    after = fit_noise_model(term, sk, frames, theta)
    got_fp, got_fn, width = term.rates()
    torch.testing.assert_close(got_fp, torch.tensor(fp), atol=0.03, rtol=0)
    torch.testing.assert_close(got_fn, torch.tensor(fn), atol=0.04, rtol=0)
    assert bool((width > 0).all()) and after < before


def test_the_true_pose_scores_best(scene):
    sk, body, rig, theta = scene
    frames = _noisy(body, rig, theta, [0.05, 0.05], [0.1, 0.1], 3)
    term = SilhouetteNoiseLikelihood(body, rig, stride=2)
    V = FrameEnergy(term, term.prepare(frames[0]), sk)
    g = torch.Generator().manual_seed(4)
    worse = sk.clamp(theta[:1] + 0.15 * torch.randn(4, sk.num_dofs, generator=g))
    v = V(torch.cat([theta[:1], worse]))
    assert bool((v[1:] > v[0]).all())


def test_gradcheck(scene):
    sk, body, rig, theta = scene
    body, rig, sk = (copy.deepcopy(m).double() for m in (body, rig, sk))
    term = SilhouetteNoiseLikelihood(body, rig, stride=12, width_px=2.0).double()
    frame = _noisy(body, rig, theta[:1], [0.1, 0.1], [0.1, 0.1], 5)[0]
    obs = term.prepare(frame)
    names = ("logit_fp", "logit_fn", "log_width")

    def f(*params):
        return torch.func.functional_call(term, dict(zip(names, params)),
                                          (Poses(theta[:1].double(), sk), obs))

    args = tuple(getattr(term, n).detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(f, args)


def test_dropped_views_are_not_scored(scene):
    sk, body, rig, theta = scene
    frame = _noisy(body, rig, theta[:1], [0.05, 0.05], [0.05, 0.05], 6)[0]
    term = SilhouetteNoiseLikelihood(body, rig, stride=4)
    both = FrameEnergy(term, term.prepare(frame), sk)(theta[:1])
    frame.view_dropped = torch.tensor([False, True])
    one = FrameEnergy(term, term.prepare(frame), sk)(theta[:1])
    single = SilhouetteNoiseLikelihood(body, rig.subset([0]), stride=4)
    alone = FrameEnergy(single, single.prepare(Frame(0, 0.0,
                                                     silhouettes=frame.silhouettes[:1])), sk)
    torch.testing.assert_close(one, alone(theta[:1]))
    assert float(one) < float(both)


@pytest.mark.parametrize("kw,match", [({"false_positive": 0.5}, "false_positive"),
                                      ({"false_negative": 0.0}, "false_negative"),
                                      ({"width_px": -1.0}, "width_px"),
                                      ({"stride": 0}, "stride")])
def test_bad_settings_are_named(scene, kw, match):
    sk, body, rig, theta = scene
    with pytest.raises(ValueError, match=match):
        SilhouetteNoiseLikelihood(body, rig, **kw)
