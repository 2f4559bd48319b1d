"""Tests for torchmocap.filters.optim.local (batched per-problem L-BFGS / Adam)."""

from __future__ import annotations

import math

import pytest
import torch

from torchmocap.filters.optim.local import LocalResult, minimise_local

F64 = torch.float64


def rosenbrock(x: torch.Tensor) -> torch.Tensor:
    return (100 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1 - x[:, :-1]) ** 2).sum(-1)


def _quadratic(p: int, d: int, seed: int = 0, dtype=F64):
    """Per-problem quadratics ``Σ_j c_ij (x_j − m_ij)²`` with conditioning up to 1e3."""
    g = torch.Generator().manual_seed(seed)
    m = torch.randn(p, d, generator=g, dtype=dtype)
    c = 10 ** (3 * torch.rand(p, d, generator=g, dtype=dtype))
    return m, c, lambda x: (c * (x - m) ** 2).sum(-1)


class TestLBFGS:
    def test_smoke(self):
        res = minimise_local(lambda x: (x**2).sum(-1), torch.ones(3, 2), iterations=5)
        assert isinstance(res, LocalResult)
        assert res.x.shape == (3, 2) and res.energy.shape == (3,) and res.final.shape == (3, 2)
        assert res.trace.shape == (6, 3) and res.converged.shape == (3,)

    def test_batched_quadratic(self):
        """Condition numbers up to 1e3: scipy's L-BFGS-B needs 75 (median) to 163 iterations
        for gtol 1e-9 on these; 200 iterations reach 1e-6 here."""
        m, _, energy = _quadratic(64, 10)
        res = minimise_local(energy, torch.zeros(64, 10, dtype=F64), iterations=200)
        assert float((res.x - m).abs().max()) < 1e-6
        assert bool(res.converged.all())

    @pytest.mark.parametrize("dim", [2, 5, 10])
    def test_rosenbrock(self, dim):
        g = torch.Generator().manual_seed(dim)
        start = torch.tensor([-1.2, 1.0] * dim, dtype=F64)[:dim]
        x0 = start + 0.1 * torch.randn(8, dim, generator=g, dtype=F64)
        res = minimise_local(rosenbrock, x0, iterations=300)
        assert float((res.x - 1).abs().max()) < 1e-4
        assert float(res.energy.max()) < 1e-8

    def test_problems_independent(self):
        """A problem's path does not depend on its batch-mates (one is scaled by 1e6)."""
        m, c, _ = _quadratic(4, 6, seed=1)
        c = c.clone()
        c[2] *= 1e6
        energy = lambda x: (c * (x - m) ** 2).sum(-1)
        x0 = torch.zeros(4, 6, dtype=F64)
        batch = minimise_local(energy, x0, iterations=8, tol=0.0)
        for i in range(4):
            alone = minimise_local(
                lambda x, i=i: (c[i] * (x - m[i]) ** 2).sum(-1),
                x0[i : i + 1],
                iterations=8,
                tol=0.0,
            )
            assert torch.allclose(batch.final[i], alone.final[0], rtol=1e-12, atol=1e-14)
        # torch.optim.LBFGS on the summed loss couples the problems (for contrast)
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([x], max_iter=8, line_search_fn="strong_wolfe")
        opt.step(lambda: (opt.zero_grad(), energy(x).sum().backward(), energy(x).sum())[2])
        err_joint = (x.detach()[0] - m[0]).abs().max()
        assert float((batch.final[0] - m[0]).abs().max()) < float(err_joint)

    def test_trace_monotone(self):
        x0 = torch.tensor([[-1.2, 1.0], [2.0, -1.0]], dtype=F64)
        res = minimise_local(rosenbrock, x0, iterations=50)
        assert torch.all(res.trace[1:] <= res.trace[:-1] + 1e-12)
        assert torch.allclose(res.energy, res.trace.min(0).values)
        assert torch.allclose(res.trace[0], rosenbrock(x0))

    def test_box_separable(self):
        """Separable quadratic: the box-constrained minimum is the clamped unconstrained one."""
        m, _, energy = _quadratic(16, 5, seed=2)
        lo = torch.tensor([-0.5, -0.2, -math.inf, 0.0, -1.0], dtype=F64)
        hi = torch.tensor([0.5, math.inf, 0.3, 0.1, 1.0], dtype=F64)
        res = minimise_local(energy, torch.zeros(16, 5, dtype=F64), lower=lo, upper=hi)
        assert torch.allclose(res.x, torch.maximum(torch.minimum(m, hi), lo), atol=1e-7)
        assert torch.all(res.x >= lo) and torch.all(res.x <= hi)

    def test_box_kkt(self):
        """Coupled quadratic with a box: projected gradient vanishes at the solution."""
        g = torch.Generator().manual_seed(3)
        a = torch.randn(8, 4, 4, generator=g, dtype=F64)
        q = a @ a.transpose(-1, -2) + 0.5 * torch.eye(4, dtype=F64)
        b = 3 * torch.randn(8, 4, generator=g, dtype=F64)
        energy = lambda x: 0.5 * (x[:, None, :] @ q @ x[:, :, None])[:, 0, 0] - (b * x).sum(-1)
        res = minimise_local(
            energy, torch.zeros(8, 4, dtype=F64), lower=-1.0, upper=1.0, iterations=200
        )
        x = res.x
        grad = (q @ x[..., None])[..., 0] - b
        free = ~(((x <= -1) & (grad > 0)) | ((x >= 1) & (grad < 0)))
        assert float((grad * free).abs().max()) < 1e-6
        assert bool(((x.abs() - 1).abs() < 1e-12).any())  # some bounds are active

    def test_float32(self):
        m, _, energy = _quadratic(8, 4, dtype=torch.float32)
        res = minimise_local(energy, torch.zeros(8, 4), iterations=200)
        assert res.x.dtype == torch.float32
        assert float((res.x - m).abs().max()) < 1e-3

    def test_decode(self):
        basis = torch.tensor([[1.0, 1.0, 0.0], [0.0, 1.0, -1.0]], dtype=F64)
        target = torch.tensor([0.5, -1.0], dtype=F64) @ basis
        res = minimise_local(
            lambda y: ((y - target) ** 2).sum(-1),
            torch.zeros(2, 2, dtype=F64),
            decode=lambda x: x @ basis,
        )
        assert torch.allclose(res.x, torch.tensor([0.5, -1.0], dtype=F64).expand(2, 2), atol=1e-7)


