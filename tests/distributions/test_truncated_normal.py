"""TruncatedNormal (the angular prior of Hauberg & Pedersen, eq. 3): scipy.stats.truncnorm
comparisons, normalisation by quadrature in 1-D and 2-D, moments, far tails in float32, KS tests
with a fixed generator, shapes, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.integrate
import scipy.stats as st
import torch

from torchmocap.distributions import TruncatedNormal, log_normal_mass
from torchmocap.skeleton import human31

F64 = torch.float64
INF = math.inf
# standardized windows (a, b): central, one-sided, far tails (8-40 sd), narrow, unbounded
WINDOWS = [(-1.0, 2.0), (-0.5, 0.5), (0.0, 3.0), (1.5, INF), (-INF, -2.0), (8.0, 9.0),
           (-9.0, -8.0), (-INF, -8.0), (12.0, 12.5), (29.0, 30.0), (-40.0, -39.0),
           (-INF, INF), (-3.0, 40.0)]


def _dist(a, b, loc=0.3, scale=2.0, dtype=F64):
    t = lambda v: torch.tensor(v, dtype=dtype)  # noqa: E731
    return TruncatedNormal(t(loc), t(scale), t(loc + scale * a), t(loc + scale * b))


def _grid(a, b, n=4001):
    """Standardized points spanning the window (infinite ends cut at 12 sd)."""
    lo = a if math.isfinite(a) else min(b, 0.0) - 12.0
    hi = b if math.isfinite(b) else max(a, 0.0) + 12.0
    return np.linspace(lo, hi, n)


class TestTruncatedNormal:
    def test_smoke(self, device, dtype):
        d = TruncatedNormal(torch.tensor(0.0, dtype=dtype, device=device), 1.0, -1.0, 2.0)
        x = d.sample((7,), generator=torch.Generator(device=device).manual_seed(0))
        assert x.shape == (7,) and x.dtype == dtype and x.device.type == device.type
        assert d.log_prob(x).shape == (7,)
        assert d.batch_shape == () and d.event_shape == ()
        assert isinstance(d.support, torch.distributions.constraints.interval)

    @pytest.mark.parametrize("sample_shape", [(), (5,), (2, 3)])
    @pytest.mark.parametrize("shapes", [((), (), (), ()), ((4,), (), (), ()),
                                        ((3, 1), (4,), (4,), ()), ((31,), (31,), (31,), (31,))])
    def test_cardinality(self, sample_shape, shapes):
        g = torch.Generator().manual_seed(1)
        loc = torch.randn(shapes[0], generator=g)
        scale = torch.rand(shapes[1], generator=g) + 0.1
        low = -torch.rand(shapes[2], generator=g) - 0.5
        high = torch.rand(shapes[3], generator=g) + 0.5
        d = TruncatedNormal(loc, scale, low, high)
        batch = torch.broadcast_shapes(*shapes)
        assert d.batch_shape == batch
        x = d.sample(sample_shape, generator=g)
        assert x.shape == torch.Size(sample_shape) + batch
        assert d.log_prob(x).shape == x.shape and d.cdf(x).shape == x.shape
        assert d.mean.shape == batch and d.variance.shape == batch
        assert d.entropy().shape == batch
        e = d.expand((6,) + tuple(batch))
        assert e.batch_shape == (6,) + tuple(batch)
        assert e.sample(generator=g).shape == (6,) + tuple(batch)
        # the joint density of the last dimension
        if len(batch):
            ind = d.to_event(1)
            torch.testing.assert_close(ind.log_prob(x), d.log_prob(x).sum(-1))

    @pytest.mark.parametrize("a,b", WINDOWS)
    def test_vs_scipy(self, a, b):
        d = _dist(a, b)
        ref = st.truncnorm(a, b, loc=0.3, scale=2.0)
        z = _grid(a, b, 201)[1:-1]
        x = torch.tensor(0.3 + 2.0 * z, dtype=F64)
        np.testing.assert_allclose(d.log_prob(x).numpy(), ref.logpdf(x.numpy()),
                                   rtol=1e-10, atol=1e-6)
        np.testing.assert_allclose(d.cdf(x).numpy(), ref.cdf(x.numpy()), rtol=1e-9, atol=1e-12)
        q = np.array([1e-9, 1e-3, 0.1, 0.5, 0.9, 0.999, 1 - 1e-9])
        np.testing.assert_allclose(d.icdf(torch.tensor(q, dtype=F64)).numpy(), ref.ppf(q),
                                   rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(float(d.mean), ref.mean(), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(float(d.variance), ref.var(), rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(float(d.log_normalizer), _log_mass_mp(a, b), rtol=1e-12)

    def test_log_normal_mass(self):
        # log(Phi(u) - Phi(v)) against 50-digit arithmetic, in float64 and float32
        u = [9.0, -8.0, 2.0, INF, INF, 40.0, 1e-3, -37.5, 0.5]
        v = [8.0, -9.0, -2.0, 3.0, -INF, 39.0, 0.0, -38.0, -30.0]
        ref = torch.tensor([_log_mass_mp(a, b) for a, b in zip(v, u)], dtype=F64)
        for dtype, rtol in ((F64, 1e-12), (torch.float32, 1e-5)):
            got = log_normal_mass(torch.tensor(u, dtype=dtype), torch.tensor(v, dtype=dtype))
            torch.testing.assert_close(got.double(), ref, rtol=rtol, atol=0)
        # symmetry and the empty window
        uu, vv = torch.tensor(u[:6], dtype=F64), torch.tensor(v[:6], dtype=F64)
        torch.testing.assert_close(log_normal_mass(uu, vv), log_normal_mass(-vv, -uu))
        assert log_normal_mass(torch.tensor(1.0), torch.tensor(1.0)) == -INF

    @pytest.mark.parametrize("a,b", WINDOWS)
    def test_normalised_1d(self, a, b):
        # the density integrates to 1 over its window (adaptive quadrature, scaled x)
        d = _dist(a, b, loc=-1.0, scale=0.5)

        def f(z):
            x = torch.tensor(-1.0 + 0.5 * z, dtype=F64)
            return float(torch.exp(d.log_prob(x))) * 0.5

        lo = a if math.isfinite(a) else -INF
        hi = b if math.isfinite(b) else INF
        brk = [p for p in (0.0,) if lo < p < hi]
        total = 0.0
        edges = [lo, *brk, hi]
        for e0, e1 in zip(edges[:-1], edges[1:]):
            total += scipy.integrate.quad(f, e0, e1, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
        assert abs(total - 1.0) < 1e-8

    def test_normalised_2d(self):
        # a 2-D (Independent) density on a grid: one far-tail window, one one-sided window
        loc = torch.tensor([0.2, -0.4], dtype=F64)
        scale = torch.tensor([0.3, 0.8], dtype=F64)
        low = torch.tensor([0.2 + 0.3 * 8.0, -INF], dtype=F64)
        high = torch.tensor([0.2 + 0.3 * 9.0, 0.5], dtype=F64)
        d = TruncatedNormal(loc, scale, low, high).to_event(1)
        n = 1200
        x0 = torch.linspace(float(low[0]), float(high[0]), n, dtype=F64)
        x1 = torch.linspace(-0.4 - 0.8 * 12.0, 0.5, n, dtype=F64)
        X0, X1 = torch.meshgrid(x0, x1, indexing="ij")
        dens = torch.exp(d.log_prob(torch.stack([X0, X1], -1)))
        mass = torch.trapezoid(torch.trapezoid(dens, x1, dim=1), x0)
        assert abs(float(mass) - 1.0) < 1e-5
        assert dens[X1 > 0.5].numel() == 0 or (dens[X1 > 0.5] == 0).all()

    def test_outside_support(self):
        d = _dist(-1.0, 2.0)
        x = torch.tensor([0.3 - 2.0 - 1e-9, 0.3 + 4.0 + 1e-9, -INF, INF], dtype=F64)
        assert (d.log_prob(x) == -INF).all()
        torch.testing.assert_close(d.cdf(x), torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=F64))
        assert torch.isfinite(d.log_prob(torch.tensor([0.3 - 2.0, 0.3 + 4.0], dtype=F64))).all()
        strict = TruncatedNormal(d.loc, d.scale, d.low, d.high, validate_args=True)
        with pytest.raises(ValueError, match="value: expected values inside"):
            strict.log_prob(x)

    @pytest.mark.parametrize("a,b", [(-1.0, 2.0), (8.0, 9.0), (-9.0, -8.5), (1.5, INF),
                                     (-INF, -8.0), (12.0, 13.0), (-40.0, -39.0), (-INF, INF)])
    @pytest.mark.parametrize("dtype", [torch.float32, F64], ids=["f32", "f64"])
    def test_samples(self, a, b, dtype):
        # exact: always inside the window (far tails in float32 too), KS against scipy
        d = _dist(a, b, loc=0.0, scale=1.0, dtype=dtype)
        x = d.sample((20000,), generator=torch.Generator().manual_seed(2))
        assert x.dtype == dtype and torch.isfinite(x).all()
        assert ((x >= d.low) & (x <= d.high)).all()
        assert torch.isfinite(d.log_prob(x)).all()
        ref = st.truncnorm(a, b)
        assert st.kstest(x.double().numpy(), ref.cdf).pvalue > 1e-3
        y = ref.rvs(20000, random_state=np.random.default_rng(3))
        assert st.ks_2samp(x.double().numpy(), y).pvalue > 1e-3
        # moments of the samples against the closed forms
        m, v = float(d.mean), float(d.variance)
        assert abs(float(x.double().mean()) - m) < 5 * math.sqrt(v / 20000)
        assert abs(float(x.double().var()) / v - 1) < 0.05

    @pytest.mark.parametrize("a,b", [(-1.0, 2.0), (8.0, 9.0), (-INF, -8.0), (0.0, INF),
                                     (-40.0, -39.0)])
    def test_feature_moments_and_entropy(self, a, b):
        # closed forms against quadrature of x f(x), (x - m)^2 f(x), -f log f
        d = _dist(a, b, loc=0.3, scale=2.0)
        z = _grid(a, b, 200001)
        x = torch.tensor(0.3 + 2.0 * z, dtype=F64)
        lp = d.log_prob(x)
        f = torch.exp(lp)
        mean = torch.trapezoid(x * f, x)
        var = torch.trapezoid((x - mean) ** 2 * f, x)
        ent = torch.trapezoid(torch.where(f > 0, -f * lp, 0.0), x)
        torch.testing.assert_close(d.mean, mean, rtol=1e-7, atol=1e-9)
        torch.testing.assert_close(d.variance, var, rtol=1e-5, atol=1e-12)
        torch.testing.assert_close(d.entropy(), ent, rtol=1e-6, atol=1e-7)
        # float32 parameters: moments still accurate in the far tails (evaluated in float64)
        d32 = _dist(a, b, loc=0.3, scale=2.0, dtype=torch.float32)
        torch.testing.assert_close(d32.mean, d.mean.float(), rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(d32.variance, d.variance.float(), rtol=1e-3, atol=1e-7)

    def test_cdf_icdf_round_trip(self):
        for a, b in WINDOWS:
            d = _dist(a, b)
            q = torch.tensor([0.0, 1e-6, 0.25, 0.5, 0.75, 1 - 1e-6, 1.0], dtype=F64)
            x = d.icdf(q)
            assert ((x >= d.low) & (x <= d.high)).all()
            if math.isfinite(a):
                torch.testing.assert_close(x[0], d.low, rtol=0, atol=1e-12)
            if math.isfinite(b):
                torch.testing.assert_close(x[-1], d.high, rtol=0, atol=1e-12)
            torch.testing.assert_close(d.cdf(x[1:-1]), q[1:-1], rtol=1e-8, atol=1e-12)
        with pytest.raises(ValueError, match="value: expected probabilities"):
            _dist(-1.0, 1.0).icdf(torch.tensor([1.5], dtype=F64))

    def test_generator_reproducible(self):
        d = TruncatedNormal(torch.zeros(31), torch.full((31,), 0.2), -1.0, torch.full((31,), 0.5))
        a = d.sample((100,), generator=torch.Generator().manual_seed(7))
        b = d.sample((100,), generator=torch.Generator().manual_seed(7))
        c = d.sample((100,), generator=torch.Generator().manual_seed(8))
        assert torch.equal(a, b) and not torch.equal(a, c)
        # the global RNG is not touched
        state = torch.get_rng_state()
        d.sample((10,), generator=torch.Generator().manual_seed(7))
        assert torch.equal(state, torch.get_rng_state())

    def test_angular_prior_eq3(self):
        # eq. 3: N(theta_prev, diag) times the uniform on the joint limits, for human31 (root
        # translation and rotation unlimited, the rest limited; the previous pose on a bound)
        sk = human31().double()
        prev = sk.clamp(0.3 * torch.randn(31, generator=torch.Generator().manual_seed(9),
                                          dtype=F64))
        prev[sk.dof_index("l_knee_flex")] = 0.0  # straight knee: on its lower limit
        scale = torch.full((31,), 0.15, dtype=F64)
        prior = TruncatedNormal(prev, scale, sk.lower.double(), sk.upper.double())
        theta = prior.sample((5000,), generator=torch.Generator().manual_seed(10))
        assert theta.shape == (5000, 31) and sk.within_limits(theta).all()
        lp = prior.to_event(1).log_prob(theta)
        assert lp.shape == (5000,) and torch.isfinite(lp).all()
        knee = theta[:, sk.dof_index("l_knee_flex")]
        # half-normal on the limit: mean scale * sqrt(2 / pi), not a clamp's point mass
        assert (knee > 0).all()
        assert abs(float(knee.mean()) - 0.15 * math.sqrt(2 / math.pi)) < 0.005
        # a clamped Gaussian would put half of its mass on the bound
        assert (knee < 1e-6).float().mean() < 0.01

    def test_exception(self):
        one = torch.tensor(1.0)
        with pytest.raises(ValueError, match="scale: expected finite values > 0"):
            TruncatedNormal(0.0, torch.tensor([1.0, 0.0]), -1.0, 1.0)
        with pytest.raises(ValueError, match="scale"):
            TruncatedNormal(0.0, -one, -1.0, 1.0)
        with pytest.raises(ValueError, match="low, high: expected low < high"):
            TruncatedNormal(0.0, one, 1.0, 1.0)
        with pytest.raises(ValueError, match="low, high: expected low < high"):
            TruncatedNormal(0.0, one, torch.tensor([0.0, 2.0]), torch.tensor([1.0, 1.0]))
        for name, args in [("loc", (math.nan, 1.0, -1.0, 1.0)),
                           ("scale", (0.0, math.nan, -1.0, 1.0)),
                           ("low", (0.0, 1.0, math.nan, 1.0)),
                           ("high", (0.0, 1.0, -1.0, math.nan))]:
            with pytest.raises(ValueError, match=f"{name}: expected"):
                TruncatedNormal(*[torch.tensor(v) for v in args])
        with pytest.raises(ValueError, match="loc: expected finite"):
            TruncatedNormal(torch.tensor(INF), one, -1.0, 1.0)
        # validation can be switched off (e.g. for parameters known to be valid in a hot loop)
        TruncatedNormal(0.0, one, 1.0, 1.0, validate_args=False)


def _log_mass_mp(a, b):
    """log(Phi(b) - Phi(a)) with 50 significant digits (mpmath, a dependency of torch)."""
    mpmath = pytest.importorskip("mpmath")
    if a + b > 0:  # the same mass on the mirrored window, where Phi is small
        a, b = -b, -a
    with mpmath.workdps(50):
        lo = mpmath.mpf(0) if a == -INF else mpmath.ncdf(a)
        hi = mpmath.mpf(1) if b == INF else mpmath.ncdf(b)
        return float(mpmath.log(hi - lo))
