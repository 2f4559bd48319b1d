"""Inference modules (annealing with a proposal as mutation kernel, local descent), diffusion
rules and estimators: their contracts, closed forms and a quadratic that a broken one misses."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.filters import (
    AnnealedInference,
    BestParticleEstimator,
    LocalInference,
    ManifoldMeanEstimator,
    ShrinkingDiffusion,
    SpreadDiffusion,
    TemporalMapEstimator,
    WeightedMeanEstimator,
)
from torchmocap.filters.optim.resampling import SystematicResampler
from torchmocap.filters.optim.schedules import ESSSchedule
from torchmocap.ik import SensorManifold
from torchmocap.proposals import GaussianDiffusionProposal, PreviousFrame, ProposalContext, Proposed
from torchmocap.skeleton import human31

F64 = torch.float64


class RecordingProposal(GaussianDiffusionProposal):
    """A Gaussian diffusion that records the std it was asked to use per call."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.calls = []

    def sample(self, context, num, generator=None):
        self.calls.append((None if context.std is None else context.std.clone(), context.scale,
                           tuple(context.previous.shape)))
        out = super().sample(context, num, generator)
        return Proposed(out.particles, stats={"tries": num, "accepted": num // 2,
                                              "filled": 0.5})


def _quadratic(target):
    def V(x):
        return ((x - target) ** 2).sum(-1)

    return V


def test_annealed_inference_finds_the_minimum_of_a_quadratic():
    target = torch.tensor([0.4, -0.3, 0.2, 0.1], dtype=F64)
    prop = GaussianDiffusionProposal(torch.full((4,), 0.3))
    inf = AnnealedInference(layers=15)
    errs = []
    for seed in range(3):
        res = inf(_quadratic(target), prop, WeightedMeanEstimator(),
                  ProposalContext(torch.zeros(4, dtype=F64)), 300,
                  torch.Generator().manual_seed(seed))
        errs.append(float((res.estimate - target).norm()))
        assert res.particles.shape == (300, 4) and res.log_weights.shape == (300,)
        assert len(res.info["beta"]) == 15 and len(res.info["ess"]) == 15
        assert torch.exp(res.log_weights).sum().item() == pytest.approx(1.0)
    start = float(target.norm())
    assert max(errs) < 0.1 * start, errs  # one layer (no annealing) stays at ~start


def test_annealed_inference_hands_layer_stds_to_the_proposal():
    prop = RecordingProposal(torch.full((3,), 0.2))
    inf = AnnealedInference(layers=5, diffusion=SpreadDiffusion(rho=0.5, decay=0.5))
    inf(_quadratic(torch.zeros(3)), prop, WeightedMeanEstimator(),
        ProposalContext(torch.ones(3)), 100, torch.Generator().manual_seed(0))
    assert len(prop.calls) == 5  # layer 0 + 4 mutations
    assert prop.calls[0][0] is None and prop.calls[0][2] == (3,)  # own std around the start
    assert all(c[0] is not None and c[0].shape == (3,) and c[2] == (100, 3)
               for c in prop.calls[1:])
    # diffusion cools: the std handed over shrinks across layers
    stds = [float(c[0].mean()) for c in prop.calls[1:]]
    assert stds[-1] < 0.5 * stds[0]
    prop2 = RecordingProposal(torch.full((3,), 0.2))
    AnnealedInference(layers=4, diffusion=ShrinkingDiffusion(0.5))(
        _quadratic(torch.zeros(3)), prop2, WeightedMeanEstimator(),
        ProposalContext(torch.ones(3)), 50, torch.Generator().manual_seed(0))
    assert [c[1] for c in prop2.calls[1:]] == [1.0, 0.5, 0.25]


def test_annealed_inference_summarises_proposal_statistics():
    prop = RecordingProposal(torch.full((2,), 0.1))
    res = AnnealedInference(layers=3)(_quadratic(torch.zeros(2)), prop,
                                      WeightedMeanEstimator(), ProposalContext(torch.ones(2)),
                                      40, torch.Generator().manual_seed(0))
    st = res.info["proposal"]
    assert st["tries"] == 120 and st["accepted"] == 60
    assert st["acceptance_rate"] == pytest.approx(0.5) and st["filled_min"] == 0.5