class TestAdam:
    def test_batched_quadratic(self):
        g = torch.Generator().manual_seed(4)
        m = torch.randn(32, 6, generator=g, dtype=F64)
        energy = lambda x: ((x - m) ** 2).sum(-1)
        res = minimise_local(
            energy, torch.zeros(32, 6, dtype=F64), method="adam", iterations=1500, lr=0.02
        )
        assert float((res.x - m).abs().max()) < 1e-3
        assert res.trace.shape == (1501, 32)

    def test_rosenbrock_2d(self):
        x0 = torch.tensor([[-1.2, 1.0]], dtype=F64)
        res = minimise_local(rosenbrock, x0, method="adam", iterations=2500, lr=0.04)
        assert float((res.x - 1).abs().max()) < 1e-3  # measured 2.6e-5

    def test_box(self):
        m = torch.tensor([[2.0, -3.0, 0.2]], dtype=F64)
        res = minimise_local(
            lambda x: ((x - m) ** 2).sum(-1),
            torch.zeros(1, 3, dtype=F64),
            method="adam",
            iterations=500,
            lr=0.05,
            lower=-1.0,
            upper=1.0,
        )
        assert torch.allclose(res.x, torch.tensor([[1.0, -1.0, 0.2]], dtype=F64), atol=1e-3)

    @pytest.mark.parametrize("iterations", [0, 1, 7])
    def test_one_evaluation_per_iterate_and_the_reference_iterates(self, iterations):
        """Adam evaluates the energy once per iterate (``iterations + 1`` calls, the value taken
        with the gradient doubles as the iterate's trace entry) and visits the iterates of a plain
        ``torch.optim.Adam`` loop with clamping: trace, best point and last point match it."""
        m, c, energy = _quadratic(5, 3, seed=2)
        lo, hi = -0.5, 0.8
        calls = []

        def counted(x):
            calls.append(x.requires_grad)
            return energy(x)

        x0 = torch.zeros(5, 3, dtype=F64)
        res = minimise_local(
            counted, x0, method="adam", iterations=iterations, lr=0.1, lower=lo, upper=hi
        )
        assert len(calls) == iterations + 1
        x = x0.clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=0.1)
        ref = []
        for _ in range(iterations):
            opt.zero_grad()
            v = energy(x)
            ref.append(v.detach())
            v.sum().backward()
            opt.step()
            with torch.no_grad():
                x.clamp_(lo, hi)
        ref.append(energy(x).detach())
        ref = torch.stack(ref)
        torch.testing.assert_close(res.trace, ref, rtol=0, atol=0)
        torch.testing.assert_close(res.final, x.detach(), rtol=0, atol=0)
        torch.testing.assert_close(res.energy, ref.min(0).values, rtol=0, atol=0)
        assert torch.equal(energy(res.x), res.energy)


