"""Mixture density propagation: Bhattacharyya reweighting (known answers), distinct minima,
Levenberg-Marquardt, energy derivatives, MixtureInference on a toy multi-modal energy (both
modes kept, top-weighted estimate, the mixture carried to the next frame), and the monocular
tracker presets kjs / css / ss on the bundled walk."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.assembly import Runtime, build_tracker, tracker_config
from torchmocap.filters import BestParticleEstimator, MixtureInference
from torchmocap.filters.optim import (
    bhattacharyya_reweight,
    distinct_minima,
    energy_derivatives,
    levenberg_marquardt,
)
from torchmocap.proposals import (
    CovarianceScaledProposal,
    GaussianDiffusionProposal,
    PreviousFrame,
    ProposalContext,
)

A = torch.tensor([1.0, 1.0])
B = torch.tensor([-1.5, -0.5])


def double_well(x):
    """-log(0.6 N(x; A, 0.2^2 I) + 0.4 N(x; B, 0.3^2 I)) up to a constant: two modes, A deeper."""
    la = math.log(0.6) - ((x - A) ** 2).sum(-1) / (2 * 0.04) - 2 * math.log(0.2)
    lb = math.log(0.4) - ((x - B) ** 2).sum(-1) / (2 * 0.09) - 2 * math.log(0.3)
    return -torch.logsumexp(torch.stack([la, lb]), 0)


class TestBhattacharyyaReweight:
    def test_feature_one_dimensional_known_answer(self):
        eye = torch.ones(2, 1, 1, dtype=torch.float64)
        new = torch.tensor([[0.0], [5.0]], dtype=torch.float64)
        prior = torch.tensor([[4.9], [0.1]], dtype=torch.float64)
        lw, a = bhattacharyya_reweight(new, eye, torch.log(torch.tensor([0.5, 0.5])).double(),
                                       prior, eye, torch.log(torch.tensor([0.2, 0.8])).double())
        assert a.tolist() == [1, 0]
        assert torch.allclose(lw.exp(), torch.tensor([0.8, 0.2], dtype=torch.float64))
        # likelihood weights multiply: 0.25 * 0.8 : 0.75 * 0.2 -> 4/7 : 3/7
        lw, _ = bhattacharyya_reweight(new, eye, torch.log(torch.tensor([0.25, 0.75])).double(),
                                       prior, eye, torch.log(torch.tensor([0.2, 0.8])).double())
        assert torch.allclose(lw.exp(), torch.tensor([4 / 7, 3 / 7], dtype=torch.float64))

    def test_feature_discard_and_covariances(self):
        # three new modes near one prior mode: with discard only the closest inherits its
        # weight, the pool is refilled for the others
        new = torch.tensor([[0.0], [0.3], [3.0]], dtype=torch.float64)
        covs = torch.ones(3, 1, 1, dtype=torch.float64)
        prior = torch.tensor([[0.05], [10.0]], dtype=torch.float64)
        pcov = torch.ones(2, 1, 1, dtype=torch.float64)
        plw = torch.log(torch.tensor([0.9, 0.1], dtype=torch.float64))
        lw0 = torch.zeros(3, dtype=torch.float64)
        lw, a = bhattacharyya_reweight(new, covs, lw0, prior, pcov, plw, discard=True)
        # pairs by increasing distance: (0, prior 0), (2, prior 1); the pool refills for 1
        assert a.tolist() == [0, 0, 1]
        lw_nd, a_nd = bhattacharyya_reweight(new, covs, lw0, prior, pcov, plw, discard=False)
        assert a_nd.tolist() == [0, 0, 0]
        assert torch.allclose(lw_nd.exp(), torch.full((3,), 1 / 3, dtype=torch.float64))
        # the distance accounts for covariances: a broad prior mode is "closer" to a far mode
        # than a sharp one at the same distance
        prior2 = torch.tensor([[2.0], [-2.0]], dtype=torch.float64)
        pcov2 = torch.tensor([[[0.01]], [[4.0]]], dtype=torch.float64)
        _, a2 = bhattacharyya_reweight(torch.zeros(1, 1, dtype=torch.float64),
                                       torch.ones(1, 1, 1, dtype=torch.float64),
                                       torch.zeros(1, dtype=torch.float64), prior2, pcov2,
                                       torch.zeros(2, dtype=torch.float64))
        assert a2.tolist() == [1]


class TestDistinctMinima:
    def test_feature(self):
        x = torch.tensor([[0.0, 0.0], [0.01, 0.0], [1.0, 0.0], [1.02, 0.0], [5.0, 5.0]])
        v = torch.tensor([3.0, 1.0, 2.0, 4.0, 0.5])
        idx = distinct_minima(x, v, 0.05)
        assert idx.tolist() == [4, 1, 2]
        pos = x[:, None, :].expand(5, 3, 2)  # (P, J, 2) joint-like layout
        assert distinct_minima(pos, v, 0.05).tolist() == [4, 1, 2]
        with pytest.raises(ValueError, match="energy"):
            distinct_minima(x, v[:3], 0.1)


class TestLevenbergMarquardt:
    def test_feature_converges_within_bounds(self):
        c = torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
        W = torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64)

        def derivs(x, rows):
            d = x - c
            return (W * d * d).sum(-1), 2 * W * d, torch.diag_embed(2 * W.expand_as(x))

        x0 = torch.zeros(5, 3, dtype=torch.float64)
        x0[:, 0] = torch.linspace(-3, 3, 5)
        lo = torch.tensor([-5.0, -5.0, -5.0], dtype=torch.float64)
        hi = torch.tensor([5.0, 5.0, 0.2], dtype=torch.float64)  # c[2] outside: at the bound
        x, v, H, conv, its = levenberg_marquardt(derivs, x0, lo, hi, 50, max_step=None)
        want = torch.tensor([2.0, -1.0, 0.2], dtype=torch.float64)
        assert torch.allclose(x, want.expand(5, 3), atol=1e-6) and bool(conv.all())
        # a step cap slows it down but it still gets there
        x2, *_ = levenberg_marquardt(derivs, x0, lo, hi, 100, max_step=0.1)
        assert torch.allclose(x2, want.expand(5, 3), atol=1e-6)

    def test_feature_rows_are_the_evaluated_problems(self):
        seen = []

        def derivs(x, rows):
            seen.append(rows.tolist())
            return (x * x).sum(-1), 2 * x, torch.diag_embed(2 * torch.ones_like(x))

        x0 = torch.tensor([[0.0], [1.0], [2.0]], dtype=torch.float64)
        levenberg_marquardt(derivs, x0, torch.tensor([-9.0]).double(),
                            torch.tensor([9.0]).double(), 5, max_step=None)
        assert seen[0] == [0, 1, 2] and seen[1] == [1, 2]  # row 0 starts converged


class TestEnergyDerivatives:
    def test_feature_autograd_and_finite_differences(self):
        x = torch.tensor([[0.3, -0.2], [1.1, 0.9]], dtype=torch.float64)
        v, g, H = energy_derivatives(double_well, x, method="autograd")
        xx = x.clone().requires_grad_(True)
        (ga,) = torch.autograd.grad(double_well(xx).sum(), xx)
        assert torch.allclose(g, ga)
        Ht = torch.stack([torch.autograd.functional.hessian(double_well, x[i])
                          for i in range(2)])
        assert torch.allclose(H, Ht, atol=1e-10)
        _, _, Hf = energy_derivatives(double_well, x, method="finite_difference")
        assert torch.allclose(Hf, Ht, rtol=1e-2, atol=1e-2)
        with pytest.raises(ValueError, match="Gauss-Newton"):
            energy_derivatives(double_well, x, method="gauss_newton")

    def test_methods_come_from_one_table(self, monkeypatch):
        """``DERIVATIVES`` and ``LOCAL_OPTIMISERS`` are the tables the names are dispatched
        by: a registered derivative method is reached, an unknown name is refused, and every
        optimiser name ``MixtureInference`` accepts is "auto" or a table entry."""
        from torchmocap.filters.inference import mixture

        assert set(mixture.OPTIMISERS) == {"auto", *mixture.LOCAL_OPTIMISERS}
        assert mixture.HESSIANS == tuple(mixture.DERIVATIVES)
        x = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
        called = []

        def fake(energy, theta, hessian, step, gauss_newton):
            called.append(step)
            return energy(theta), torch.zeros_like(theta), None

        monkeypatch.setitem(mixture.DERIVATIVES, "fake", fake)
        energy_derivatives(double_well, x, hessian=False, method="fake", fd_step=0.5)
        assert called == [0.5]
        with pytest.raises(ValueError, match="method: expected one of"):
            energy_derivatives(double_well, x, method="newton")
        # non-differentiable energy: "autograd" refuses, "auto" falls back to differences
        flat = lambda t: t.detach().square().sum(-1)  # noqa: E731
        with pytest.raises(ValueError, match="differentiabl"):
            energy_derivatives(flat, x, method="autograd")
        v, g, H = energy_derivatives(flat, x, method="auto")
        assert g is None and torch.allclose(H, 2 * torch.eye(2, dtype=torch.float64)[None],
                                             atol=1e-6)


class TestMixtureInference:
    def _run(self, context, seed=0, num=60, **kw):
        inf = MixtureInference(components=3, optimiser="lbfgs", hessian="autograd",
                               iterations=30, **kw)
        prop = CovarianceScaledProposal(num_dofs=2, scale=4.0, std_deg=60.0)
        return inf(double_well, prop, BestParticleEstimator(), context, num,
                   torch.Generator().manual_seed(seed))

    def test_feature_keeps_both_modes_and_estimates_the_top_one(self):
        for seed in range(3):
            res = self._run(ProposalContext(previous=torch.zeros(2)), seed)
            H = torch.tensor(res.info["hypotheses"])
            w = torch.tensor(res.info["hypothesis_weights"])
            assert res.info["modes"] == len(w) == H.shape[0] >= 2
            assert float(w.sum()) == pytest.approx(1.0, abs=1e-6)
            near_a = (H - A).norm(dim=-1).min()
            near_b = (H - B).norm(dim=-1).min()
            assert float(near_a) < 0.01 and float(near_b) < 0.01, res.info
            assert torch.allclose(res.estimate, H[int(torch.argmax(w))])
            assert float((res.estimate - A).norm()) < 0.01  # the deeper mode wins
            # the weights are exp(-V) at the modes, normalised
            v = double_well(H)
            assert torch.allclose(w, torch.softmax(-v.double(), 0).float(), atol=1e-5)
            # covariances: inverse Hessians at the modes (0.2^2 at A)
            cov = res.carry["covariances"]
            ia = int((H - A).norm(dim=-1).argmin())
            assert torch.allclose(cov[ia], 0.04 * torch.eye(2), rtol=0.05)
            assert res.particles.shape == H.shape and res.log_weights.shape == w.shape

    def test_feature_the_mixture_is_carried_and_reweighted(self):
        first = self._run(ProposalContext(previous=torch.zeros(2)), 0)
        ctx = ProposalContext(previous=first.estimate,
                              previous_frame=PreviousFrame(carry=first.carry))
        second = self._run(ctx, 1)
        assert second.info["from_carry"] and second.info["prior_components"] == first.info[
            "modes"]
        # same energy: the prior weight of each mode multiplies its likelihood weight again
        H1 = torch.tensor(first.info["hypotheses"])
        w1 = torch.tensor(first.info["hypothesis_weights"])
        H2 = torch.tensor(second.info["hypotheses"])
        w2 = torch.tensor(second.info["hypothesis_weights"])
        ia1, ib1 = int((H1 - A).norm(dim=-1).argmin()), int((H1 - B).norm(dim=-1).argmin())
        ia2, ib2 = int((H2 - A).norm(dim=-1).argmin()), int((H2 - B).norm(dim=-1).argmin())
        r1 = float(w1[ia1] / w1[ib1])
        r2 = float(w2[ia2] / w2[ib2])
        assert r2 == pytest.approx(r1 * r1, rel=1e-3)
        assert second.info["assignment"][ia2] == ia1 and second.info["assignment"][ib2] == ib1

    def test_feature_prediction_shift_and_temporal_prior(self):
        first = self._run(ProposalContext(previous=torch.zeros(2)), 0)
        carry = dict(first.carry)
        shift = torch.tensor([0.05, 0.0])
        ctx = ProposalContext(previous=first.estimate + shift,
                              previous_frame=PreviousFrame(carry=carry))
        res = self._run(ctx, 2, prior_std_deg=math.degrees(0.05), num=20)
        assert res.info["from_carry"]
        # a strong prior around the shifted modes pulls the optimum off the likelihood minimum
        H = torch.tensor(res.info["hypotheses"])
        ia = int((H - A).norm(dim=-1).argmin())
        assert 0.001 < float(H[ia, 0] - A[0]) < 0.05

    def test_feature_prior_in_weights(self):
        """With the temporal prior in the weights, the mode far from the prior mode loses
        weight by exp(-|d|^2 / (2 sigma^2))."""
        start = ProposalContext(previous=A.clone())
        s = 1.0  # radians
        plain = self._run(start, 0, prior_std_deg=math.degrees(s))
        weighted = self._run(start, 0, prior_std_deg=math.degrees(s), prior_in_weights=True)
        Hp = torch.tensor(plain.info["hypotheses"])
        Hw = torch.tensor(weighted.info["hypotheses"])
        wp = torch.tensor(plain.info["hypothesis_weights"])
        ww = torch.tensor(weighted.info["hypothesis_weights"])
        ia, ib = int((Hp - A).norm(dim=-1).argmin()), int((Hp - B).norm(dim=-1).argmin())
        ja, jb = int((Hw - A).norm(dim=-1).argmin()), int((Hw - B).norm(dim=-1).argmin())
        ratio_p, ratio_w = float(wp[ib] / wp[ia]), float(ww[jb] / ww[ja])
        dist2 = float(((Hw[jb] - A) ** 2).sum() - ((Hw[ja] - A) ** 2).sum())
        assert ratio_w == pytest.approx(ratio_p * math.exp(-dist2 / (2 * s * s)), rel=0.05)

    @pytest.mark.parametrize("continuations", [0, 1])
    def test_feature_continuations_keep_the_tracked_mode(self, continuations):
        """One component tracked at the shallower mode B; the proposal's samples near the
        deeper mode A are kinematic jumps. The plain K-best pruning keeps A (lower energy); with
        ``continuations=1`` the best unjumped descendant of the prior mode — B — is kept first."""
        from torchmocap.proposals import Proposal, Proposed

        class Jumps(Proposal):
            def sample(self, context, num, generator=None):
                near_b = B + 0.05 * torch.randn(num // 2, 2, generator=generator)
                near_a = A + 0.05 * torch.randn(num - num // 2, 2, generator=generator)
                jumped = torch.cat([torch.zeros(num // 2, dtype=torch.bool),
                                    torch.ones(num - num // 2, dtype=torch.bool)])
                return Proposed(particles=torch.cat([near_b, near_a]),
                                stats={"jumped": jumped})

        inf = MixtureInference(components=1, optimiser="lbfgs", hessian="autograd",
                               iterations=30, continuations=continuations)
        res = inf(double_well, Jumps(), BestParticleEstimator(),
                  ProposalContext(previous=B.clone()), 20, torch.Generator().manual_seed(0))
        kept = torch.tensor(res.info["hypotheses"])[0]
        assert res.info["minima"] >= 2  # both modes were found either way
        want = B if continuations else A
        assert float((kept - want).norm()) < 0.02, (continuations, kept)

    def test_feature_any_proposal_and_generic_energy(self):
        inf = MixtureInference(components=2, iterations=30, lower=torch.tensor([-3.0, -3.0]),
                               upper=torch.tensor([3.0, 0.8]))
        prop = GaussianDiffusionProposal(0.8, num_dofs=2)
        res = inf(double_well, prop, BestParticleEstimator(),
                  ProposalContext(previous=torch.zeros(2)), 80, torch.Generator().manual_seed(0))
        H = torch.tensor(res.info["hypotheses"])
        assert bool((H[:, 1] <= 0.8 + 1e-6).all())  # the box holds
        assert float((H - torch.tensor([1.0, 0.8])).norm(dim=-1).min()) < 0.02

    def test_exception(self):
        with pytest.raises(ValueError, match="components"):
            MixtureInference(components=0)
        with pytest.raises(ValueError, match="optimiser"):
            MixtureInference(optimiser="newton")
        with pytest.raises(ValueError, match="joints"):
            MixtureInference(merge_space="joints")
        with pytest.raises(ValueError, match="prior_std_deg"):
            MixtureInference(prior_std_deg=-1.0)
        with pytest.raises(ValueError, match="continuations"):
            MixtureInference(continuations=-1)


# ---------------------------------------------------------------------- the presets
@pytest.fixture(scope="module")
def walk_mono():
    from torchmocap.data.synthetic.clips import synthesized_sequence

    seq = synthesized_sequence({"name": "walk", "path": None, "frames": 4}, "monocular",
                               {"silhouettes.enabled": False}, seed=0)
    return seq, Runtime.from_sequence(seq)


def _mpjpe(sk, theta, positions):
    return float((sk(theta).positions - positions).norm(dim=-1).mean()) * 1000


@pytest.mark.parametrize("preset", ["kjs", "css", "ss"])
def test_monocular_presets_track_three_frames_better_than_holding_the_first_pose(walk_mono,
                                                                                preset):
    seq, rt = walk_mono
    sk = rt.skeleton
    gt = seq.ground_truth.positions[1:].float()
    held = _mpjpe(sk, seq.ground_truth.theta[:1].float().expand(3, -1), gt)
    errs = []
    for seed in range(3):
        tr = build_tracker(tracker_config(preset, ["tracker.num_particles=60"]), rt, seed=seed)
        assert isinstance(tr.inference, MixtureInference) and tr.requires == ("joints2d",)
        track = tr.run(seq, progress=False)
        errs.append(_mpjpe(sk, track.theta[1:], gt))
        info = track.infos[-1]
        K = info.inference["modes"]
        assert len(info.hypotheses) == K and len(info.hypotheses[0]) == sk.num_dofs
        assert len(info.hypothesis_weights) == K
        top = int(torch.tensor(info.hypothesis_weights).argmax())
        assert torch.allclose(track.theta[-1], torch.tensor(info.hypotheses[top]).float(),
                              atol=1e-5)
    # measured (MPJPE, mm): holding the first pose 99; kjs, css, ss 45 for every seed
    assert max(errs) < 0.8 * held and sum(errs) / 3 < 0.65 * held, (preset, errs, held)


def test_monocular_presets_are_compositions():
    kjs, css, ss = (tracker_config(p) for p in ("kjs", "css", "ss"))
    assert kjs.proposal._target_.endswith("KinematicJumpProposal")
    assert kjs.proposal.base._target_.endswith("CovarianceScaledProposal")
    assert css.proposal._target_.endswith("CovarianceScaledProposal") and not css.proposal.spherical
    assert ss.proposal.spherical is True
    for c, name in ((kjs, "kjs"), (css, "css"), (ss, "ss")):
        assert c.name == name and c.inference._target_.endswith("MixtureInference")
        assert c.likelihood.terms.joints2d._target_.endswith("Joints2DLikelihood")
    # the preset selects its observations; the command line still wins
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="torchmocap.conf", version_base="1.3"):
        assert compose("track", ["tracker=kjs"]).data.scenario == "monocular"
        assert compose("track", ["tracker=kjs", "data.scenario=studio"]).data.scenario == "studio"
        c = compose("track", ["tracker=css", "tracker.num_particles=7",
                              "tracker.inference.layers=2"])
        assert c.tracker.num_particles == 7 and c.tracker.inference.layers == 2
        assert compose("track", ["tracker=p"]).data.scenario == "studio"
    GlobalHydra.instance().clear()


def test_mixture_tracker_is_deterministic_and_resumes_from_a_checkpoint(walk_mono, tmp_path):
    seq, rt = walk_mono
    ov = ["tracker.num_particles=24", "tracker.inference.components=3"]

    def tracker(seed=5):
        return build_tracker(tracker_config("kjs", ov), rt, seed=seed)

    full = tracker().run(seq, progress=False)
    again = tracker().run(seq, progress=False)
    assert torch.equal(full.theta, again.theta)
    ck = str(tmp_path / "state.pt")
    part = tracker().run(seq, progress=False, checkpoint=ck, checkpoint_every=1, stop_after=2)
    assert part.theta.shape[0] == 3
    resumed = tracker().run(seq, progress=False, checkpoint=ck)
    assert torch.equal(resumed.theta, full.theta)  # the carried mixture came back
    assert resumed.infos[-1].inference["from_carry"]
    assert resumed.infos[-1].inference["prior_components"] >= 1
