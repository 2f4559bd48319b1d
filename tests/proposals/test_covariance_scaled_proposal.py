"""Covariance-scaled (CSS) and spherical (SS) sampling proposals: the sample covariance is
s Sigma, SS has the equal-volume radius, heavy tails, mixtures of modes, Hessians inverted,
projection onto the joint limits."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.proposals import CovarianceScaledProposal, ProposalContext
from torchmocap.skeleton import human31


def _spd(D, g, dtype=torch.float64):
    A = torch.randn(D, D, generator=g, dtype=dtype)
    return A @ A.T / D + 0.1 * torch.eye(D, dtype=dtype)


class TestCovarianceScaledProposal:
    def test_smoke(self):
        sk = human31()
        css = CovarianceScaledProposal(sk, scale=8.0)
        ctx = ProposalContext(previous=sk.zero_pose(),
                              covariances=0.01 * torch.eye(31))
        out = css.sample(ctx, 20, torch.Generator().manual_seed(0))
        assert out.particles.shape == (20, 31) and out.stats["components"] == 1
        assert out.stats["component"].tolist() == [0] * 20
        assert bool(sk.within_limits(out.particles, tol=1e-6).all())

    @pytest.mark.parametrize("scale", [1.0, 4.0, 16.0])
    def test_feature_sample_covariance_is_s_sigma(self, scale):
        g = torch.Generator().manual_seed(1)
        D = 4
        cov = _spd(D, g)
        mu = torch.randn(D, generator=g, dtype=torch.float64)
        css = CovarianceScaledProposal(num_dofs=D, scale=scale, boundary="none")
        ctx = ProposalContext(previous=mu, covariances=cov)
        x = css.sample(ctx, 40000, g).particles
        assert torch.allclose(x.mean(0), mu, atol=4 * math.sqrt(scale * float(cov.max()) / 4e4))
        emp = torch.cov(x.T)
        assert torch.allclose(emp, scale * cov, atol=0.05 * scale * float(cov.diag().max()))
        # context.scale multiplies the proposal's own scale (an annealer's knob)
        half = css.sample(ProposalContext(previous=mu, scale=0.25,
                                          covariances=cov), 40000, g).particles
        assert torch.allclose(torch.cov(half.T), 0.25 * scale * cov,
                              atol=0.05 * scale * float(cov.diag().max()))

    def test_feature_spherical_sampling_has_the_equal_volume_radius(self):
        g = torch.Generator().manual_seed(2)
        D = 5
        cov = torch.diag(torch.tensor([4.0, 1.0, 0.25, 2.0, 0.5], dtype=torch.float64))
        R = float(torch.linalg.det(cov)) ** (1 / D)  # (lambda_1 ... lambda_n)^(1/n)
        ss = CovarianceScaledProposal(num_dofs=D, scale=8.0, spherical=True, boundary="none")
        x = ss.sample(ProposalContext(previous=torch.zeros(D, dtype=torch.float64),
                                      covariances=cov), 40000, g).particles
        emp = torch.cov(x.T)
        assert torch.allclose(emp, 8.0 * R * torch.eye(D, dtype=torch.float64),
                              atol=0.05 * 8.0 * R)
        # the same volume as CSS: det of the scale matrices agree
        css = CovarianceScaledProposal(num_dofs=D, scale=8.0, boundary="none")
        y = css.sample(ProposalContext(previous=torch.zeros(D, dtype=torch.float64),
                                       covariances=cov), 40000, g).particles
        ld_ss, ld_css = torch.logdet(emp), torch.logdet(torch.cov(y.T))
        assert float(ld_ss) == pytest.approx(float(ld_css), abs=0.1)

    def test_feature_heavy_tails(self):
        g = torch.Generator().manual_seed(3)
        D = 3
        mu = torch.zeros(D, dtype=torch.float64)
        ctx = ProposalContext(previous=mu, covariances=torch.eye(D, dtype=torch.float64))
        gauss = CovarianceScaledProposal(num_dofs=D, boundary="none", scale=1.0)
        cauchy = CovarianceScaledProposal(num_dofs=D, boundary="none", scale=1.0, tails="cauchy")
        xg = gauss.sample(ctx, 20000, g).particles
        xc = cauchy.sample(ctx, 20000, g).particles
        far_g = float((xg.abs() > 4).any(-1).double().mean())
        far_c = float((xc.abs() > 4).any(-1).double().mean())
        # each whitened coordinate of the Cauchy is standard Cauchy: P(|t| > 4) = 0.156
        assert far_g < 0.001 and far_c > 0.2
        med = float(xc[:, 0].abs().median())
        assert med == pytest.approx(1.0, abs=0.05)  # median |Cauchy(0, 1)| = 1

    def test_feature_modes_weights_and_hessians(self):
        g = torch.Generator().manual_seed(4)
        D = 2
        modes = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
        H = torch.stack([torch.diag(torch.tensor([100.0, 100.0])),
                         torch.diag(torch.tensor([1.0, 4.0])),
                         torch.diag(torch.tensor([25.0, 25.0]))]).double()
        lw = torch.log(torch.tensor([0.6, 0.3, 0.1]))
        css = CovarianceScaledProposal(num_dofs=D, scale=1.0, boundary="none")
        out = css.sample(ProposalContext(previous=modes, log_weights=lw,
                                         hessians=H), 30000, g)
        comp = out.stats["component"]
        freq = torch.bincount(comp, minlength=3).double() / 30000
        assert torch.allclose(freq, torch.tensor([0.6, 0.3, 0.1], dtype=torch.float64),
                              atol=0.015)
        x1 = out.particles[comp == 1]
        assert torch.allclose(x1.var(0), torch.tensor([1.0, 0.25], dtype=torch.float64),
                              rtol=0.06)
        # uniform_mix spreads a fraction of the samples evenly over the modes
        mix = CovarianceScaledProposal(num_dofs=D, scale=1.0, boundary="none", uniform_mix=0.3)
        c2 = mix.sample(ProposalContext(previous=modes, log_weights=lw,
                                        hessians=H), 30000, g).stats["component"]
        f2 = torch.bincount(c2, minlength=3).double() / 30000
        assert float(f2[2]) == pytest.approx(0.7 * 0.1 + 0.1, abs=0.015)

    def test_feature_infeasible_samples_are_projected_onto_the_limits(self):
        sk = human31()
        css = CovarianceScaledProposal(sk, scale=16.0)
        th = sk.zero_pose()
        ctx = ProposalContext(previous=th, covariances=0.3 * torch.eye(31))
        out = css.sample(ctx, 500, torch.Generator().manual_seed(5))
        assert bool(sk.within_limits(out.particles).all())
        assert out.stats["clamped"] > 0.9  # knees at 0 flexion: half the draws go below
        lo = sk.lower[sk.dof_index("l_knee_flex")]
        knee = out.particles[:, sk.dof_index("l_knee_flex")]
        assert float((knee == lo).double().mean()) == pytest.approx(0.5, abs=0.08)

    def test_feature_own_std_and_annealing_std(self):
        sk = human31()
        css = CovarianceScaledProposal(sk, scale=1.0, std_deg=2.0, boundary="none")
        th = sk.zero_pose()
        x = css.sample(ProposalContext(previous=th), 20000,
                       torch.Generator().manual_seed(6)).particles
        assert float(x[:, 10].std()) == pytest.approx(math.radians(2.0), rel=0.05)
        assert torch.allclose(css.coordinate_std, css.std)
        std = torch.full((31,), 0.1)
        y = css.sample(ProposalContext(previous=th, std=std), 20000,
                       torch.Generator().manual_seed(6)).particles
        assert float(y[:, 10].std()) == pytest.approx(0.1, rel=0.05)

    def test_exception(self):
        with pytest.raises(ValueError, match="scale"):
            CovarianceScaledProposal(num_dofs=2, scale=0.0)
        with pytest.raises(ValueError, match="dof"):
            CovarianceScaledProposal(num_dofs=2, tails="student_t")
        with pytest.raises(ValueError, match="num_dofs"):
            CovarianceScaledProposal()
        css = CovarianceScaledProposal(num_dofs=2)
        with pytest.raises(ValueError, match="previous"):
            css.sample(ProposalContext(previous=torch.zeros(3)), 4)
        with pytest.raises(ValueError, match="covariances"):
            css.sample(ProposalContext(previous=torch.zeros(2),
                                       covariances=torch.eye(3)), 4)
        with pytest.raises(ValueError, match="log_weights"):
            css.sample(ProposalContext(previous=torch.zeros(3, 2),
                                       log_weights=torch.zeros(2)), 4)