def test_rounds_keep_the_best_and_shrink_the_spread():
    target = torch.tensor([2.0, -1.0], dtype=F64)
    prop = RecordingProposal(torch.full((2,), 1.0))
    res = AnnealedInference(layers=4, rounds=3, round_scale=0.5)(
        _quadratic(target), prop, WeightedMeanEstimator(), ProposalContext(torch.zeros(2,
                                                                           dtype=F64)),
        100, torch.Generator().manual_seed(1))
    starts = [c for c in prop.calls if c[0] is None and c[2] == (2,)]
    assert [c[1] for c in starts] == [1.0, 0.5, 0.25]
    assert res.info["rounds"] == 3 and len(res.info["beta"]) == 12
    assert float((res.estimate - target).norm()) < 0.3


def test_refine_descends_from_the_annealed_estimate_and_keeps_the_annealers_particles():
    """Global search then local refinement: the estimate is the refined one (much closer to
    the minimum than the 3-layer anneal alone), the particles and weights carried to the next
    frame are exactly the annealer's."""
    from types import SimpleNamespace

    target = torch.tensor([0.5, -0.4, 0.3, 0.2], dtype=F64)
    box = SimpleNamespace(lower=torch.full((4,), -2.0, dtype=F64),
                          upper=torch.full((4,), 2.0, dtype=F64))
    prop = GaussianDiffusionProposal(torch.full((4,), 0.3))
    ctx = ProposalContext(torch.zeros(4, dtype=F64))
    plain = AnnealedInference(layers=3)
    refined = AnnealedInference(layers=3, refine=LocalInference(box, iterations=300, lr=0.02))
    for seed in range(3):
        a = plain(_quadratic(target), prop, WeightedMeanEstimator(), ctx, 50,
                  torch.Generator().manual_seed(seed))
        b = refined(_quadratic(target), prop, WeightedMeanEstimator(), ctx, 50,
                    torch.Generator().manual_seed(seed))
        err_a = float((a.estimate - target).norm())
        err_b = float((b.estimate - target).norm())
        assert err_a > 0.02 and err_b < 0.2 * err_a, (err_a, err_b)
        assert torch.equal(a.particles, b.particles)
        assert torch.equal(a.log_weights, b.log_weights)
        assert b.info["refine"]["final_energy"] < b.info["refine"]["start_energy"]
        assert b.info["refine"]["start_energy"] == pytest.approx(
            float(_quadratic(target)(a.estimate[None])[0]))
    with pytest.raises(TypeError, match="refine"):
        AnnealedInference(refine="adam")


def _tilted_double_well(x):
    """``(x0² − 1)² + 0.3 x0 + Σ_{i>0} x_i²``: global minimum near x0 = −1.04, a local one
    near x0 = +0.96."""
    return (x[..., 0] ** 2 - 1) ** 2 + 0.3 * x[..., 0] + (x[..., 1:] ** 2).sum(-1)


def test_local_inference_descends_every_start_and_keeps_the_lowest():
    from types import SimpleNamespace

    box = SimpleNamespace(lower=torch.full((3,), -3.0, dtype=F64),
                          upper=torch.full((3,), 3.0, dtype=F64))
    loc = LocalInference(box, iterations=300, lr=0.02)
    prop = GaussianDiffusionProposal(torch.full((3,), 0.1))
    one = loc(_tilted_double_well, prop, WeightedMeanEstimator(),
              ProposalContext(torch.tensor([0.9, 0.2, -0.1], dtype=F64)), 1)
    assert float(one.estimate[0]) == pytest.approx(0.96, abs=0.02)  # the local minimum
    starts = torch.tensor([[0.9, 0.2, -0.1], [-0.8, 0.1, 0.3]], dtype=F64)
    two = loc(_tilted_double_well, prop, WeightedMeanEstimator(), ProposalContext(starts), 1)
    assert float(two.estimate[0]) == pytest.approx(-1.04, abs=0.02)  # the global one
    assert two.particles.shape == (2, 3) and two.info["start"] == 1
    assert two.info["final_energy"] == pytest.approx(
        float(_tilted_double_well(two.estimate)))


