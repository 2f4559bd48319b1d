"""Covariance-scaled sampling, spherical covariances, Bhattacharyya distances, Hessian inverses."""

from __future__ import annotations

import doctest
import importlib
import math

import numpy as np
import pytest
import scipy.integrate as si
import scipy.stats as st
import torch

from torchmocap.distributions import (
    CovarianceScaledSampler,
    bhattacharyya_distance,
    covariance_scaled_sample,
    hessian_to_covariance,
    mixture_covariance_scaled_sample,
    spherical_covariance,
)

F64 = torch.float64
css_module = importlib.import_module("torchmocap.distributions.covariance_scaled")


def _spd(D: int, gen: torch.Generator, log_range=(-2.0, 1.0), batch=()) -> torch.Tensor:
    """Random SPD matrices with log10-uniform eigenvalues in ``log_range``."""
    Q, _ = torch.linalg.qr(torch.randn(*batch, D, D, generator=gen, dtype=F64))
    lam = 10 ** (log_range[0] + (log_range[1] - log_range[0])
                 * torch.rand(*batch, D, generator=gen, dtype=F64))
    S = (Q * lam[..., None, :]) @ Q.transpose(-1, -2)
    return 0.5 * (S + S.transpose(-1, -2))


def _whiten(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    L = torch.linalg.cholesky(cov)
    return torch.linalg.solve_triangular(L, (x - mean)[..., None], upper=False)[..., 0]


class TestCovarianceScaledSample:
    def test_smoke(self, device, dtype):
        g = torch.Generator(device=device).manual_seed(0)
        x = covariance_scaled_sample(torch.zeros(3, dtype=dtype, device=device),
                                     torch.eye(3, dtype=dtype, device=device), 5, generator=g)
        assert x.shape == (5, 3) and x.dtype == dtype and x.device.type == device.type

    def test_cardinality(self):
        g = torch.Generator().manual_seed(1)
        S = _spd(4, g)
        assert covariance_scaled_sample(torch.zeros(4), S.float(), 7, generator=g).shape == (7, 4)
        assert covariance_scaled_sample(torch.zeros(3, 4, dtype=F64), S, 7, generator=g
                                        ).shape == (7, 3, 4)
        Sk = _spd(4, g, batch=(3,))
        assert covariance_scaled_sample(torch.zeros(4, dtype=F64), Sk, 7, generator=g
                                        ).shape == (7, 3, 4)
        for tails, dof in (("student_t", 3.0), ("cauchy", None)):
            x = covariance_scaled_sample(torch.zeros(3, 4, dtype=F64), Sk, 6, tails=tails,
                                         dof=dof, generator=g)
            assert x.shape == (6, 3, 4)
        assert covariance_scaled_sample(torch.zeros(4, dtype=F64), S, 0, generator=g
                                        ).shape == (0, 4)

    @pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
    def test_feature_covariance_is_scaled(self, seed):
        """The sample covariance of Gaussian CSS is ``s Sigma``: in ``(s Sigma)``-whitened
        coordinates every entry of the sample covariance is within 4.5 standard errors of the
        identity (``sqrt(2/n)`` on the diagonal, ``sqrt(1/n)`` off it), the mean within 4.5
        ``sqrt(1/n)`` of 0 — and the same check rejects ``sqrt(s) Sigma``."""
        g = torch.Generator().manual_seed(100 + seed)
        D, n, s = 6, 40000, 8.0
        mean = torch.randn(D, generator=g, dtype=F64)
        cov = _spd(D, g)
        x = covariance_scaled_sample(mean, cov, n, scale=s, generator=g)

        def z_scores(scale):
            z = _whiten(x, mean, scale * cov)
            C = z.T @ z / n  # known mean: no bias correction
            se = torch.full((D, D), math.sqrt(1 / n), dtype=F64) + torch.diag(
                torch.full((D,), math.sqrt(2 / n) - math.sqrt(1 / n), dtype=F64))
            return ((C - torch.eye(D, dtype=F64)) / se).abs().max(), z.mean(0).abs().max() * (
                math.sqrt(n))

        zc, zm = z_scores(s)
        assert float(zc) < 4.5 and float(zm) < 4.5
        zc_wrong, _ = z_scores(math.sqrt(s))
        assert float(zc_wrong) > 50

    def test_feature_components(self):
        """Per-component sampling uses each component's mean and covariance."""
        g = torch.Generator().manual_seed(5)
        K, D, n = 3, 3, 30000
        means = 10 * torch.randn(K, D, generator=g, dtype=F64)
        covs = _spd(D, g, batch=(K,))
        x = covariance_scaled_sample(means, covs, n, scale=4.0, generator=g)
        for k in range(K):
            z = _whiten(x[:, k], means[k], 4.0 * covs[k])
            C = z.T @ z / n
            assert float((C - torch.eye(D, dtype=F64)).abs().max()) < 4.5 * math.sqrt(2 / n)

    @pytest.mark.parametrize(("tails", "dof"), [("cauchy", None), ("student_t", 1.0),
                                                ("student_t", 3.0), ("student_t", 5.5),
                                                ("student_t", 0.7)])
    def test_feature_heavy_tail_marginals(self, tails, dof):
        """Whitened coordinates ``(L^-1 (x - mu))_i / sqrt(s)`` are Student-t(nu) (KS test
        against scipy, p > 1e-3 for each coordinate); Gaussian CSS samples fail the same test
        against t(nu) (the test has power)."""
        nu = 1.0 if tails == "cauchy" else dof
        g = torch.Generator().manual_seed(6)
        D, n, s = 4, 20000, 4.0
        mean = torch.randn(D, generator=g, dtype=F64)
        cov = _spd(D, g)
        x = covariance_scaled_sample(mean, cov, n, scale=s, tails=tails, dof=dof, generator=g)
        z = _whiten(x, mean, s * cov)
        for i in range(D):
            assert st.kstest(z[:, i].numpy(), st.t(nu).cdf).pvalue > 1e-3
        xg = covariance_scaled_sample(mean, cov, n, scale=s, generator=g)
        zg = _whiten(xg, mean, s * cov)
        assert st.kstest(zg[:, 0].numpy(), st.t(nu).cdf).pvalue < 1e-6 or nu > 5
        if nu > 5:  # t(5.5) vs normal needs the tails: compare kurtosis instead
            assert float(st.kurtosis(z.reshape(-1).numpy())) > 1.0

    def test_feature_elliptical(self):
        """Heavy tails share one chi-square per sample: the whitened squared radius over
        ``D`` is ``F(D, nu)`` distributed (independent per-coordinate t's would not be)."""
        g = torch.Generator().manual_seed(7)
        D, n, nu = 5, 20000, 3.0
        x = covariance_scaled_sample(torch.zeros(D, dtype=F64), torch.eye(D, dtype=F64), n,
                                     scale=1.0, tails="student_t", dof=nu, generator=g)
        r2 = (x * x).sum(-1) / D
        assert st.kstest(r2.numpy(), st.f(D, nu).cdf).pvalue > 1e-3

    def test_feature_semidefinite_covariance(self):
        """A rank-deficient covariance samples inside its range."""
        g = torch.Generator().manual_seed(8)
        A = torch.randn(5, 2, generator=g, dtype=F64)
        cov = A @ A.T
        x = covariance_scaled_sample(torch.zeros(5, dtype=F64), cov, 1000, generator=g)
        Q, _ = torch.linalg.qr(A)
        resid = x - (x @ Q) @ Q.T
        assert float(resid.abs().max()) < 1e-7 * float(x.abs().max())
        assert float(x.abs().max()) > 1.0

    def test_feature_generator(self):
        """Reproducible from the generator; the global RNG is untouched."""
        state = torch.get_rng_state()
        mean, cov = torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64)
        for tails in ("gaussian", "cauchy"):
            a = covariance_scaled_sample(mean, cov, 50, tails=tails,
                                         generator=torch.Generator().manual_seed(9))
            b = covariance_scaled_sample(mean, cov, 50, tails=tails,
                                         generator=torch.Generator().manual_seed(9))
            assert torch.equal(a, b)
        mixture_covariance_scaled_sample(torch.ones(2), torch.zeros(2, 3), torch.eye(3).expand(
            2, 3, 3), 10, tails="student_t", dof=2.5, generator=torch.Generator().manual_seed(1))
        assert torch.equal(torch.get_rng_state(), state)

    def test_exception(self):
        z, eye = torch.zeros(3), torch.eye(3)
        with pytest.raises(ValueError, match="cov"):
            covariance_scaled_sample(z, torch.eye(4), 3)
        with pytest.raises(ValueError, match="cov"):
            covariance_scaled_sample(z, torch.tensor([[1.0, 2, 0], [0, 1, 0], [0, 0, 1]]), 3)
        with pytest.raises(ValueError, match="cov"):
            covariance_scaled_sample(z, -eye, 3)  # not positive semi-definite
        with pytest.raises(ValueError, match="mean"):
            covariance_scaled_sample(torch.zeros(2, 2, 3), eye, 3)
        with pytest.raises(ValueError, match="mean"):
            covariance_scaled_sample(torch.full((3,), math.nan), eye, 3)
        with pytest.raises(ValueError, match="scale"):
            covariance_scaled_sample(z, eye, 3, scale=0.0)
        with pytest.raises(ValueError, match="tails"):
            covariance_scaled_sample(z, eye, 3, tails="laplace")
        with pytest.raises(ValueError, match="dof"):
            covariance_scaled_sample(z, eye, 3, tails="student_t")
        with pytest.raises(ValueError, match="num"):
            covariance_scaled_sample(z, eye, -1)
        with pytest.raises(TypeError, match="mean"):
            covariance_scaled_sample([0.0, 0.0, 0.0], eye, 3)
        with pytest.raises(ValueError, match="cov"):
            covariance_scaled_sample(torch.zeros(2, 3), eye.expand(3, 3, 3), 3)


