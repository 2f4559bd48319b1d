"""RejectionProposal: acceptance vs an analytic probability, caps, best-so-far fill-in."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.ik import SensorManifold
from torchmocap.proposals import (
    GaussianDiffusionProposal,
    ProposalContext,
    RejectionProposal,
    SensorAngleCriterion,
)
from torchmocap.skeleton import human31

F64 = torch.float64


@pytest.fixture(scope="module")
def knees():
    """Sensors on both shanks; a diffusion that only moves the knee hinges by N(0, sigma^2):
    each shank's orientation error is exactly |delta knee|, so P(accept) = erf(t/(s sqrt2))^2."""
    sk = human31().double()
    m = SensorManifold(sk, {"l_shank": "l_knee", "r_shank": "r_knee"}).double()
    th = torch.zeros(31, dtype=F64)
    kd = sk.joint_dofs("l_knee") + sk.joint_dofs("r_knee")
    th[kd] = 1.0  # far from the limits: no clamping
    std = torch.zeros(31, dtype=F64)
    std[kd] = math.radians(10.0)
    base = GaussianDiffusionProposal(std, 31)
    return sk, m, th, base


class TestRejectionProposal:
    def test_feature_acceptance_matches_analytic(self, knees):
        sk, m, th, base = knees
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        rp = RejectionProposal(base, m, threshold_deg=10.0, max_tries=40000, batch_size=40000)
        out = rp.sample(ctx, 40000, torch.Generator().manual_seed(0))  # one batch of 40000
        p1 = math.erf(1 / math.sqrt(2))  # threshold = 1 sigma
        rate = out.stats["acceptance_rate"]
        n = out.stats["tries"]
        assert n == 40000
        se = math.sqrt(p1**2 * (1 - p1**2) / n)
        assert abs(rate - p1**2) < 4 * se, (rate, p1**2)
        ps = out.stats["per_sensor_acceptance"]
        assert torch.allclose(ps, torch.full((2,), p1, dtype=F64), atol=4 * math.sqrt(
            p1 * (1 - p1) / n))
        # filled slots really satisfy the constraint
        err = SensorAngleCriterion(m)(out.particles[out.valid], ctx)
        assert float(err.max()) <= math.radians(10.0) + 1e-12

    def test_feature_fills_all_slots(self, knees):
        sk, m, th, base = knees
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        rp = RejectionProposal(base, m, threshold_deg=10.0)
        out = rp.sample(ctx, 200, torch.Generator().manual_seed(1))
        assert out.particles.shape == (200, 31) and bool(out.valid.all())
        assert out.stats["stopped"] == "filled" and out.stats["filled"] == 1.0
        assert out.stats["accepted"] >= 200 and out.stats["rounds"] >= 1

    def test_feature_cap_returns_best_so_far(self, knees):
        sk, m, th, base = knees
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        rp = RejectionProposal(base, m, threshold_deg=0.5, max_tries=3000, batch_size=1000)
        out = rp.sample(ctx, 200, torch.Generator().manual_seed(2))
        assert out.stats["stopped"] == "max_tries" and out.stats["tries"] == 3000
        nv = int(out.valid.sum())
        assert 0 <= nv < 200 and out.stats["filled"] == nv / 200
        err = SensorAngleCriterion(m)(out.particles, ctx).max(-1).values
        assert bool((err[out.valid] <= math.radians(0.5)).all())
        assert bool((err[~out.valid] > math.radians(0.5)).all())
        # best-so-far: the worst filled-in error is small compared to typical rejections
        assert float(err[~out.valid].max()) < math.radians(5.0)
        # P(accept) = erf(0.05/sqrt2)^2 ~ 0.0016: the rate is reported even when tiny
        assert out.stats["acceptance_rate"] < 0.01

    def test_feature_time_cap_never_hangs(self, knees):
        sk, m, th, base = knees
        ctx = ProposalContext(previous=th, sensors=m.sensor_orientations(th))
        rp = RejectionProposal(base, m, threshold_deg=1e-6, max_seconds=0.2, batch_size=500)
        out = rp.sample(ctx, 50, torch.Generator().manual_seed(3))
        assert out.stats["stopped"] == "max_seconds" and not bool(out.valid.any())
        assert out.stats["seconds"] < 5.0
        assert torch.isfinite(out.particles).all()

    def test_generic_error_fn(self):
        base = GaussianDiffusionProposal(1.0, 2)
        ctx = ProposalContext(previous=torch.zeros(2, dtype=F64))

        def err(theta, context):  # accept |x| <= 1 (in "radians"): P = erf(1/sqrt2)
            return theta[:, 0].abs()

        rp = RejectionProposal(base, err, threshold_deg=math.degrees(1.0), batch_size=40000,
                               max_tries=40000)
        out = rp.sample(ctx, 40000, torch.Generator().manual_seed(4))
        p = math.erf(1 / math.sqrt(2))
        assert abs(out.stats["acceptance_rate"] - p) < 4 * math.sqrt(p * (1 - p) / 40000)

    def test_exception(self, knees):
        sk, m, th, base = knees
        with pytest.raises(ValueError, match="threshold"):
            RejectionProposal(base, m, threshold_deg=0.0)
        rp = RejectionProposal(base, m)
        with pytest.raises(ValueError, match="num"):
            rp.sample(ProposalContext(previous=th, sensors=m.sensor_orientations(th)), 0)
        with pytest.raises(ValueError, match="sensors"):
            rp.sample(ProposalContext(previous=th), 5)