def test_refine_from_the_prediction_too_leaves_the_annealers_wrong_basin():
    """The previous frame's particles sit in the local basin (x0 ≈ +1), the prediction in the
    global one: refined from the annealed estimate alone the track stays in the local minimum;
    with ``refine_from="estimate_and_prediction"`` the lower of the two descents is kept."""
    from types import SimpleNamespace

    box = SimpleNamespace(lower=torch.full((3,), -3.0, dtype=F64),
                          upper=torch.full((3,), 3.0, dtype=F64))
    prop = GaussianDiffusionProposal(torch.full((3,), 0.05))
    pred = torch.tensor([-0.9, 0.0, 0.0], dtype=F64)
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        parts = torch.tensor([1.0, 0.0, 0.0], dtype=F64) + 0.05 * torch.randn(
            50, 3, generator=g, dtype=F64)
        ctx = ProposalContext(pred, previous_frame=PreviousFrame(particles=parts, estimate=pred))
        x0, starts, wins = {}, {}, {}
        for start in ("estimate", "estimate_and_prediction", ("last_estimate", "estimate"),
                      ("estimate", "prediction", "last_estimate"), "prediction"):
            inf = AnnealedInference(layers=3, propagate="particles", refine_from=start,
                                    refine=LocalInference(box, iterations=300, lr=0.02))
            res = inf(_tilted_double_well, prop, WeightedMeanEstimator(), ctx, 50,
                      torch.Generator().manual_seed(seed))
            x0[start] = float(res.estimate[0])
            starts[start] = res.info["refine"]["start"]
            wins[start] = {k: v for k, v in res.info["refine"].items() if k.startswith("from_")}
            assert float(res.particles[:, 0].mean()) > 0.5  # the annealer's set: kept as is
        assert x0["estimate"] == pytest.approx(0.96, abs=0.05), x0
        for start in ("estimate_and_prediction", ("last_estimate", "estimate"),
                      ("estimate", "prediction", "last_estimate"), "prediction"):
            assert x0[start] == pytest.approx(-1.04, abs=0.05), x0
        # the index of the winning start follows the order of refine_from
        assert starts["estimate_and_prediction"] == 1
        assert starts[("last_estimate", "estimate")] == 0
        assert starts[("estimate", "prediction", "last_estimate")] in (1, 2)
        assert (wins["estimate_and_prediction"]["from_estimate"],
                wins["estimate_and_prediction"]["from_prediction"]) == (0.0, 1.0)
        assert wins["estimate"] == {"from_estimate": 1.0}
    for bad in ("predicted", ("estimate", "estimate"), ()):
        with pytest.raises(ValueError, match="refine_from"):
            AnnealedInference(refine_from=bad)


def test_refine_starts_are_stacked_in_the_order_asked_for():
    est, pred, last = (torch.full((3,), v, dtype=F64) for v in (1.0, 2.0, 3.0))
    inf = AnnealedInference(refine_from=["last_estimate", "estimate", "prediction"])
    ctx = ProposalContext(pred, previous_frame=PreviousFrame(estimate=last))
    rows, names = inf._refine_starts(est, ctx)
    assert rows[:, 0].tolist() == [3.0, 1.0, 2.0]
    assert names == ["last_estimate", "estimate", "prediction"]
    # the first frame of a track without a last estimate, or a batched prediction: left out
    rows, names = inf._refine_starts(est, ProposalContext(pred))
    assert rows[:, 0].tolist() == [1.0, 2.0] and names == ["estimate", "prediction"]
    batched = ProposalContext(pred.expand(4, 3), previous_frame=PreviousFrame(estimate=last))
    assert inf._refine_starts(est, batched)[0][:, 0].tolist() == [3.0, 1.0]
    rows, names = AnnealedInference(refine_from="prediction")._refine_starts(
        est, ProposalContext(pred.expand(4, 3)))
    assert rows.tolist() == est.tolist() and names == ["estimate"]


