"""Tests for torchmocap.filters.optim.resampling."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.filters.optim.resampling import (
    KeepRedrawResampler,
    MultinomialResampler,
    ResidualResampler,
    StratifiedResampler,
    SystematicResampler,
    as_resampler,
    counts_to_indices,
    effective_sample_size,
    ess_fraction,
    gather_particles,
    keep_redraw_resample,
    multinomial_resample,
    normalize_log_weights,
    offspring_counts,
    residual_resample,
    stratified_resample,
    systematic_resample,
)

FUNCS = {
    "multinomial": multinomial_resample,
    "systematic": systematic_resample,
    "stratified": stratified_resample,
    "residual": residual_resample,
    "keep_redraw": keep_redraw_resample,
}
MODULES = {
    "multinomial": MultinomialResampler,
    "systematic": SystematicResampler,
    "stratified": StratifiedResampler,
    "residual": ResidualResampler,
    "keep_redraw": KeepRedrawResampler,
}


def _weights(n: int, seed: int, zeros: int = 3) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    log_w = 2.0 * torch.randn(n, generator=g, dtype=torch.float64)
    log_w[torch.randperm(n, generator=g)[:zeros]] = -math.inf
    return log_w


class TestEffectiveSampleSize:
    def test_feature(self):
        n = 50
        assert effective_sample_size(torch.zeros(n)).item() == pytest.approx(n, rel=1e-6)
        one_hot = torch.full((n,), -math.inf)
        one_hot[7] = 0.0
        assert effective_sample_size(one_hot).item() == pytest.approx(1.0)
        log_w = _weights(n, 0)
        w = torch.exp(log_w)
        w = w / w.sum()
        assert effective_sample_size(log_w).item() == pytest.approx(1 / (w**2).sum().item())
        assert ess_fraction(log_w).item() == pytest.approx(1 / (w**2).sum().item() / n)

    def test_scale_free(self):
        # huge log weights: never exponentiated raw, shift-invariant
        log_w = 1e4 * torch.randn(100, generator=torch.Generator().manual_seed(1))
        e1 = effective_sample_size(log_w)
        e2 = effective_sample_size(log_w + 1e6)
        assert torch.isfinite(e1) and 1.0 <= e1.item() <= 100
        assert e1.item() == pytest.approx(e2.item(), rel=1e-3)

    def test_cardinality(self):
        assert effective_sample_size(torch.zeros(2, 3, 10)).shape == (2, 3)

    def test_normalize(self):
        log_w = _weights(20, 2)
        lw = normalize_log_weights(log_w)
        assert torch.logsumexp(lw, -1).item() == pytest.approx(0.0, abs=1e-12)


def _offspring_variance(name: str, w: torch.Tensor) -> torch.Tensor:
    """Exact variance of each particle's offspring count for normalised weights ``w (N,)``
    and ``N`` draws, from each scheme's construction:

    * multinomial: ``N W (1 - W)``;
    * systematic: ``f (1 - f)``, ``f = frac(N W)`` (floor or ceil of ``N W``; one shared
      uniform);
    * stratified: ``sum_s p_s (1 - p_s)``, ``p_s`` = the share of stratum ``s`` covered by the
      particle's CDF interval (independent uniforms per stratum);
    * residual: ``R r (1 - r)``, ``r = frac(N W) / R``, ``R = N - sum floor(N W)``;
    * keep/redraw: slot ``i`` keeps its particle (prob ``k_i = W_i / max W``) or is redrawn;
      ``count_i = Bernoulli(k_i + (1 - k_i) W_i) + sum_{j != i} Bernoulli((1 - k_j) W_i)``.
    """
    w = w.double()
    n = w.numel()
    nw = n * w
    if name == "multinomial":
        return nw * (1 - w)
    if name == "systematic":
        f = nw - torch.floor(nw)
        return f * (1 - f)
    if name == "stratified":
        hi = torch.cumsum(nw, 0)
        lo = hi - nw
        s = torch.arange(n, dtype=torch.float64)
        p = (torch.minimum(hi[:, None], s + 1) - torch.maximum(lo[:, None], s)).clamp(0, 1)
        return (p * (1 - p)).sum(1)
    if name == "residual":
        f = nw - torch.floor(nw)
        r = f.sum()
        return f * (1 - f / r) if float(r) > 0 else torch.zeros_like(w)
    if name == "keep_redraw":
        k = w / w.max()
        a = (1 - k) * w[:, None]  # a[i, j] = P(slot j redrawn onto particle i)
        q = k + (1 - k) * w
        var = q * (1 - q) + (a * (1 - a)).sum(1) - torch.diagonal(a * (1 - a))
        return var
    raise KeyError(name)


@pytest.mark.parametrize("name", list(FUNCS))
class TestResamplers:
    def test_smoke(self, name):
        g = torch.Generator().manual_seed(0)
        idx = FUNCS[name](torch.zeros(200), g)
        assert idx.shape == (200,) and idx.dtype == torch.int64
        assert int(idx.min()) >= 0 and int(idx.max()) < 200

    def test_cardinality(self, name):
        g = torch.Generator().manual_seed(0)
        log_w = torch.randn(2, 3, 17, generator=g)
        assert FUNCS[name](log_w, g).shape == (2, 3, 17)
        if name == "keep_redraw":
            with pytest.raises(ValueError, match="num"):
                FUNCS[name](log_w, g, num=5)
            return
        assert FUNCS[name](log_w, g, num=5).shape == (2, 3, 5)
        assert FUNCS[name](log_w, g, num=40).shape == (2, 3, 40)

    @pytest.mark.parametrize("tiny", [False, True], ids=["weights", "tiny_weights"])
    def test_unbiased(self, name, tiny):
        """Mean offspring counts over R draws equal N·W, judged against each scheme's own
        offspring variance (multinomial N W (1 - W); the others far smaller, see
        :func:`_offspring_variance`), so a bias of a fraction of an offspring is caught; with
        weights of 1e-12 too (a particle that must practically never be drawn)."""
        n, reps = 20, 4000
        log_w = _weights(n, 3)
        if tiny:
            log_w[[2, 7]] = math.log(1e-12) + torch.logsumexp(log_w, 0)
        w = torch.exp(normalize_log_weights(log_w))
        g = torch.Generator().manual_seed(11)
        idx = FUNCS[name](log_w.expand(reps, n), g)
        counts = offspring_counts(idx, n).double()
        assert torch.all(counts.sum(-1) == n)
        mean = counts.mean(0)
        var = _offspring_variance(name, w)
        # zero-variance particles (systematic: N W a whole number; zero weights) are exact
        exact = var < 1e-300
        assert torch.equal(mean[exact], (n * w)[exact].round())
        z = ((mean - n * w) / torch.sqrt(var / reps))[~exact].abs()
        assert float(z.max()) < 5.0, (name, z.max(), mean, n * w)
        if tiny:  # P(any offspring in 4000 draws) ~ 1e-7
            assert float(counts[:, [2, 7]].sum()) == 0
        # the variance model is right, not only an upper bound: sample variance agrees
        sv = counts.var(0)
        ok = var > 1e-3
        assert torch.allclose(sv[ok], var[ok], rtol=0.15), (name, sv[ok] / var[ok])

    def test_batch_rows_independent(self, name):
        """Each row of a batch follows its own weights (one-hot rows give constant indices)."""
        n = 30
        log_w = torch.full((4, n), -math.inf)
        for r, k in enumerate([0, 5, 17, n - 1]):
            log_w[r, k] = 0.0
        idx = FUNCS[name](log_w, torch.Generator().manual_seed(0))
        for r, k in enumerate([0, 5, 17, n - 1]):
            assert torch.all(idx[r] == k)

    def test_neg_inf_never_selected(self, name):
        n = 64
        log_w = torch.randn(500, n, generator=torch.Generator().manual_seed(4))
        log_w[:, ::3] = -math.inf
        log_w[:, -1] = -math.inf  # the last particle: the clamp must not give it offspring
        idx = FUNCS[name](log_w, torch.Generator().manual_seed(5))
        assert not bool(((idx % 3) == 0).any())
        assert not bool((idx == n - 1).any())

    def test_float32_cumsum_trap(self, name):
        """N = 1e5 float32 weights: indices stay in range and zero-weight tail is never hit."""
        n = 100_000
        log_w = torch.randn(n, generator=torch.Generator().manual_seed(6)).float()
        log_w[-10:] = -math.inf
        for seed in range(3):
            idx = FUNCS[name](log_w, torch.Generator().manual_seed(seed))
            assert int(idx.max()) < n - 10

    def test_degenerate(self, name):
        log_w = torch.tensor([-1e30, 0.0, -1e30, -1e30])
        idx = FUNCS[name](log_w, torch.Generator().manual_seed(0))
        assert torch.all(idx == 1)

    def test_reproducible(self, name):
        log_w = _weights(50, 8)
        a = FUNCS[name](log_w, torch.Generator().manual_seed(3))
        b = FUNCS[name](log_w, torch.Generator().manual_seed(3))
        assert torch.equal(a, b)

    def test_exception(self, name):
        f = FUNCS[name]
        with pytest.raises(ValueError, match="log_w.*NaN"):
            f(torch.tensor([0.0, float("nan"), 1.0]))
        with pytest.raises(ValueError, match="log_w.*\\+inf"):
            f(torch.tensor([0.0, float("inf")]))
        with pytest.raises(ValueError, match="log_w.*all -inf"):
            f(torch.tensor([[0.0, 1.0], [-math.inf, -math.inf]]))
        with pytest.raises(ValueError, match="log_w.*shape"):
            f(torch.tensor(1.0))
        with pytest.raises(ValueError, match="log_w.*shape"):
            f(torch.zeros(3, 0))
        with pytest.raises(TypeError, match="log_w"):
            f(torch.zeros(3, dtype=torch.int64))
        with pytest.raises(TypeError, match="log_w"):
            f([0.0, 1.0])
        with pytest.raises(ValueError, match="num"):
            f(torch.zeros(3), None, -1)

    def test_module(self, name):
        log_w = _weights(40, 9)
        mod = MODULES[name]()
        a = mod(log_w, torch.Generator().manual_seed(2))
        b = FUNCS[name](log_w, torch.Generator().manual_seed(2))
        assert torch.equal(a, b)


class TestVarianceProperties:
    def test_systematic_floor_ceil(self):
        n, reps = 37, 2000
        log_w = _weights(n, 12, zeros=5)
        nw = n * torch.exp(normalize_log_weights(log_w))
        idx = systematic_resample(log_w.expand(reps, n), torch.Generator().manual_seed(1))
        c = offspring_counts(idx, n).double()
        assert torch.all(c >= torch.floor(nw) - 1e-9)
        assert torch.all(c <= torch.ceil(nw) + 1e-9)

    def test_stratified_within_one(self):
        n, reps = 37, 2000
        log_w = _weights(n, 13, zeros=5)
        nw = n * torch.exp(normalize_log_weights(log_w))
        idx = stratified_resample(log_w.expand(reps, n), torch.Generator().manual_seed(1))
        c = offspring_counts(idx, n).double()
        assert torch.all(c >= torch.floor(nw) - 1)
        assert torch.all(c <= torch.ceil(nw) + 1)

    def test_residual_deterministic_part(self):
        n, reps = 37, 2000
        log_w = _weights(n, 14, zeros=5)
        nw = n * torch.exp(normalize_log_weights(log_w))
        idx = residual_resample(log_w.expand(reps, n), torch.Generator().manual_seed(1))
        c = offspring_counts(idx, n).double()
        assert torch.all(c >= torch.floor(nw) - 1e-9)
        # each particle gets at most floor + (number of residual draws)
        r = n - torch.floor(nw).sum()
        assert torch.all(c <= torch.floor(nw) + r)

    def test_variance_ordering(self):
        """Total offspring variance: systematic, stratified, residual below multinomial."""
        n, reps = 30, 4000
        log_w = _weights(n, 15, zeros=0)
        tot = {}
        for name, f in FUNCS.items():
            idx = f(log_w.expand(reps, n), torch.Generator().manual_seed(21))
            tot[name] = float(offspring_counts(idx, n).double().var(0).sum())
        w = torch.exp(normalize_log_weights(log_w))
        exact_multi = float((n * w * (1 - w)).sum())
        assert tot["multinomial"] == pytest.approx(exact_multi, rel=0.1)
        for name in ("systematic", "stratified", "residual"):
            assert tot[name] < 0.8 * tot["multinomial"], tot

    def test_residual_not_filterpy_bias(self):
        """filterpy's residual weights W - floor(N W) would overweight heavy particles here."""
        n, reps = 4, 20000
        w = torch.tensor([0.55, 0.15, 0.15, 0.15], dtype=torch.float64)
        idx = residual_resample(torch.log(w).expand(reps, n), torch.Generator().manual_seed(0))
        mean = offspring_counts(idx, n).double().mean(0)
        # exact: floor(N W) = (2, 0, 0, 0), R = 2 residual draws with probabilities
        # (0.1, 0.3, 0.3, 0.3) -> E[count_0] = 2.2
        assert float(mean[0]) == pytest.approx(2.2, abs=0.02)


