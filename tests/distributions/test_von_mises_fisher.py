"""von Mises–Fisher: marginal KS tests, moments, extreme kappa, scipy comparisons (REFERENCE §2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special as sps
import scipy.stats as st
import torch

from torchmocap.distributions import (
    VonMisesFisher,
    bessel_iv_ratio,
    kappa_to_angle,
    log_bessel_iv,
    vmf_log_normalizer,
    vmf_mean_resultant_length,
)

F64 = torch.float64
E1 = [1.0, 0.0, 0.0, 0.0]


def _s_kappa(x: torch.Tensor, mu: torch.Tensor, kappa: float) -> np.ndarray:
    """``t = kappa (1 - mu.x)`` computed without cancellation: ``|x - mu|^2 / 2``."""
    s = 0.5 * ((x.double() - mu.double()) ** 2).sum(-1)
    return (kappa * s).numpy()


def _marginal_cdf(kappa: float):
    """CDF of ``t = kappa (1 - w)`` for vMF on S^3: density ``∝ e^{-t} sqrt(t (2 - t/kappa))``."""
    tmax = 2 * kappa if kappa < 40 else 80.0
    t = np.linspace(0, tmax, 400001)
    with np.errstate(invalid="ignore"):
        f = np.exp(-t) * np.sqrt(np.clip(t * (2 - t / kappa), 0, None))
    c = np.concatenate([[0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t))])
    c /= c[-1]
    return lambda x: np.interp(x, t, c)


class TestVonMisesFisher:
    def test_smoke(self):
        d = VonMisesFisher(torch.tensor(E1), torch.tensor(1000.0))
        x = d.sample((7,), generator=torch.Generator().manual_seed(0))
        assert x.shape == (7, 4) and x.dtype == torch.float32
        assert d.log_prob(x).shape == (7,)

    @pytest.mark.parametrize("sample_shape", [(), (5,), (2, 3)])
    @pytest.mark.parametrize("loc_batch,kappa_batch", [((), ()), ((4,), ()), ((), (4,)),
                                                        ((3, 1), (4,))])
    @pytest.mark.parametrize("p", [3, 4])
    def test_cardinality(self, sample_shape, loc_batch, kappa_batch, p):
        g = torch.Generator().manual_seed(1)
        loc = torch.nn.functional.normalize(torch.randn(*loc_batch, p, generator=g), dim=-1)
        kappa = torch.rand(kappa_batch, generator=g) * 100
        d = VonMisesFisher(loc, kappa)
        batch = torch.broadcast_shapes(loc_batch, kappa_batch)
        assert d.batch_shape == batch and d.event_shape == (p,)
        x = d.sample(sample_shape, generator=g)
        assert x.shape == tuple(sample_shape) + tuple(batch) + (p,)
        assert d.log_prob(x).shape == tuple(sample_shape) + tuple(batch)
        assert torch.allclose(x.norm(dim=-1), torch.ones(()), atol=1e-5)
        assert d.mean.shape == tuple(batch) + (p,)
        assert d.expand((2,) + tuple(batch)).sample(generator=g).shape == (2,) + tuple(batch) + (p,)

    def test_exception(self):
        with pytest.raises(ValueError, match="loc"):
            VonMisesFisher(torch.tensor([1.0, 1.0, 0.0, 0.0]), 1.0)
        with pytest.raises(ValueError, match="loc"):
            VonMisesFisher(torch.tensor([float("nan"), 0.0, 0.0, 0.0]), 1.0)
        with pytest.raises(ValueError, match="loc"):
            VonMisesFisher(torch.tensor([1.0]), 1.0)
        with pytest.raises(ValueError, match="concentration"):
            VonMisesFisher(torch.tensor(E1), -1.0)
        with pytest.raises(ValueError, match="concentration"):
            VonMisesFisher(torch.tensor(E1), float("nan"))
        d = VonMisesFisher(torch.tensor(E1), 1.0)
        with pytest.raises(ValueError, match="value"):
            d.log_prob(torch.zeros(3))

    def test_rejection_cap(self):
        """The rejection loop is capped: with one round, ~1/3 of 1000 entries stay rejected and
        the sampler raises instead of looping or returning garbage; the default cap fills all."""
        g = torch.Generator().manual_seed(4)
        d = VonMisesFisher(torch.tensor(E1), torch.tensor(1000.0), max_rounds=1)
        with pytest.raises(RuntimeError, match="rejected"):
            d.sample((100000,), generator=g)
        kap = torch.full((1000,), 1000.0)
        with pytest.raises(RuntimeError, match="rejected"):
            VonMisesFisher(torch.tensor(E1), kap, max_rounds=1).sample(generator=g)
        x = VonMisesFisher(torch.tensor(E1), kap).sample((50,), generator=g)
        assert torch.isfinite(x).all() and x.shape == (50, 1000, 4)

    def test_reproducible_with_generator(self):
        d = VonMisesFisher(torch.tensor([0.0, 0.6, 0.0, 0.8]), torch.tensor(50.0))
        a = d.sample((100,), generator=torch.Generator().manual_seed(3))
        b = d.sample((100,), generator=torch.Generator().manual_seed(3))
        assert torch.equal(a, b)

    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    @pytest.mark.parametrize("kappa", [0.5, 10.0, 1000.0, 1e6])
    def test_feature_ks_marginal(self, dtype, kappa):
        """KS of t = kappa (1 - mu.x) against the exact marginal e^{-t} sqrt(t (2 - t/kappa))."""
        g = torch.Generator().manual_seed(int(kappa * 7) % 1000 + (dtype == F64))
        mu = torch.tensor([0.5, 0.5, -0.5, 0.5], dtype=dtype)
        x = VonMisesFisher(mu, torch.tensor(kappa, dtype=dtype)).sample((20000,), generator=g)
        t = _s_kappa(x, mu, kappa)
        p = st.kstest(t, _marginal_cdf(kappa)).pvalue
        assert p > 1e-3, p

    @pytest.mark.parametrize("kappa", [0.01, 1.0, 30.0, 1000.0, 1e8])
    def test_feature_mean_resultant_length(self, kappa):
        g = torch.Generator().manual_seed(11)
        mu = torch.tensor(E1, dtype=F64)
        x = VonMisesFisher(mu, torch.tensor(kappa, dtype=F64)).sample((40000,), generator=g)
        s = 0.5 * ((x - mu) ** 2).sum(-1)  # 1 - w
        a4 = vmf_mean_resultant_length(torch.tensor(kappa, dtype=F64), 4).item()
        ref = sps.ive(2, kappa) / sps.ive(1, kappa)
        assert a4 == pytest.approx(ref, rel=1e-10)
        se = s.std().item() / math.sqrt(len(s))
        assert abs((1 - s.mean().item()) - a4) < 4 * se

    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    @pytest.mark.parametrize("kappa", [100.0, 1000.0, 1e4])
    def test_feature_median_angle(self, dtype, kappa):
        g = torch.Generator().manual_seed(5)
        x = VonMisesFisher(torch.tensor(E1, dtype=dtype), torch.tensor(kappa, dtype=dtype)).sample(
            (20000,), generator=g)
        ang = 2 * torch.atan2(x[:, 1:].norm(dim=-1), x[:, 0].abs())
        med = math.degrees(ang.double().median().item())
        assert med == pytest.approx(176.0 / math.sqrt(kappa), rel=0.03)
        assert med == pytest.approx(math.degrees(kappa_to_angle(kappa).item()), rel=0.03)
        p95 = math.degrees(ang.double().quantile(0.95).item())
        assert p95 == pytest.approx(320.0 / math.sqrt(kappa), rel=0.04)

    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    @pytest.mark.parametrize("kappa", [0.0, 1e-300, 1e30])
    def test_feature_extreme_kappa_finite(self, dtype, kappa):
        g = torch.Generator().manual_seed(2)
        mu = torch.tensor([0.0, 0.0, -1.0, 0.0], dtype=dtype)
        d = VonMisesFisher(mu, torch.tensor(kappa, dtype=dtype))
        x = d.sample((5000,), generator=g)
        lp = d.log_prob(x)
        assert torch.isfinite(x).all() and torch.isfinite(lp).all()
        assert torch.isfinite(d.entropy()).all() and torch.isfinite(d.mean).all()
        assert torch.allclose(x.norm(dim=-1), torch.ones((), dtype=dtype), atol=1e-6)
        if kappa == 1e30:
            assert torch.allclose(x, mu.expand_as(x))
        else:  # uniform on S^3: w = mu.x has density (2/pi) sqrt(1 - w^2)
            w = (x.double() @ mu.double()).numpy()
            cdf = lambda v: 0.5 + (v * np.sqrt(1 - v * v) + np.arcsin(v)) / np.pi
            assert st.kstest(w, cdf).pvalue > 1e-3
            log_area = math.log(2 * math.pi**2)
            assert float(lp[0]) == pytest.approx(-log_area, abs=1e-6)

    @pytest.mark.parametrize("p,kappa", [(4, 5.0), (4, 1000.0), (3, 20.0), (5, 3.0), (10, 200.0)])
    def test_feature_two_sample_ks_vs_scipy(self, p, kappa):
        g = torch.Generator().manual_seed(p)
        mu = torch.nn.functional.normalize(torch.randn(p, generator=g, dtype=F64), dim=0)
        x = VonMisesFisher(mu, torch.tensor(kappa, dtype=F64)).sample((8000,), generator=g)
        y = st.vonmises_fisher(mu.numpy(), kappa).rvs(8000, random_state=np.random.default_rng(p))
        # projections on mu and on a fixed oblique direction (checks the rotation to mu)
        v = torch.nn.functional.normalize(mu + torch.randn(p, generator=g, dtype=F64), dim=0)
        for u in (mu, v):
            assert st.ks_2samp((x @ u).numpy(), y @ u.numpy()).pvalue > 1e-3

    @pytest.mark.parametrize("p", [2, 3, 4, 5, 7, 12])
    def test_feature_log_prob_vs_scipy(self, p):
        g = torch.Generator().manual_seed(20 + p)
        mu = torch.nn.functional.normalize(torch.randn(p, generator=g, dtype=F64), dim=0)
        for kappa in (1e-4, 0.7, 12.0, 49.9, 50.1, 400.0, 1e5):
            d = VonMisesFisher(mu, torch.tensor(kappa, dtype=F64))
            x = d.sample((6,), generator=g)
            x = x / x.norm(dim=-1, keepdim=True)
            ref = st.vonmises_fisher(mu.numpy(), kappa).logpdf(x.numpy())
            assert np.allclose(d.log_prob(x).numpy(), ref, rtol=1e-9, atol=1e-9)
            assert d.entropy().item() == pytest.approx(
                st.vonmises_fisher(mu.numpy(), kappa).entropy(), rel=1e-8, abs=1e-8)

    def test_feature_normalised_by_monte_carlo(self):
        g = torch.Generator().manual_seed(7)
        u = torch.nn.functional.normalize(torch.randn(400000, 4, generator=g, dtype=F64), dim=-1)
        d = VonMisesFisher(torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=F64), torch.tensor(3.0,
                                                                                  dtype=F64))
        integral = d.log_prob(u).exp().mean().item() * 2 * math.pi**2
        assert integral == pytest.approx(1.0, abs=0.01)

    def test_feature_float32_log_prob_at_huge_kappa(self):
        mu = torch.tensor(E1)
        d32 = VonMisesFisher(mu, torch.tensor(1e30))
        d64 = VonMisesFisher(mu.double(), torch.tensor(1e30, dtype=F64))
        assert float(d32.log_prob(mu)) == pytest.approx(float(d64.log_prob(mu.double())), rel=1e-5)
        # log C + kappa ~ 2 log kappa - log(2 pi^2) + log(sqrt(2pi)/ ...) is ~ 131, not +-1e30
        assert abs(float(d32.log_prob(mu))) < 200

    def test_feature_per_sample_mean_and_kappa(self):
        g = torch.Generator().manual_seed(8)
        n = 3
        mu = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=F64), dim=-1)
        kappa = torch.tensor([5.0, 100.0, 1e4], dtype=F64)
        x = VonMisesFisher(mu, kappa).sample((20000,), generator=g)  # (20000, 3, 4)
        w = (x * mu).sum(-1)
        a = vmf_mean_resultant_length(kappa, 4)
        se = w.std(0) / math.sqrt(20000)
        assert bool(((w.mean(0) - a).abs() < 4 * se).all())

    def test_feature_householder_signs(self):
        g = torch.Generator().manual_seed(9)
        for mu in ([-1.0, 0, 0, 0], [1 - 1e-12, 1e-6, 0, 0], [0, 0, 0, 1.0], [-0.6, 0, 0.8, 0]):
            m = torch.nn.functional.normalize(torch.tensor(mu, dtype=F64), dim=0)
            x = VonMisesFisher(m, torch.tensor(200.0, dtype=F64)).sample((20000,), generator=g)
            assert torch.isfinite(x).all()
            mean_dir = torch.nn.functional.normalize(x.mean(0), dim=0)
            assert float((mean_dir - m).norm()) < 0.01

    def test_gradcheck_log_prob(self):
        mu = torch.tensor([0.0, 0.6, 0.0, 0.8], dtype=F64)
        x = VonMisesFisher(mu, torch.tensor(3.0, dtype=F64)).sample(
            (4,), generator=torch.Generator().manual_seed(0))
        for k0 in (0.3, 10.0, 80.0):
            kappa = torch.tensor(k0, dtype=F64, requires_grad=True)
            assert torch.autograd.gradcheck(
                lambda k: VonMisesFisher(mu, k, validate_args=False).log_prob(x), (kappa,))


    def test_gradcheck_log_prob_loc_and_value(self):
        """log_prob is differentiable in the mean direction and in the value (float64)."""
        g = torch.Generator().manual_seed(1)
        mu = torch.nn.functional.normalize(torch.randn(2, 4, generator=g, dtype=F64), dim=-1)
        x = VonMisesFisher(mu, torch.tensor(5.0, dtype=F64)).sample((3,), generator=g)
        kappa = torch.tensor([5.0, 300.0], dtype=F64)
        loc = mu.clone().requires_grad_()
        val = x.clone().requires_grad_()
        assert torch.autograd.gradcheck(
            lambda m: VonMisesFisher(m, kappa, validate_args=False).log_prob(x), (loc,))
        assert torch.autograd.gradcheck(
            lambda v: VonMisesFisher(mu, kappa, validate_args=False).log_prob(v), (val,))
        # closed form on the sphere: the tangential gradient of kappa mu.x is
        # kappa (mu - (mu.x) x) (the normal part depends on how log_prob extends off the sphere)
        lp = VonMisesFisher(mu, kappa).log_prob(val)
        (gx,) = torch.autograd.grad(lp.sum(), val)
        tangential = gx - (gx * x).sum(-1, keepdim=True) * x
        m = mu.expand_as(x)
        expect = kappa[:, None] * (m - (m * x).sum(-1, keepdim=True) * x)
        torch.testing.assert_close(tangential, expect)


def _entropy_reference(p: int, kappa: float) -> float:
    """vMF entropy on S^{p-1} by quadrature in ``s = kappa (1 - mu.x)`` (float64, p >= 3)::

        H = log|S^{p-2}| - (p-1)/2 log kappa + log J0 + J1 / J0,
        J_i = int_0^{2 kappa} s^i e^{-s} (s (2 - s/kappa))^{(p-3)/2} ds
    """
    from scipy import integrate

    if kappa == 0:
        return math.log(2) + (p / 2) * math.log(math.pi) - math.lgamma(p / 2)
    e = (p - 3) / 2
    up = min(2 * kappa, 400.0 + 4 * p)
    kw = dict(limit=500, epsabs=0, epsrel=1e-13)
    j0 = integrate.quad(lambda s: math.exp(-s) * (s * (2 - s / kappa)) ** e, 0, up, **kw)[0]
    j1 = integrate.quad(lambda s: s * math.exp(-s) * (s * (2 - s / kappa)) ** e, 0, up, **kw)[0]
    log_area = math.log(2) + ((p - 1) / 2) * math.log(math.pi) - math.lgamma((p - 1) / 2)
    return log_area - ((p - 1) / 2) * math.log(kappa) + math.log(j0) + j1 / j0


class TestEntropy:
    KAPPAS = [0.0, 1e-3, 0.5, 10.0, 100.0, 1999.0, 2001.0, 1e5, 1e8, 1e10, 1e17, 1e30]

    @pytest.mark.parametrize("p", [3, 4, 5, 10, 30])
    def test_feature_vs_quadrature(self, p, dtype):
        """Accurate for every kappa: the textbook -log C - kappa A is 0 at kappa = 1e10 in
        float32 and at 1e17 in float64 (true values -30.3 and -54.5 for p = 4)."""
        mu = torch.zeros(p, dtype=dtype)
        mu[0] = 1
        k = torch.tensor(self.KAPPAS, dtype=dtype)
        got = VonMisesFisher(mu, k).entropy()
        ref = torch.tensor([_entropy_reference(p, float(v)) for v in k], dtype=F64)
        rtol, atol = (1e-6, 1e-6) if dtype == torch.float32 else (1e-11, 1e-9)
        torch.testing.assert_close(got.double(), ref, rtol=rtol, atol=atol)
        assert got.dtype == dtype

    def test_feature_closed_form_p3(self):
        """S^2: H = log(2 pi / kappa) + 1 + log(1 - e^{-2k}) - 2k e^{-2k} / (1 - e^{-2k})."""
        k = torch.tensor([0.3, 2.0, 40.0, 1e4, 1e9, 1e12, 1e20, 1e30], dtype=F64)
        q = torch.exp(-2 * k)
        ref = torch.log(2 * math.pi / k) + 1 + torch.log1p(-q) - 2 * k * q / (1 - q)
        got = VonMisesFisher(torch.tensor([0.0, 0.0, 1.0], dtype=F64), k).entropy()
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)

    def test_feature_large_kappa_limit(self):
        """p = 4, kappa = 1e10: (p-1)/2 log(2 pi e / kappa) + O(1/kappa) = -30.28."""
        for dtype in (torch.float32, F64):
            d = VonMisesFisher(torch.tensor(E1, dtype=dtype), torch.tensor(1e10, dtype=dtype))
            assert float(d.entropy()) == pytest.approx(
                1.5 * math.log(2 * math.pi * math.e / float(d.concentration)), abs=1e-5)

    def test_gradcheck(self):
        for k0 in (0.5, 30.0, 1900.0, 2100.0, 1e6):
            kappa = torch.tensor(k0, dtype=F64, requires_grad=True)
            assert torch.autograd.gradcheck(
                lambda k: VonMisesFisher(torch.tensor(E1, dtype=F64), k).entropy(), (kappa,))


class TestBessel:
    @pytest.mark.parametrize("nu", [0.0, 0.5, 1.0, 1.5, 2.0, 4.0, 9.5, 30.0])
    def test_feature_vs_scipy(self, nu):
        x = torch.tensor([1e-6, 0.01, 0.5, 3.0, 20.0, 49.99, 50.01, 120.0, 700.0, 1e4, 1e7],
                         dtype=F64)
        ref = np.log(sps.ive(nu, x.numpy())) + x.numpy()
        got = log_bessel_iv(nu, x).numpy()
        assert np.allclose(got, ref, rtol=1e-10, atol=1e-10)
        ratio = sps.ive(nu + 1, x.numpy()) / sps.ive(nu, x.numpy())
        assert np.allclose(bessel_iv_ratio(nu, x).numpy(), ratio, rtol=1e-9, atol=1e-14)

    def test_feature_log_normalizer_limits(self):
        k = torch.tensor([0.0, 1e-300, 1e30], dtype=F64)
        c = vmf_log_normalizer(k, 4)
        assert float(c[0]) == pytest.approx(-math.log(2 * math.pi**2))
        assert float(c[1]) == pytest.approx(-math.log(2 * math.pi**2))
        assert math.isfinite(float(c[2]))
        c32 = vmf_log_normalizer(k.float(), 4)
        assert torch.isfinite(c32).all()

    def test_exception(self):
        with pytest.raises(ValueError, match="nu"):
            log_bessel_iv(-1.0, torch.ones(1))