def test_spread_diffusion_closed_form():
    x = torch.tensor([[0.0, 1.0], [2.0, 1.0], [4.0, 1.0]], dtype=F64)
    d = SpreadDiffusion(rho=0.5, decay=0.5, delta=1e-8)
    std = d(x, 2, 15, None)["std"]
    assert std.tolist() == pytest.approx([math.sqrt(0.5 * 0.25 * 4.0 + 1e-8), 1e-4])
    default = SpreadDiffusion()(x, 13, 15, None)["std"]  # decay 0.1^(1/13): 10x over 13 steps
    assert default[0].item() == pytest.approx(math.sqrt(0.5 * 0.1 * 4.0 + 1e-8))
    with pytest.raises(ValueError, match="rho"):
        SpreadDiffusion(rho=0)
    with pytest.raises(ValueError, match="decay"):
        ShrinkingDiffusion(1.5)


def test_inference_settings_are_objects_or_names():
    inf = AnnealedInference(layers=3, schedule=ESSSchedule(0.3), selection=SystematicResampler())
    assert "ESSSchedule(alpha=0.3" in repr(inf) and "Systematic" in repr(inf)
    with pytest.raises(ValueError, match="layers"):
        AnnealedInference(layers=0)
    with pytest.raises(TypeError, match="schedule"):
        AnnealedInference(schedule="ess")
    with pytest.raises(TypeError, match="selection"):
        AnnealedInference(selection="multinomial")
    with pytest.raises(ValueError, match="round_scale"):
        AnnealedInference(round_scale=0)


def test_local_inference_descends_and_respects_limits():
    sk = human31().double()
    target = sk.zero_pose(dtype=F64)
    target[sk.dof_index("l_elbow_flex")] = 0.7
    target[sk.dof_index("r_knee_flex")] = 3.0  # beyond the 135 deg limit

    def V(x):
        return ((x - target) ** 2).sum(-1)

    inf = LocalInference(sk, method="lbfgs", iterations=30)
    res = inf(V, GaussianDiffusionProposal(torch.full((31,), 0.1)), WeightedMeanEstimator(),
              ProposalContext(sk.zero_pose(dtype=F64)), 1)
    assert res.estimate[sk.dof_index("l_elbow_flex")].item() == pytest.approx(0.7, abs=1e-6)
    assert res.estimate[sk.dof_index("r_knee_flex")].item() == pytest.approx(
        float(sk.upper[sk.dof_index("r_knee_flex")]), abs=1e-6)
    assert res.info["final_energy"] < res.info["start_energy"]
    multi = LocalInference(sk, method="adam", iterations=5, lr=0.05, starts=4)(
        V, GaussianDiffusionProposal(torch.full((31,), 0.1)), WeightedMeanEstimator(),
        ProposalContext(sk.zero_pose(dtype=F64)), 1, torch.Generator().manual_seed(0))
    assert multi.particles.shape == (4, 31)
    with pytest.raises(ValueError, match="method"):
        LocalInference(sk, method="sgd")
    with pytest.raises(ValueError, match="starts"):
        LocalInference(sk, starts=0)


