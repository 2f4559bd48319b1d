"""SIRInference against the exact Kalman filter of a linear-Gaussian model: posterior means,
variances and interval coverage, the evidence estimate, and the correction factor of a proposal
that is not the prior; the angular prior's densities."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.filters import SIRInference, SystematicResampler, WeightedMeanEstimator
from torchmocap.proposals import PreviousFrame, Proposal, ProposalContext, Proposed

F64 = torch.float64
Q, R = 0.3**2, 0.5**2  # random-walk and observation variances


class RandomWalk(Proposal):
    """x_t = x_{t-1} + N(0, (scale * sqrt(Q))^2); reports log_q and the prior's log density."""

    def __init__(self, scale: float = 1.0):
        super().__init__()
        self.scale = scale

    def sample(self, context, num, generator=None):
        prev = context.previous
        eps = torch.randn(prev.shape, generator=generator, dtype=F64)
        s_q = self.scale * math.sqrt(Q)
        x = prev + s_q * eps
        d = (x - prev)[:, 0]
        log_q = -0.5 * (d / s_q) ** 2 - math.log(s_q) - 0.5 * math.log(2 * math.pi)
        log_p = -0.5 * d**2 / Q - 0.5 * math.log(Q) - 0.5 * math.log(2 * math.pi)
        return Proposed(x, log_q=log_q, log_prior=log_p if self.scale != 1.0 else None)


def _kalman(z):
    m, P, logz = 0.0, 0.0, 0.0
    out = []
    for zt in z:
        P = P + Q
        S = P + R
        logz += -0.5 * (zt - m) ** 2 / S - 0.5 * math.log(2 * math.pi * S)
        K = P / S
        m, P = m + K * (zt - m), (1 - K) * P
        out.append((m, P))
    return out, logz


def _run_sir(z, num, seed, proposal):
    inf = SIRInference(selection=SystematicResampler(), ess_threshold=0.5)
    g = torch.Generator().manual_seed(seed)
    parts, lw, logz, out = None, None, 0.0, []
    for zt in z:
        def V(x, zt=zt):
            return 0.5 * (x[:, 0] - zt) ** 2 / R + 0.5 * math.log(2 * math.pi * R)

        ctx = ProposalContext(torch.zeros(1, dtype=F64),
                              previous_frame=PreviousFrame(particles=parts, log_weights=lw))
        res = inf(V, proposal, WeightedMeanEstimator(), ctx, num, g)
        parts, lw = res.particles, res.log_weights
        w = lw.exp()
        m = float((w * parts[:, 0]).sum())
        out.append((m, float((w * (parts[:, 0] - m) ** 2).sum())))
        logz += res.info["log_evidence"]
    return out, logz


@pytest.mark.parametrize("scale", [1.0, 2.0])  # bootstrap, and a 2x wider proposal corrected
def test_sir_matches_the_kalman_filter(scale):
    g = torch.Generator().manual_seed(0)
    ratios, covered, total = [], 0, 0
    for d in range(12):
        x = torch.cumsum(torch.randn(8, generator=g, dtype=F64) * math.sqrt(Q), 0)
        z = (x + torch.randn(8, generator=g, dtype=F64) * math.sqrt(R)).tolist()
        exact, logz = _kalman(z)
        sir, logz_hat = _run_sir(z, 3000, d, RandomWalk(scale))
        for (m, P), (mh, Ph), xt in zip(exact, sir, x.tolist()):
            assert mh == pytest.approx(m, abs=4 * math.sqrt(P / 3000) * 3 + 0.01)
            assert Ph == pytest.approx(P, rel=0.15)
            covered += abs(xt - mh) <= 1.96 * math.sqrt(Ph)
            total += 1
        ratios.append(math.exp(logz_hat - logz))
    assert 0.88 < covered / total <= 1.0
    # E[p_hat] = p: the ratio averages 1 (log-evidence itself is biased low)
    assert sum(ratios) / len(ratios) == pytest.approx(1.0, abs=0.05)


def test_without_the_correction_a_wide_proposal_is_wrong():
    """Control: the same wider proposal with its correction dropped misses the variance."""

    class Uncorrected(RandomWalk):
        def sample(self, context, num, generator=None):
            out = super().sample(context, num, generator)
            return Proposed(out.particles)

    g = torch.Generator().manual_seed(1)
    x = torch.cumsum(torch.randn(8, generator=g, dtype=F64) * math.sqrt(Q), 0)
    z = (x + torch.randn(8, generator=g, dtype=F64) * math.sqrt(R)).tolist()
    exact, _ = _kalman(z)
    sir, _ = _run_sir(z, 3000, 0, Uncorrected(2.0))
    assert sir[-1][1] > 1.3 * exact[-1][1]


def test_first_frame_and_info():
    inf = SIRInference()
    res = inf(lambda x: (x**2).sum(-1), RandomWalk(), WeightedMeanEstimator(),
              ProposalContext(torch.ones(1, dtype=F64)), 100,
              torch.Generator().manual_seed(0))
    assert res.particles.shape == (100, 1) and res.info["resampled"]
    assert 0 < res.info["ess_fraction"] <= 1 and len(res.info["ess"]) == 1
    with pytest.raises(ValueError, match="ess_threshold"):
        SIRInference(ess_threshold=1.5)
    with pytest.raises(ValueError, match="every particle"):
        inf(lambda x: torch.full((x.shape[0],), math.inf, dtype=F64), RandomWalk(),
            WeightedMeanEstimator(), ProposalContext(torch.ones(1, dtype=F64)), 10)


class TestAngularPrior:
    def test_feature_truncation_and_frozen_dofs(self):
        from torchmocap.proposals import AngularPriorProposal
        from torchmocap.skeleton import human31

        sk = human31().double()
        prop = AngularPriorProposal(sk, rotation_std_deg=30.0, joints="upper_body")
        th = sk.zero_pose(dtype=F64)
        e = sk.dof_index("l_elbow_flex")
        out = prop.sample(ProposalContext(th), 4000, torch.Generator().manual_seed(0))
        x = out.particles
        assert bool(sk.within_limits(x).all())  # truncated, not clamped:
        assert float((x[:, e] == 0).float().mean()) < 0.01  # no mass piled on the 0 limit
        frozen = [d for d in range(31) if d not in prop.free.tolist()]
        assert torch.equal(x[:, frozen], th[frozen].expand(4000, -1))
        assert sk.dof_index("l_hip_flex") in frozen and e in prop.free.tolist()
        assert torch.allclose(out.log_q, out.log_prior)  # the proposal is the prior

    def test_feature_importance_weights_are_unbiased(self):
        """E_q[(p/q) f] = E_p[f] for a proposal wider than the prior (prior_scale 0.5)."""
        from torchmocap.proposals import AngularPriorProposal
        from torchmocap.skeleton import human31

        sk = human31().double()
        th = sk.zero_pose(dtype=F64)
        e = sk.dof_index("l_elbow_flex")
        th[e] = 0.3
        wide = AngularPriorProposal(sk, rotation_std_deg=20.0, joints=["l_elbow"],
                                    prior_scale=0.5)
        narrow = AngularPriorProposal(sk, rotation_std_deg=10.0, joints=["l_elbow"])
        g = torch.Generator().manual_seed(1)
        q = wide.sample(ProposalContext(th), 200000, g)
        w = (q.log_prior - q.log_q).exp()
        est = float((w * q.particles[:, e]).mean())
        ref = float(narrow.sample(ProposalContext(th), 200000, g).particles[:, e].mean())
        assert est == pytest.approx(ref, abs=0.002)
        assert float(w.mean()) == pytest.approx(1.0, abs=0.01)