class TestMixtureSample:
    def test_feature_weights_and_components(self):
        g = torch.Generator().manual_seed(10)
        K, D, n = 3, 2, 30000
        w = torch.tensor([0.2, 0.5, 0.3], dtype=F64)
        means = torch.tensor([[-20.0, 0.0], [0.0, 20.0], [20.0, 0.0]], dtype=F64)
        covs = _spd(D, g, batch=(K,))
        x, k = mixture_covariance_scaled_sample(w * 7, means, covs, n, scale=4.0, generator=g)
        assert x.shape == (n, D) and k.shape == (n,) and k.dtype == torch.int64
        counts = torch.bincount(k, minlength=K).double()
        assert st.chisquare(counts.numpy(), (w * n).numpy()).pvalue > 1e-3
        for j in range(K):
            z = _whiten(x[k == j], means[j], 4.0 * covs[j])
            C = z.T @ z / z.shape[0]
            assert float((C - torch.eye(D, dtype=F64)).abs().max()) < 4.5 * math.sqrt(
                2 / z.shape[0])

    def test_exception(self):
        m, c = torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3)
        with pytest.raises(ValueError, match="weights"):
            mixture_covariance_scaled_sample(torch.zeros(2), m, c, 5)
        with pytest.raises(ValueError, match="weights"):
            mixture_covariance_scaled_sample(torch.tensor([1.0, -1.0]), m, c, 5)
        with pytest.raises(ValueError, match="weights"):
            mixture_covariance_scaled_sample(torch.ones(3), m, c, 5)
        with pytest.raises(ValueError, match="covs"):
            mixture_covariance_scaled_sample(torch.ones(2), m, torch.eye(3), 5)
        with pytest.raises(ValueError, match="means"):
            mixture_covariance_scaled_sample(torch.ones(2), torch.zeros(3), c, 5)