class TestEstimators:
    def test_weighted_mean_and_best(self):
        x = torch.tensor([[0.0, 1.0], [2.0, 3.0]])
        w = torch.tensor([0.25, 0.75])
        assert WeightedMeanEstimator()(x, w).tolist() == [1.5, 2.5]
        assert BestParticleEstimator()(x, w).tolist() == [2.0, 3.0]
        with pytest.raises(ValueError, match="weights"):
            WeightedMeanEstimator()(x, torch.ones(3))

    def test_temporal_map_closed_form(self):
        """Score = log w - 1/2 sum ((x - m) / sigma)^2, rotations wrapped, translations in
        metres: equal weights pick the mode nearer the prediction; a large enough weight ratio
        overrides it (the switch point is the closed form's); no prediction = largest weight."""
        sk = human31().double()
        est = TemporalMapEstimator(sk, rotation_std_deg=10.0, translation_std=0.05)
        m = sk.zero_pose()
        i = sk.dof_index("l_shoulder_flex")
        near, far = m.clone(), m.clone()
        near[i], far[i] = math.radians(10), math.radians(-30)  # 1 and 3 sigma
        x = torch.stack([far, near])
        ctx = ProposalContext(previous=m)
        assert torch.equal(est(x, torch.tensor([0.5, 0.5], dtype=F64), ctx), near)
        # far wins once log(w_far / w_near) > (9 - 1) / 2 = 4 nats
        for ratio, winner in ((math.exp(3.9), near), (math.exp(4.1), far)):
            w = torch.tensor([ratio, 1.0], dtype=F64)
            assert torch.equal(est(x, w / w.sum(), ctx), winner)
        s = est.log_scores(x, torch.tensor([0.5, 0.5], dtype=F64), m)
        assert s.tolist() == pytest.approx([math.log(0.5) - 4.5, math.log(0.5) - 0.5])
        # wrapping: 359 deg from the prediction is 1 deg away; translations use metres
        wrapped = m.clone()
        wrapped[i] = math.radians(359)
        t = sk.translation_dofs[0]
        moved = m.clone()
        moved[t] = 0.1  # 2 sigma
        s = est.log_scores(torch.stack([wrapped, moved]), torch.tensor([0.5, 0.5], dtype=F64), m)
        assert s.tolist() == pytest.approx([math.log(0.5) - 0.005, math.log(0.5) - 2.0])
        # without a prediction: the largest weight
        assert torch.equal(est(x, torch.tensor([0.6, 0.4], dtype=F64)), far)
        with pytest.raises(ValueError, match="rotation_std_deg"):
            TemporalMapEstimator(sk, rotation_std_deg=0.0)
        with pytest.raises(ValueError, match=r"context.previous: expected a \(31,\)"):
            est(x, torch.tensor([0.5, 0.5], dtype=F64), ProposalContext(previous=m[:5]))
        with pytest.raises(ValueError, match="weights"):
            est(x, torch.ones(3, dtype=F64), ctx)

    def test_root_rotation_mean_on_so3(self):
        """Headings of +179 and -179 deg average to 180, not to 0."""
        sk = human31()
        x = sk.zero_pose((2,))
        rz = sk.dof_index("pelvis_rz")
        x[0, rz], x[1, rz] = math.radians(179), math.radians(-179)
        w = torch.tensor([0.5, 0.5])
        est = WeightedMeanEstimator(sk, rotation_groups=True)(x, w)
        assert abs(abs(est[rz].item()) - math.pi) < 1e-4
        assert abs(WeightedMeanEstimator()(x, w)[rz].item()) < 1e-6  # the naive mean
        with pytest.raises(ValueError, match="skeleton"):
            WeightedMeanEstimator(rotation_groups=True)

    def test_manifold_mean_lies_on_the_manifold(self):
        sk = human31().double()
        m = SensorManifold(sk).double()
        g = torch.Generator().manual_seed(0)
        th = sk.zero_pose(dtype=F64) + 0.1 * torch.randn(31, generator=g, dtype=F64)
        th = sk.clamp(th)
        sensors = m.sensor_orientations(th)
        parts = m.inverse(m(th) + 0.05 * torch.randn(50, m.num_active, generator=g,
                                                    dtype=F64), sensors).theta
        w = torch.softmax(torch.randn(50, generator=g, dtype=F64), 0)
        est = ManifoldMeanEstimator(m)(parts, w, ProposalContext(th, sensors=sensors))
        assert torch.allclose(m(est), (w[:, None] * m(parts)).sum(0))
        from torchmocap.geometry import geodesic_angle

        err = geodesic_angle(m.bone_orientations(est), m.bone_orientations(th))
        assert float(err.max()) < 1e-9  # the sensors are met exactly
        with pytest.raises(ValueError, match="sensors"):
            ManifoldMeanEstimator(m)(parts, w, ProposalContext(th))