class TestErrors:
    def test_exception(self):
        good = lambda x: (x**2).sum(-1)
        x0 = torch.zeros(3, 2)
        with pytest.raises(ValueError, match="energy.*non-finite"):
            minimise_local(lambda x: (x**2).sum(-1) * float("nan"), x0)
        with pytest.raises(ValueError, match="energy.*\\(3,\\)"):
            minimise_local(lambda x: x**2, x0)
        with pytest.raises(ValueError, match="energy.*differentiabl"):
            minimise_local(lambda x: torch.zeros(3), x0)
        with pytest.raises(TypeError, match="energy"):
            minimise_local(None, x0)
        with pytest.raises(ValueError, match="x0"):
            minimise_local(good, torch.zeros(3))
        with pytest.raises(ValueError, match="x0.*finite"):
            minimise_local(good, torch.full((3, 2), math.inf))
        with pytest.raises(TypeError, match="x0"):
            minimise_local(good, torch.zeros(3, 2, dtype=torch.int64))
        with pytest.raises(ValueError, match="method"):
            minimise_local(good, x0, method="newton")
        with pytest.raises(ValueError, match="iterations"):
            minimise_local(good, x0, iterations=-1)
        with pytest.raises(ValueError, match="lower"):
            minimise_local(good, x0, lower=torch.zeros(3))
        with pytest.raises(ValueError, match="lower"):
            minimise_local(good, x0, lower=1.0, upper=0.0)
        with pytest.raises(ValueError, match="lr"):
            minimise_local(good, x0, method="adam", lr=0.0)
        with pytest.raises(ValueError, match="history"):
            minimise_local(good, x0, history=0)
        with pytest.raises(ValueError, match="method"):
            minimise_local(good, x0, method="sgd")

    def test_a_registered_optimiser_is_dispatched_to_by_name(self, monkeypatch):
        """``OPTIMISERS`` is the one table of methods: minimise_local and LocalInference accept
        a name once it is registered and refuse it otherwise."""
        from torchmocap.filters import LocalInference
        from torchmocap.filters.optim import local
        from torchmocap.skeleton import human31

        calls = []

        def fake(f, x0, lo, hi, it, history, lr, tol):
            calls.append((it, history, lr, tol))
            return local.OPTIMISERS["adam"](f, x0, lo, hi, it, history, lr, tol)

        _, _, energy = _quadratic(3, 2, seed=1)
        x0 = torch.zeros(3, 2, dtype=F64)
        with pytest.raises(ValueError, match="method: expected one of \\['adam', 'lbfgs'\\]"):
            LocalInference(human31(), method="fake")
        monkeypatch.setitem(local.OPTIMISERS, "fake", fake)
        minimise_local(energy, x0, method="fake", iterations=3, lr=0.5, history=4, tol=1e-6)
        LocalInference(human31(), method="fake")
        assert calls == [(3, 4, 0.5, 1e-6)]