class TestStandardGamma:
    @pytest.mark.parametrize("shape", [0.35, 0.5, 1.0, 1.5, 3.0, 12.0])
    def test_feature_distribution(self, shape):
        g = torch.Generator().manual_seed(11)
        x = css_module._standard_gamma(shape, (20000,), g, F64, torch.device("cpu"))
        assert bool((x > 0).all())
        assert st.kstest(x.numpy(), st.gamma(shape).cdf).pvalue > 1e-3


class TestSphericalCovariance:
    def test_feature_equal_volume(self, dtype):
        g = torch.Generator().manual_seed(12)
        S = _spd(5, g, batch=(4,))
        SS = spherical_covariance(S.to(dtype))
        assert SS.shape == (4, 5, 5) and SS.dtype == dtype
        R = SS[:, 0, 0]
        torch.testing.assert_close(SS, R[:, None, None] * torch.eye(5, dtype=dtype))
        rtol = 1e-12 if dtype == F64 else 1e-5
        torch.testing.assert_close(torch.logdet(SS.double()), torch.logdet(S), rtol=rtol,
                                   atol=rtol)
        lam = torch.linalg.eigvalsh(S)
        torch.testing.assert_close(R.double(), lam.prod(-1) ** (1 / 5), rtol=rtol * 10, atol=0)

    def test_feature_tiny_eigenvalues(self):
        """30 eigenvalues near 1e-12: the plain product underflows to 0, log space does not."""
        g = torch.Generator().manual_seed(13)
        S = _spd(30, g, log_range=(-12.5, -11.5))
        lam = torch.linalg.eigvalsh(S)
        naive = lam.prod() ** (1 / 30)
        assert float(naive) == 0.0  # the naive formula fails on this input
        R = spherical_covariance(S)[0, 0]
        expect = torch.exp(torch.log(lam).mean())
        assert float(abs(R / expect - 1)) < 1e-10 and 1e-13 < float(R) < 1e-11

    def test_exception(self):
        with pytest.raises(ValueError, match="cov"):
            spherical_covariance(torch.zeros(3, 2))
        with pytest.raises(ValueError, match="positive-definite"):
            spherical_covariance(torch.diag(torch.tensor([1.0, 0.0, 1.0])))