class TestHelpers:
    def test_counts_to_indices(self):
        c = torch.tensor([[0, 2, 1, 0], [1, 1, 1, 0]])
        assert counts_to_indices(c).tolist() == [[1, 1, 2], [0, 1, 2]]
        with pytest.raises(ValueError, match="counts"):
            counts_to_indices(torch.tensor([[1, 0], [1, 1]]))

    def test_offspring_roundtrip(self):
        idx = torch.tensor([[3, 0, 3, 1]])
        c = offspring_counts(idx, 5)
        assert c.tolist() == [[1, 1, 0, 2, 0]]
        assert counts_to_indices(c).tolist() == [[0, 1, 3, 3]]

    def test_gather(self):
        x = torch.arange(12.0).reshape(2, 3, 2)
        idx = torch.tensor([[2, 2, 0], [1, 0, 0]])
        out = gather_particles(x, idx)
        assert torch.equal(out[0], x[0, [2, 2, 0]]) and torch.equal(out[1], x[1, [1, 0, 0]])
        with pytest.raises(ValueError, match="particles"):
            gather_particles(x[0], idx)

    def test_as_resampler(self):
        """Resamplers are objects (configs choose one by ``_target_``); no name lookup."""
        assert isinstance(as_resampler(None), SystematicResampler)
        assert isinstance(as_resampler(None, default=MultinomialResampler), MultinomialResampler)
        f = lambda lw, g=None, num=None: systematic_resample(lw, g, num)
        assert as_resampler(f) is f
        with pytest.raises(TypeError, match="selection: expected a resampler object"):
            as_resampler("systematic", "selection")
        with pytest.raises(TypeError, match="resampler"):
            as_resampler(3)

    def test_uniform_keeps_all(self):
        """Equal weights: every particle is kept in place (keep probability 1)."""
        idx = keep_redraw_resample(torch.zeros(3, 50), torch.Generator().manual_seed(0))
        assert torch.equal(idx, torch.arange(50).expand(3, 50))

    def test_keep_probability(self):
        """Slot i keeps its own particle with probability W_i / max W (+ redraw chance W_i)."""
        n, reps = 5, 20000
        w = torch.tensor([0.4, 0.2, 0.2, 0.1, 0.1], dtype=torch.float64)
        idx = keep_redraw_resample(torch.log(w).expand(reps, n), torch.Generator().manual_seed(1))
        own = (idx == torch.arange(n)).double().mean(0)
        expect = w / w.max() + (1 - w / w.max()) * w
        assert torch.allclose(own, expect, atol=0.015)


