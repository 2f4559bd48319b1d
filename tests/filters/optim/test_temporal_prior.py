"""Gaussian temporal prior: precision, wrapping, gradient; anneal's untempered log-prior against
the closed-form posterior of a quadratic energy; AnnealedInference keeps the predicted mode of a
bimodal energy."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from torchmocap.filters import AnnealedInference, WeightedMeanEstimator
from torchmocap.filters.optim.anneal import anneal
from torchmocap.filters.optim.temporal_prior import TemporalPrior, temporal_prior_precision
from torchmocap.proposals import GaussianDiffusionProposal, PreviousFrame, ProposalContext

F64 = torch.float64


def test_precision_and_wrapping():
    prec = temporal_prior_precision(5, [0, 1], 20.0, 0.1, dtype=F64)
    torch.testing.assert_close(prec, torch.tensor([100.0, 100.0] + [1 / math.radians(20) ** 2]
                                                  * 3, dtype=F64))
    rot = torch.tensor([False, False, True, True, True])
    mean = torch.tensor([0.0, 0.0, 3.1, 0.0, 0.0], dtype=F64)
    prior = TemporalPrior(prec, rot)
    assert torch.equal(TemporalPrior.from_stds(5, [0, 1], 20.0, 0.1).precision, prec)
    assert torch.equal(TemporalPrior.from_stds(5, [0, 1], 20.0, 0.1).rotation, rot)
    x = torch.tensor([[0.1, 0.0, -3.1, 0.0, 0.0],     # across the seam: 0.083 rad, not 6.2
                      [0.0, 0.0, 3.1, 2 * math.pi, 0.0]], dtype=F64)  # a full turn: no cost
    d = 2 * math.pi - 6.2
    want = torch.tensor([0.5 * (100 * 0.01 + prec[2] * d * d), 0.0], dtype=F64)
    torch.testing.assert_close(prior.energy(x, mean), want)
    torch.testing.assert_close(prior.log_prob(x.float(), mean), -want)
    xg = (mean + 0.3 * torch.randn(4, 5, dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: prior.energy(y, mean), (xg,))
    # the analytic gradient equals autograd's
    g_auto, = torch.autograd.grad(prior.energy(xg, mean).sum(), xg)
    torch.testing.assert_close(prior.gradient(xg.detach(), mean), g_auto)
    with pytest.raises(ValueError, match="std_deg"):
        temporal_prior_precision(5, [], 0.0, 0.1)
    with pytest.raises(ValueError, match="translation_std"):
        temporal_prior_precision(5, [], 10.0, float("nan"))
    with pytest.raises(ValueError, match="precision, rotation"):
        TemporalPrior(prec[:3], rot)
    with pytest.raises(ValueError, match="rotation: expected a bool"):
        TemporalPrior(prec, rot.float())


def test_anneal_log_prior_is_untempered_closed_form():
    """One layer from uniform particles with beta fixed to 2: the weights target
    exp(-2 (x - a)^2 / 2) N(x; b, s^2), a Gaussian with precision 2 + 1/s^2 and mean
    (2 a + b / s^2) / (2 + 1/s^2) — the prior enters once, not multiplied by beta."""
    a, b, s = 0.5, -0.5, 0.5
    post_prec = 2.0 + 1 / s**2
    post_mean = (2 * a + b / s**2) / post_prec
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        x = (torch.rand(200_000, 1, generator=g, dtype=F64) * 8 - 4)
        res = anneal(lambda y: 0.5 * (y[:, 0] - a) ** 2, x, layers=1,
                     schedule=lambda k, v: torch.tensor(2.0, dtype=F64), generator=g,
                     log_prior=lambda y: -0.5 * ((y[:, 0] - b) / s) ** 2)
        w = res.log_weights.exp()
        m = float((w * res.particles[:, 0]).sum())
        var = float((w * (res.particles[:, 0] - m) ** 2).sum())
        assert m == pytest.approx(post_mean, abs=0.01)
        assert var == pytest.approx(1 / post_prec, rel=0.03)
    with pytest.raises(ValueError, match="log_prior"):
        anneal(lambda y: y[:, 0] ** 2, torch.zeros(5, 1, dtype=F64), layers=1,
               log_prior=lambda y: torch.zeros(3, dtype=F64))


def _bimodal(x):
    """Two equally deep minima at x0 = +-1 (the other coordinate quadratic)."""
    return 20 * (x[:, 0] ** 2 - 1) ** 2 + x[:, 1] ** 2


def test_annealed_inference_prior_keeps_the_predicted_mode():
    """The energy cannot choose between x0 = -1 and +1: from a prediction at +0.2 the plain
    annealer keeps both modes and its weighted mean falls between them. With the prior about
    the prediction (0.7 rad) the particles hold the +1 mode and the estimate is at it, in every
    seed."""
    sk = SimpleNamespace(num_dofs=2, translation_dofs=[])
    prop = GaussianDiffusionProposal(torch.full((2,), 1.0))
    ctx = ProposalContext(torch.tensor([0.2, 0.0], dtype=F64))
    plain = AnnealedInference(layers=8)
    prior = AnnealedInference(layers=8, prior_std_deg=math.degrees(0.7), skeleton=sk)
    for seed in range(8):
        a = plain(_bimodal, prop, WeightedMeanEstimator(), ctx, 300,
                  torch.Generator().manual_seed(seed))
        b = prior(_bimodal, prop, WeightedMeanEstimator(), ctx, 300,
                  torch.Generator().manual_seed(seed))
        assert abs(float(a.estimate[0])) < 0.5
        assert float(a.particles[:, 0].sign().mean()) < 0.5
        assert 0.9 < float(b.estimate[0]) < 1.1
        assert float(b.particles[:, 0].sign().mean()) > 0.9
    assert "prior_std_deg=40" in repr(prior)
    with pytest.raises(ValueError, match="skeleton: required with prior_std_deg"):
        AnnealedInference(prior_std_deg=20.0)


def test_prior_mean_last_estimate_centres_on_the_previous_estimate():
    """The same energy with the prediction on the -1 side and the previous estimate on the +1
    side: the prior follows whichever ``prior_mean`` names."""
    sk = SimpleNamespace(num_dofs=2, translation_dofs=[])
    prop = GaussianDiffusionProposal(torch.full((2,), 1.0))
    ctx = ProposalContext(torch.tensor([-0.3, 0.0], dtype=F64))
    ctx.previous_frame = PreviousFrame(estimate=torch.tensor([0.3, 0.0], dtype=F64))
    on_pred = AnnealedInference(layers=8, prior_std_deg=math.degrees(0.7), skeleton=sk)
    on_last = AnnealedInference(layers=8, prior_std_deg=math.degrees(0.7), skeleton=sk,
                                prior_mean="last_estimate")
    for seed in range(3):
        a = on_pred(_bimodal, prop, WeightedMeanEstimator(), ctx, 300,
                    torch.Generator().manual_seed(seed))
        b = on_last(_bimodal, prop, WeightedMeanEstimator(), ctx, 300,
                    torch.Generator().manual_seed(seed))
        assert -1.1 < float(a.estimate[0]) < -0.9
        assert 0.9 < float(b.estimate[0]) < 1.1
    with pytest.raises(ValueError, match="prior_mean"):
        AnnealedInference(prior_mean="mode")


def test_prior_mean_fraction_blends_along_the_shorter_arc():
    """``prior_mean=a``: the point ``a`` of the way from the previous estimate to the prediction;
    a rotation crossing ±π goes the short way, a translation linearly; 0 and 1 are the named
    centres."""
    sk = SimpleNamespace(num_dofs=3, translation_dofs=[0])
    ctx = ProposalContext(torch.tensor([1.0, -3.0, 0.2], dtype=F64))  # the prediction
    ctx.previous_frame = PreviousFrame(estimate=torch.tensor([0.0, 3.0, 0.4], dtype=F64))
    half = AnnealedInference(prior_std_deg=30.0, skeleton=sk, prior_mean=0.5)
    c = half.prior_centre(ctx)
    gap = 2 * math.pi - 6.0  # 3.0 -> -3.0 the short way, through pi
    assert torch.allclose(c, torch.tensor([0.5, 3.0 + gap / 2, 0.3], dtype=F64))
    for a, name in ((0.0, "last_estimate"), (1.0, "prediction")):
        x = AnnealedInference(prior_std_deg=30.0, skeleton=sk, prior_mean=a).prior_centre(ctx)
        y = AnnealedInference(prior_std_deg=30.0, skeleton=sk, prior_mean=name).prior_centre(ctx)
        assert torch.equal(x, y)
    assert torch.equal(AnnealedInference(prior_std_deg=30.0, skeleton=sk, prior_mean=1.0)
                       .prior_centre(ctx), ctx.previous)
    for bad in (-0.1, 1.5, True, "half"):
        with pytest.raises(ValueError, match="prior_mean"):
            AnnealedInference(prior_mean=bad)
