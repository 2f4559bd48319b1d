"""The angular prior's speed-adaptive spread (``AngularPriorProposal(speed_gain=g)``): the
counterpart of the spatial prior's, so that both priors can follow fast limbs in an ablation."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.proposals import AngularPriorProposal, PreviousFrame, ProposalContext
from torchmocap.skeleton import human31

F64 = torch.float64


def _history(sk, dof: str, delta: float):
    prev = sk.zero_pose().double()
    last = prev.clone()
    last[sk.dof_index(dof)] += delta
    return last, torch.stack([prev, last])


def test_spread_closed_form_and_only_the_moving_dof_widens():
    """σ = 5°, g = 0.5, the elbow moved 0.6 rad and the pelvis yaw wrapped from +3.1 to -3.1
    rad (0.083 rad the short way): their stds are sqrt(σ² + (g Δ)²); every other DoF keeps σ."""
    sk = human31().double()
    prop = AngularPriorProposal(sk, rotation_std_deg=5.0, speed_gain=0.5).double()
    last, hist = _history(sk, "l_elbow_flex", 0.6)
    yaw = sk.dof_index("pelvis_rz")
    hist[0, yaw], hist[1, yaw] = 3.1, -3.1
    ctx = ProposalContext(last, previous_frame=PreviousFrame(history=hist))
    std = prop._spread(ctx)
    sigma = math.radians(5.0)
    free = prop.free.tolist()
    e, y = free.index(sk.dof_index("l_elbow_flex")), free.index(yaw)
    assert float(std[e]) == pytest.approx(math.hypot(sigma, 0.3), rel=1e-6)
    short = 2 * math.pi - 6.2
    assert float(std[y]) == pytest.approx(math.hypot(sigma, 0.5 * short), rel=1e-6)
    others = [i for i in range(len(free)) if i not in (e, y)]
    assert torch.allclose(std[others], prop.std[others])
    # no history (first frame) or a single estimate: the fixed spread of eq. 3
    assert torch.equal(prop._spread(ProposalContext(last)), prop.std)
    short = PreviousFrame(history=hist[:1])
    assert torch.equal(prop._spread(ProposalContext(last, previous_frame=short)),
                       prop.std)


def test_draws_follow_the_widened_spread_and_the_prior_with_them():
    """4000 draws: the elbow's sample std matches the widened spread (within 4 %), a DoF that
    did not move keeps 5°; with prior_scale 1 the prior is the proposal (log_q == log_prior)."""
    sk = human31().double()
    prop = AngularPriorProposal(sk, rotation_std_deg=5.0, speed_gain=0.5).double()
    start = sk.zero_pose().double()
    start[sk.dof_index("l_elbow_flex")] = 1.2  # far from the limits: the truncation is inert
    start[sk.dof_index("r_elbow_flex")] = 1.2
    hist = torch.stack([start.clone(), start.clone()])
    hist[0, sk.dof_index("l_elbow_flex")] -= 0.4
    ctx = ProposalContext(start, previous_frame=PreviousFrame(history=hist))
    out = prop.sample(ctx, 4000, torch.Generator().manual_seed(0))
    e = sk.dof_index("l_elbow_flex")
    want = math.hypot(math.radians(5.0), 0.2)
    assert float(out.particles[:, e].std()) == pytest.approx(want, rel=0.04)
    k = sk.dof_index("r_elbow_flex")
    assert float(out.particles[:, k].std()) == pytest.approx(math.radians(5.0), rel=0.1)
    torch.testing.assert_close(out.log_q, out.log_prior)
    # without the gain the elbow draws stay at 5°
    fixed = AngularPriorProposal(sk, rotation_std_deg=5.0).double()
    got = fixed.sample(ctx, 4000, torch.Generator().manual_seed(0)).particles[:, e].std()
    assert float(got) == pytest.approx(math.radians(5.0), rel=0.1)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), True, "0.5"])
def test_bad_speed_gain(bad):
    with pytest.raises(ValueError, match="speed_gain"):
        AngularPriorProposal(human31(), speed_gain=bad)
