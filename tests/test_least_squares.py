"""The damped least-squares core: damping rules, the iteration's contract (retirement,
compaction, retries, stationary stops), and a batch of linear and nonlinear problems solved to
their closed-form minima."""

from __future__ import annotations

import pytest
import torch

from torchmocap.least_squares import (
    DampedProblem,
    Marquardt,
    Nielsen,
    Verdict,
    compact_at_once,
    compact_when_worthwhile,
    damped_least_squares,
)


class Quadratic(DampedProblem):
    """``min |A x - b|^2 + c sum(x^4)`` per row: an LM step on the Gauss-Newton model; a record
    of every call for the contract tests."""

    def __init__(self, A, b, c=0.0, tol=1e-14, stationary_tol=None):
        self.A, self.b, self.c, self.tol, self.st = A, b, c, tol, stationary_tol
        n, _, D = A.shape
        self.x = torch.zeros(n, D, dtype=A.dtype)
        self.ids = torch.arange(n)
        self.out = self.x.clone()
        self.calls: list[tuple[str, int]] = []
        self.retired: list[int] = []

    def value(self, x, A, b):
        r = (A @ x[..., None])[..., 0] - b
        return (r * r).sum(-1) + self.c * (x ** 4).sum(-1)

    def grad_hess(self, x, A, b):
        r = (A @ x[..., None])[..., 0] - b
        g = 2 * (A.transpose(1, 2) @ r[..., None])[..., 0] + 4 * self.c * x ** 3
        H = 2 * A.transpose(1, 2) @ A + torch.diag_embed(12 * self.c * x ** 2)
        return g, H

    def propose(self, mu, rows):
        self.calls.append(("propose", rows.numel()))
        A, b, x = self.A[rows], self.b[rows], self.x[rows]
        g, H = self.grad_hess(x, A, b)
        diag = H.diagonal(dim1=1, dim2=2)
        A_mu = H + mu[:, None, None] * torch.diag_embed(diag)
        return x + torch.linalg.solve(A_mu, -g[..., None])[..., 0]

    def assess(self, trial, mu, rows):
        A, b = self.A[rows], self.b[rows]
        old, new = self.value(self.x[rows], A, b), self.value(trial, A, b)
        ok = new < old
        return Verdict(accepted=ok, gain=torch.ones_like(new),
                       converged=(old - new).abs() <= self.tol * old.clamp_min(1e-300))

    def commit(self, trial, accepted, rows):
        self.x[rows] = torch.where(accepted[:, None], trial, self.x[rows])

    def stationary(self):
        if self.st is None:
            return None
        g, _ = self.grad_hess(self.x, self.A, self.b)
        return g.abs().amax(-1) <= self.st

    def retire(self, done, ids):
        self.retired += ids[done].tolist()
        self.out[ids[done]] = self.x[done]

    def keep(self, mask):
        self.A, self.b, self.x, self.ids = self.A[mask], self.b[mask], self.x[mask], self.ids[mask]


def _batch(n=6, m=5, d=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, m, d, generator=g, dtype=torch.float64),
            torch.randn(n, m, generator=g, dtype=torch.float64))


class TestDampingRules:
    def test_marquardt(self):
        rule = Marquardt(initial=1e-3, decrease=3, increase=4, minimum=1e-9, maximum=1e9,
                         stall=1e8)
        mu = rule.start(3, torch.float64, None)
        mu = rule.update(mu, torch.tensor([True, False, True]), None)
        torch.testing.assert_close(mu, torch.tensor([1e-3 / 3, 4e-3, 1e-3 / 3],
                                                    dtype=torch.float64))
        big = torch.tensor([3e8, 9.9e7, 1e9], dtype=torch.float64)
        assert rule.stalled(big).tolist() == [True, False, True]
        assert rule.update(big, torch.zeros(3, dtype=torch.bool), None).max() == 1e9

    def test_nielsen(self):
        rule = Nielsen(initial=1.0)
        st = rule.start(2, torch.float64, None)
        # rho = 1: the model was exact, mu shrinks by the most (1/3); a rejection doubles nu
        st = rule.update(st, torch.tensor([True, False]), torch.tensor([1.0, 0.0],
                                                                       dtype=torch.float64))
        torch.testing.assert_close(st, torch.tensor([[1 / 3, 2.0], [2.0, 4.0]],
                                                    dtype=torch.float64))
        with pytest.raises(ValueError, match="gain"):
            rule.update(st, torch.tensor([True, True]), None)


class TestDampedLeastSquares:
    def test_feature_linear_problems_reach_the_normal_equations(self):
        A, b = _batch()
        prob = Quadratic(A.clone(), b.clone())
        run = damped_least_squares(prob, 6, 100, Marquardt())
        exact = torch.linalg.lstsq(A, b[..., None]).solution[..., 0]
        torch.testing.assert_close(prob.out, exact, rtol=1e-9, atol=1e-9)
        assert bool(run.converged.all()) and sorted(prob.retired) == list(range(6))

    def test_feature_nonlinear_with_nielsen_and_lazy_compaction(self):
        A, b = _batch(n=40, seed=1)
        a, c = Quadratic(A.clone(), b.clone(), c=0.3), Quadratic(A.clone(), b.clone(), c=0.3)
        damped_least_squares(a, 40, 200, Marquardt())
        damped_least_squares(c, 40, 200, Nielsen(), compact=compact_when_worthwhile)
        torch.testing.assert_close(a.out, c.out, rtol=1e-6, atol=1e-6)  # the same minima
        g, _ = a.grad_hess(a.out, A, b)
        assert float(g.abs().max()) < 1e-6

    def test_feature_finished_problems_leave_the_batch(self):
        A, b = _batch(n=8, seed=2)
        b[:4] = 0.0  # x = 0 is these problems' minimum: they stop at once (stationary)
        prob = Quadratic(A, b, stationary_tol=1e-12)
        damped_least_squares(prob, 8, 50, Marquardt(), compact=compact_at_once)
        assert prob.retired[:4] == [0, 1, 2, 3]  # written out before any step
        assert prob.calls[0] == ("propose", 4)  # the first step only for the other four

    def test_feature_retry_ends_every_iteration_with_a_decrease(self):
        A, b = _batch(n=1, seed=3)
        # a tiny damping overshoots on the quartic: retries raise it within the iteration
        prob = Quadratic(A, b * 50, c=5.0)
        run = damped_least_squares(prob, 1, 3, Marquardt(initial=1e-9), retry=True)
        proposals = sum(1 for c in prob.calls if c[0] == "propose")
        assert run.iterations == 3 and proposals > 3  # rejected trials retried in-iteration
        plain = Quadratic(A, b * 50, c=5.0)
        damped_least_squares(plain, 1, 3, Marquardt(initial=1e-9))
        v = prob.value(prob.out, A, b * 50)
        assert float(v) < float(plain.value(plain.out, A, b * 50))  # three real steps

    def test_feature_zero_iterations_returns_the_start(self):
        A, b = _batch()
        prob = Quadratic(A, b)
        run = damped_least_squares(prob, 6, 0, Marquardt())
        assert run.iterations == 0 and torch.equal(prob.out, torch.zeros(6, 3,
                                                                          dtype=torch.float64))