class TestFidelityOptions:
    def test_rotation_mean_and_all_joint_groups(self):
        from torchmocap.geometry import rotation_mean, so3_exp

        g = torch.Generator().manual_seed(0)
        base = so3_exp(torch.randn(3, generator=g, dtype=F64))
        d = so3_exp(0.05 * torch.randn(500, 3, generator=g, dtype=F64))
        R = base @ d
        assert float((rotation_mean(R) - base).abs().max()) < 0.01
        w = torch.zeros(500, dtype=F64)
        w[7] = 1.0
        assert torch.allclose(rotation_mean(R, w), R[7], atol=1e-12)
        with pytest.raises(ValueError, match="weights"):
            rotation_mean(R, -w)
        sk = human31()
        x = sk.zero_pose((2,))
        sh = sk.joint_dofs("l_shoulder")
        x[0, sh] = torch.tensor([0.3, 1.2, -0.4])
        x[1, sh] = torch.tensor([0.3, 1.2, 0.4])
        est = WeightedMeanEstimator(sk, rotation_groups="all")(x, torch.tensor([0.5, 0.5]))
        assert est[sh].tolist() == pytest.approx([0.3, 1.2, 0.0], abs=0.02)
        with pytest.raises(ValueError, match="rotation_groups"):
            WeightedMeanEstimator(sk, rotation_groups="some")

    def test_manifold_mean_of_the_particles_noisy_sensors(self):
        """Eq. 18: with sensors='particles' the estimate keeps the particles' sensor draws."""
        sk = human31().double()
        m = SensorManifold(sk).double()
        th = sk.zero_pose(dtype=F64)
        th[sk.joint_dofs("l_elbow")] = 0.5
        meas = m.sensor_orientations(th)
        tilted = th.clone()
        tilted[sk.joint_dofs("l_shoulder")] = torch.tensor([0.2, 0.1, 0.0], dtype=F64)
        parts = tilted.expand(10, 31).clone()  # every particle drew the same tilted sensors
        w = torch.full((10,), 0.1, dtype=F64)
        ctx = ProposalContext(th, sensors=meas)
        from torchmocap.filters import ManifoldMeanEstimator

        e_meas = ManifoldMeanEstimator(m, "measured")(parts, w, ctx)
        e_part = ManifoldMeanEstimator(m, "particles")(parts, w, ctx)
        assert torch.allclose(e_part, tilted, atol=1e-9)
        assert not torch.allclose(e_meas, tilted, atol=1e-3)  # snaps back to the measurement
        with pytest.raises(ValueError, match="sensors"):
            ManifoldMeanEstimator(m, "mean")

    def test_propagation_and_motion_scaled_start(self):
        prop = RecordingProposal(torch.full((2,), 0.1))
        last = torch.zeros(2)
        pred = torch.tensor([0.5, 0.0])
        parts = torch.randn(30, 2, generator=torch.Generator().manual_seed(0))
        past = PreviousFrame(estimate=last, particles=parts, log_weights=torch.zeros(30))
        ctx = ProposalContext(pred.clone(), previous_frame=past)
        AnnealedInference(layers=2, propagate="particles", motion_scale=1.0)(
            _quadratic(torch.zeros(2)), prop, WeightedMeanEstimator(), ctx, 30,
            torch.Generator().manual_seed(1))
        std0, _, shape0 = prop.calls[0]
        assert shape0 == (30, 2)  # layer 0 starts from the previous particle set
        assert std0.tolist() == pytest.approx([math.hypot(0.1, 0.5), 0.1], rel=1e-5)
        with pytest.raises(ValueError, match="propagate"):
            AnnealedInference(propagate="none")

    def test_spread_floor(self):
        prop = GaussianDiffusionProposal(torch.full((2,), 0.2))
        x = torch.zeros(50, 2, dtype=F64)  # a collapsed cloud
        std = SpreadDiffusion(floor=0.25)(x, 5, 15, prop)["std"]
        assert std.tolist() == pytest.approx([0.05, 0.05])


def test_joint_limit_energy():
    from torchmocap.likelihoods import JointLimitLikelihood, Poses

    sk = human31()
    lik = JointLimitLikelihood(sk, scale_deg=5.0)
    th = sk.zero_pose((3,))
    e = sk.dof_index("l_elbow_flex")
    th[1, e] = float(sk.upper[e]) + math.radians(10.0)
    th[2, e] = float(sk.lower[e]) - math.radians(5.0)
    v = lik.energy(Poses(th, sk), None)
    assert v.tolist() == pytest.approx([0.0, 4.0, 1.0], rel=1e-4)
    assert lik.requires == ()
    with pytest.raises(ValueError, match="scale_deg"):
        JointLimitLikelihood(sk, scale_deg=0)
