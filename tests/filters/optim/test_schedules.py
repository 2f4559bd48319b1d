"""Tests for torchmocap.filters.optim.schedules (β schedules)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmocap.filters.optim.resampling import ess_fraction
from torchmocap.filters.optim.schedules import (
    ESSSchedule,
    GeometricSchedule,
    PolynomialSchedule,
    annealing_log_weights,
    as_schedule,
    ess_fraction_at_beta,
    ess_target_beta,
)


def _energy_sets():
    g = torch.Generator().manual_seed(0)
    sets = []
    for n in (10, 200, 3000):
        sets.append(torch.randn(n, generator=g, dtype=torch.float64))
        sets.append(torch.rand(n, generator=g, dtype=torch.float64) ** 4)
        sets.append(torch.distributions.Cauchy(0.0, 1.0).icdf(torch.rand(n, generator=g)).double())
        sets.append(-torch.log(torch.rand(n, generator=g, dtype=torch.float64)))
    return sets


class TestEssTargetBeta:
    @pytest.mark.parametrize("alpha", [0.1, 0.5, 0.9])
    @pytest.mark.parametrize("scale", [1e-6, 1.0, 1e4])
    def test_feature(self, alpha, scale):
        """The achieved ESS fraction (checked independently) equals alpha within 1e-3."""
        for v in _energy_sets():
            energies = scale * v + 7.0 * scale
            sol = ess_target_beta(energies, alpha)
            assert 0 < float(sol.beta) < 1e12
            lw = annealing_log_weights(energies, sol.beta)
            achieved = float(ess_fraction(lw))
            assert achieved == pytest.approx(alpha, abs=1e-3)
            assert float(sol.ess_fraction) == pytest.approx(alpha, abs=1e-6)

    def test_scale_covariance(self):
        v = torch.randn(300, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        b1 = float(ess_target_beta(v).beta)
        b2 = float(ess_target_beta(1000.0 * v - 5.0).beta)
        assert b2 == pytest.approx(b1 / 1000.0, rel=1e-6)

    def test_float32(self):
        v = torch.randn(200, generator=torch.Generator().manual_seed(2))
        sol = ess_target_beta(v, 0.5)
        assert sol.beta.dtype == torch.float64
        assert float(sol.ess_fraction) == pytest.approx(0.5, abs=1e-6)

    def test_monotone(self):
        v = torch.randn(100, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        betas = torch.logspace(-3, 3, 50, dtype=torch.float64)
        f = torch.stack([ess_fraction_at_beta(v, b) for b in betas])
        assert torch.all(f[1:] <= f[:-1] + 1e-12)
        assert float(f[0]) == pytest.approx(1.0, abs=1e-3)

    def test_cardinality(self):
        v = torch.randn(3, 5, 64, generator=torch.Generator().manual_seed(4))
        sol = ess_target_beta(v, 0.3)
        assert sol.beta.shape == (3, 5) and sol.ess_fraction.shape == (3, 5)
        assert torch.allclose(sol.ess_fraction, torch.full((3, 5), 0.3, dtype=torch.float64))
        for i in range(3):
            assert float(ess_target_beta(v[i, 2], 0.3).beta) == pytest.approx(
                float(sol.beta[i, 2]), rel=1e-9
            )

    @pytest.mark.parametrize("alpha", [0.1, 0.5, 0.9])
    def test_matches_an_independent_root_finder(self, alpha):
        """The solver's β against scipy's brentq on ``ESS/N(β) = α`` (in log β), on random
        batches, ties at the minimum and +inf energies; the edge cases by their rules."""
        from scipy.optimize import brentq

        g = torch.Generator().manual_seed(5)
        sets = _energy_sets() + [torch.randn(3, 4, 50, generator=g, dtype=torch.float64)]
        tied = torch.rand(40, generator=g, dtype=torch.float64)
        tied[:20] = tied.min()
        inf = torch.rand(40, generator=g, dtype=torch.float64)
        inf[:25] = math.inf
        sets += [tied, inf]
        for v in sets:
            a = ess_target_beta(v, alpha)
            assert a.beta.shape == v.shape[:-1] and a.beta.dtype == torch.float64
            for idx in np.ndindex(*v.shape[:-1]):
                row, beta = v[idx], float(a.beta[idx])
                finite = float(torch.isfinite(row).float().mean())
                if finite <= alpha:  # unreachable: beta 0 (ESS fraction = the finite share)
                    assert beta == 0.0
                    continue
                if alpha * row.shape[-1] < 1.5:  # near ESS = 1, the asymptote: no unique root
                    continue

                def f(log_b, row=row):
                    return float(ess_fraction_at_beta(row, math.exp(log_b))) - alpha
                if f(math.log(1e12)) >= 0:  # ties at the minimum keep the ESS above alpha: cap
                    assert beta == 1e12
                    continue
                ref = math.exp(brentq(f, -40.0, math.log(1e12), xtol=1e-14, rtol=1e-14))
                assert beta == pytest.approx(ref, rel=1e-9)
                assert float(a.ess_fraction[idx]) == pytest.approx(alpha, rel=1e-9)

    def test_all_equal_caps(self):
        sol = ess_target_beta(torch.full((50,), 3.0), 0.5, beta_max=1e6)
        assert float(sol.beta) == 1e6
        assert float(sol.ess_fraction) == pytest.approx(1.0)

    def test_unreachable_ties(self):
        # two particles tie at the minimum: ESS/N >= 0.5 for every beta
        sol = ess_target_beta(torch.tensor([0.0, 0.0, 1.0, 2.0]), 0.4, beta_max=1e8)
        assert float(sol.beta) == 1e8
        assert float(sol.ess_fraction) == pytest.approx(0.5)
        lw = annealing_log_weights(torch.tensor([0.0, 0.0, 1.0, 2.0]), sol.beta)
        assert torch.isfinite(lw[:2]).all()

    def test_infinite_energies(self):
        v = torch.tensor([0.0, 1.0, math.inf, math.inf])
        sol = ess_target_beta(v, 0.6)  # above P_finite/P = 0.5: beta = 0
        assert float(sol.beta) == 0.0 and float(sol.ess_fraction) == pytest.approx(0.5)
        sol = ess_target_beta(v, 0.4)
        assert float(sol.ess_fraction) == pytest.approx(0.4, abs=1e-9)
        lw = annealing_log_weights(v, 0.0)
        assert lw.tolist() == [0.0, 0.0, -math.inf, -math.inf]

    def test_exception(self):
        with pytest.raises(ValueError, match="energies.*NaN"):
            ess_target_beta(torch.tensor([0.0, float("nan")]))
        with pytest.raises(ValueError, match="energies.*-inf"):
            ess_target_beta(torch.tensor([0.0, -math.inf]))
        with pytest.raises(ValueError, match="energies.*infinite"):
            ess_target_beta(torch.tensor([math.inf, math.inf]))
        with pytest.raises(ValueError, match="energies.*shape"):
            ess_target_beta(torch.tensor(1.0))
        with pytest.raises(TypeError, match="energies"):
            ess_target_beta(torch.tensor([1, 2]))
        with pytest.raises(ValueError, match="alpha"):
            ess_target_beta(torch.zeros(3), 0.0)
        with pytest.raises(ValueError, match="alpha"):
            ess_target_beta(torch.zeros(3), 1.5)
        with pytest.raises(ValueError, match="beta_max"):
            ess_target_beta(torch.zeros(3), beta_max=math.inf)
        with pytest.raises(ValueError, match="beta"):
            annealing_log_weights(torch.zeros(3), -1.0)


class TestLogWeights:
    def test_huge_beta_finite(self):
        v = torch.tensor([5.0, 6.0, 100.0])
        lw = annealing_log_weights(v, 1e12)
        assert lw[0].item() == 0.0 and torch.isfinite(lw).all()

    def test_feature(self):
        v = torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64)
        lw = annealing_log_weights(v, 0.5)
        assert torch.allclose(lw, torch.tensor([0.0, -0.5, -1.5], dtype=torch.float64))


class TestSchedules:
    def test_polynomial(self):
        s = PolynomialSchedule(power=2.0, scale=0.5)
        assert [float(s(k, None)) for k in range(4)] == [0.5, 2.0, 4.5, 8.0]
        with pytest.raises(ValueError, match="layer"):
            s(-1, None)
        with pytest.raises(ValueError, match="scale"):
            PolynomialSchedule(scale=0.0)

    def test_geometric(self):
        s = GeometricSchedule(ratio=3.0, beta0=2.0)
        assert [float(s(k, None)) for k in range(3)] == [2.0, 6.0, 18.0]
        with pytest.raises(ValueError, match="ratio"):
            GeometricSchedule(ratio=0.0)
        with pytest.raises(ValueError, match="beta0"):
            GeometricSchedule(beta0=-1.0)

    def test_module(self):
        v = torch.randn(100, generator=torch.Generator().manual_seed(5))
        s = ESSSchedule(alpha=0.3)
        assert float(s(0, v)) == float(ess_target_beta(v, 0.3).beta)
        with pytest.raises(ValueError, match="alpha"):
            ESSSchedule(alpha=2.0)

    def test_as_schedule(self):
        """Schedules are objects (configs choose one by ``_target_``); no name lookup."""
        assert isinstance(as_schedule(None), ESSSchedule)
        f = lambda k, v: torch.tensor(1.0)
        assert as_schedule(f) is f
        for bad in ("ess", "polynomial", 1.0):
            with pytest.raises(TypeError, match="schedule"):
                as_schedule(bad)