class TestBhattacharyya:
    def test_feature_closed_form_1d(self):
        g = torch.Generator().manual_seed(14)
        m1, m2 = torch.randn(50, 1, generator=g, dtype=F64), torch.randn(50, 1, generator=g,
                                                                          dtype=F64)
        v1 = torch.rand(50, generator=g, dtype=F64) + 0.1
        v2 = torch.rand(50, generator=g, dtype=F64) + 0.1
        d = bhattacharyya_distance(m1, v1[:, None, None], m2, v2[:, None, None])
        expect = 0.25 * (m1 - m2)[:, 0] ** 2 / (v1 + v2) + 0.5 * torch.log(
            (v1 + v2) / (2 * torch.sqrt(v1 * v2)))
        torch.testing.assert_close(d, expect, rtol=1e-12, atol=1e-14)

    def test_feature_numerical_integration(self):
        """``-log int sqrt(p q)`` by quadrature, in 1-D and 2-D."""
        g = torch.Generator().manual_seed(15)
        for _ in range(3):
            m1, m2 = torch.randn(1, generator=g, dtype=F64), torch.randn(1, generator=g,
                                                                        dtype=F64)
            s1, s2 = 0.3 + torch.rand(2, generator=g, dtype=F64)
            p, q = st.norm(float(m1), float(s1)), st.norm(float(m2), float(s2))
            bc = si.quad(lambda x, p=p, q=q: math.sqrt(p.pdf(x) * q.pdf(x)), -30, 30,
                         epsabs=1e-13, limit=200)[0]
            d = bhattacharyya_distance(m1, (s1**2).reshape(1, 1), m2, (s2**2).reshape(1, 1))
            assert float(d) == pytest.approx(-math.log(bc), abs=1e-9)
        for _ in range(2):
            m1, m2 = 0.5 * torch.randn(2, generator=g, dtype=F64), 0.5 * torch.randn(
                2, generator=g, dtype=F64)
            S1, S2 = _spd(2, g, log_range=(-1, 0)), _spd(2, g, log_range=(-1, 0))
            p = st.multivariate_normal(m1.numpy(), S1.numpy())
            q = st.multivariate_normal(m2.numpy(), S2.numpy())
            xs = np.linspace(-8, 8, 1201)
            X, Y = np.meshgrid(xs, xs, indexing="ij")
            pts = np.stack([X, Y], -1)
            f = np.sqrt(p.pdf(pts) * q.pdf(pts))
            bc = si.simpson(si.simpson(f, x=xs, axis=1), x=xs)
            d = bhattacharyya_distance(m1, S1, m2, S2)
            assert float(d) == pytest.approx(-math.log(bc), abs=1e-7)

    def test_feature_zero_symmetric_nonnegative(self, dtype):
        g = torch.Generator().manual_seed(16)
        m1, m2 = torch.randn(20, 6, generator=g, dtype=F64), torch.randn(20, 6, generator=g,
                                                                          dtype=F64)
        S1, S2 = _spd(6, g, batch=(20,)), _spd(6, g, batch=(20,))
        m1, m2, S1, S2 = (t.to(dtype) for t in (m1, m2, S1, S2))
        same = bhattacharyya_distance(m1, S1, m1, S1)
        assert float(same.abs().max()) < (1e-12 if dtype == F64 else 1e-5)
        d12, d21 = bhattacharyya_distance(m1, S1, m2, S2), bhattacharyya_distance(m2, S2, m1, S1)
        torch.testing.assert_close(d12, d21)
        assert bool((d12 > 0).all())

    def test_feature_broadcast_and_scale_invariance(self):
        """Batched against one prior mode; invariant to a common change of units, even one
        whose determinants (1e-1200) do not exist in float64."""
        g = torch.Generator().manual_seed(17)
        m = torch.randn(7, 10, generator=g, dtype=F64)
        S = _spd(10, g, batch=(7,))
        m0, S0 = torch.zeros(10, dtype=F64), torch.eye(10, dtype=F64)
        d = bhattacharyya_distance(m, S, m0, S0)
        assert d.shape == (7,)
        a = 1e-60
        d_small = bhattacharyya_distance(a * m, a * a * S, a * m0, a * a * S0)
        assert float(torch.linalg.det(a * a * S0)) == 0.0  # the determinant underflows
        torch.testing.assert_close(d_small, d, rtol=1e-10, atol=1e-12)

    def test_exception(self):
        z, eye = torch.zeros(2), torch.eye(2)
        with pytest.raises(ValueError, match="cov1"):
            bhattacharyya_distance(z, torch.zeros(2, 2), z, eye)
        with pytest.raises(ValueError, match="cov2"):
            bhattacharyya_distance(z, eye, z, torch.eye(3))
        with pytest.raises(ValueError, match="mean2"):
            bhattacharyya_distance(z, eye, torch.zeros(3), eye)
        with pytest.raises(ValueError, match="mean1"):
            bhattacharyya_distance(torch.full((2,), math.inf), eye, z, eye)