# ---------------------------------------------------------------------------------------------
# property-based checks
# ---------------------------------------------------------------------------------------------

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@st.composite
def _log_weight_rows(draw):
    n = draw(st.integers(1, 40))
    rows = draw(st.integers(1, 4))
    vals = draw(
        st.lists(
            st.one_of(st.floats(-50, 50), st.just(-math.inf)),
            min_size=n * rows,
            max_size=n * rows,
        )
    )
    lw = torch.tensor(vals, dtype=torch.float32).reshape(rows, n)
    lw[:, draw(st.integers(0, n - 1))] = draw(st.floats(-50, 50))  # one finite per row
    return lw


@settings(max_examples=60, deadline=None)
@given(lw=_log_weight_rows(), seed=st.integers(0, 2**31 - 1), name=st.sampled_from(list(FUNCS)))
def test_property_valid_indices(lw, seed, name):
    """Any valid weights: indices in range, zero weights never chosen, N offspring per row."""
    idx = FUNCS[name](lw, torch.Generator().manual_seed(seed))
    n = lw.shape[-1]
    assert idx.shape == lw.shape
    assert int(idx.min()) >= 0 and int(idx.max()) < n
    assert bool(torch.isfinite(torch.gather(lw, -1, idx)).all())


@settings(max_examples=60, deadline=None)
@given(lw=_log_weight_rows(), seed=st.integers(0, 2**31 - 1))
def test_property_systematic_floor_ceil(lw, seed):
    n = lw.shape[-1]
    nw = n * torch.exp(normalize_log_weights(lw.double()))
    c = offspring_counts(systematic_resample(lw, torch.Generator().manual_seed(seed)), n)
    assert torch.all(c >= torch.floor(nw - 1e-5)) and torch.all(c <= torch.ceil(nw + 1e-5))