class TestHessianToCovariance:
    def test_feature_positive_definite_is_inverse(self, dtype):
        g = torch.Generator().manual_seed(18)
        H = _spd(5, g, batch=(3,)).to(dtype)
        tol = 1e-10 if dtype == F64 else 1e-4
        torch.testing.assert_close(hessian_to_covariance(H) @ H,
                                   torch.eye(5, dtype=dtype).expand(3, 5, 5), rtol=0, atol=tol)

    def test_feature_indefinite(self):
        g = torch.Generator().manual_seed(19)
        Q, _ = torch.linalg.qr(torch.randn(4, 4, generator=g, dtype=F64))
        lam = torch.tensor([5.0, 2.0, -1.0, -0.5], dtype=F64)
        H = (Q * lam) @ Q.T
        C = hessian_to_covariance(H)
        torch.testing.assert_close(C, (Q / lam.abs()) @ Q.T)
        Cc = hessian_to_covariance(H, mode="clamp", rel_floor=0.01)
        f = 0.01 * 5.0
        torch.testing.assert_close(Cc, (Q / torch.clamp(lam, min=f)) @ Q.T)
        assert bool((torch.linalg.eigvalsh(Cc) > 0).all())
        # usable by the sampler
        covariance_scaled_sample(torch.zeros(4, dtype=F64), C, 3,
                                 generator=torch.Generator().manual_seed(0))

    def test_feature_singular(self):
        H = torch.diag(torch.tensor([4.0, 0.0, 1e-30], dtype=F64))
        C = hessian_to_covariance(H, rel_floor=1e-6)
        torch.testing.assert_close(torch.linalg.eigvalsh(C).sort().values,
                                   torch.tensor([0.25, 2.5e5, 2.5e5], dtype=F64))
        C2 = hessian_to_covariance(H, floor=0.5)
        torch.testing.assert_close(torch.diagonal(C2), torch.tensor([0.25, 2.0, 2.0],
                                                                    dtype=F64))

    def test_exception(self):
        with pytest.raises(ValueError, match="hessian"):
            hessian_to_covariance(torch.zeros(2, 3))
        with pytest.raises(ValueError, match="mode"):
            hessian_to_covariance(torch.eye(2), mode="flip")
        with pytest.raises(ValueError, match="rel_floor"):
            hessian_to_covariance(torch.eye(2), rel_floor=0.0)
        with pytest.raises(ValueError, match="floor"):
            hessian_to_covariance(torch.eye(2), floor=-1.0)


class TestCovarianceScaledSampler:
    def test_module(self):
        g = _spd(3, torch.Generator().manual_seed(20))
        mean = torch.ones(3, dtype=F64)
        m = CovarianceScaledSampler(scale=8.0, tails="student_t", dof=4.0)
        a = m(mean, g, 20, generator=torch.Generator().manual_seed(3))
        b = covariance_scaled_sample(mean, g, 20, 8.0, "student_t", 4.0,
                                     torch.Generator().manual_seed(3))
        assert torch.equal(a, b)
        ss = CovarianceScaledSampler(scale=8.0, spherical=True)
        c = ss(mean, g, 20, generator=torch.Generator().manual_seed(3))
        d = covariance_scaled_sample(mean, spherical_covariance(g), 20, 8.0,
                                     generator=torch.Generator().manual_seed(3))
        assert torch.equal(c, d)
        assert "spherical=True" in repr(ss)
        with pytest.raises(ValueError, match="dof"):
            CovarianceScaledSampler(tails="student_t")


def test_docstring_examples():
    res = doctest.testmod(css_module, extraglobs={"torch": torch})
    assert res.attempted > 0 and res.failed == 0
