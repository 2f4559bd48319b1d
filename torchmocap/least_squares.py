"""Batched damped least squares: the Levenberg–Marquardt iteration every solver of the package runs.

A batch holds ``n`` independent problems (poses fitted to joints, keypoints, a mixture's samples,
a subject's offsets), each with its own damping ``mu``. :func:`damped_least_squares` owns the
iteration; a :class:`DampedProblem` owns its model — residuals, derivatives, the damped linear
system with its box constraints — and its tests. Per iteration, over the problems still running:

1. the problem proposes a trial point from its model damped by ``mu``
   (:meth:`~DampedProblem.propose`);
2. it evaluates the trials and says which it accepts, how well each did against its model (a gain
   ratio, when it has one) and which have converged (:meth:`~DampedProblem.assess`);
3. the :class:`DampingRule` updates ``mu`` — :class:`Marquardt` divides it on an accepted step and
   multiplies it on a rejected one; :class:`Nielsen` scales it by the gain ratio — and says when a
   problem has stalled (its damping blown up);
4. with ``retry``, a rejected trial is proposed again with the raised damping before the
   iteration ends (Marquardt's original rule: every iteration ends with a decrease or a stall);
5. the accepted trials replace their problems' points (:meth:`~DampedProblem.commit`); problems
   that converged or stalled are written out (:meth:`~DampedProblem.retire`) and leave the batch
   once ``compact(finished, running)`` says so (at once by default; a problem may stay, frozen,
   until enough have finished to make shrinking its tensors worthwhile);
6. the remaining problems' derivatives are taken at their new points
   (:meth:`~DampedProblem.relinearize`; with ``relinearize_retiring`` right after the commit,
   for the problems that finish too), and a problem may stop there, before its next step
   (:meth:`~DampedProblem.stationary`: a vanishing projected gradient).

Rows are always *working rows*: positions in the problem's current (compacted) tensors.

Example:
    >>> import torch
    >>> class Line(DampedProblem):  # fit y = a x to data, one problem per row of ``ys``
    ...     def __init__(self, xs, ys):
    ...         self.xs, self.ys = xs, ys
    ...         self.a = torch.zeros(ys.shape[0], 1, dtype=ys.dtype)
    ...         self.out = self.a.clone()
    ...     def cost(self, a):
    ...         return ((a * self.xs - self.ys) ** 2).sum(-1)
    ...     def propose(self, mu, rows):
    ...         J, r = self.xs, self.a[rows] * self.xs - self.ys[rows]
    ...         H = (J * J).sum(-1, keepdim=True)
    ...         return self.a[rows] - (J * r).sum(-1, keepdim=True) / (H * (1 + mu[:, None]))
    ...     def assess(self, trial, mu, rows):
    ...         new, old = self.cost(trial), self.cost(self.a[rows])
    ...         return Verdict(accepted=new < old, converged=(old - new).abs() < 1e-12)
    ...     def commit(self, trial, accepted, rows):
    ...         self.a[rows] = torch.where(accepted[:, None], trial, self.a[rows])
    ...     def retire(self, done, ids):
    ...         self.out[ids[done]] = self.a[done]
    ...     def keep(self, mask):
    ...         self.a, self.ys = self.a[mask], self.ys[mask]
    >>> xs = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    >>> prob = Line(xs, torch.stack([2 * xs, -xs]))
    >>> res = damped_least_squares(prob, 2, iterations=50, damping=Marquardt(initial=1e-3))
    >>> torch.allclose(prob.out.squeeze(-1), torch.tensor([2.0, -1.0], dtype=torch.float64))
    True
    >>> bool(res.converged.all())
    True
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

__all__ = [
    "DampedProblem",
    "DampingRule",
    "LeastSquaresRun",
    "Marquardt",
    "Nielsen",
    "Verdict",
    "compact_at_once",
    "compact_when_worthwhile",
    "damped_least_squares",
]


@dataclass
class Verdict:
    """A problem's assessment of its trials (every tensor ``(n,)`` over the rows assessed).

    Attributes:
        accepted: the trial replaces the current point.
        gain: the actual over the predicted decrease of the cost (for :class:`Nielsen`), or
            None.
        converged: the problem has converged (it stops, and counts as converged).
        stop: the problem stops without having converged (e.g. a vanished step), or None.
    """

    accepted: Tensor
    gain: Tensor | None = None
    converged: Tensor | None = None
    stop: Tensor | None = None


class DampingRule(ABC):
    """How the damping ``mu`` of each problem follows its trials."""

    @abstractmethod
    def start(self, n: int, dtype: torch.dtype, device) -> Tensor:
        """The initial damping state ``(n, ...)`` (its column 0, or itself, is ``mu``)."""

    @staticmethod
    def mu(state: Tensor) -> Tensor:
        """``mu (n,)`` of a damping state."""
        return state if state.dim() == 1 else state[:, 0]

    @abstractmethod
    def update(self, state: Tensor, accepted: Tensor, gain: Tensor | None) -> Tensor:
        """The state after trials that were ``accepted`` (or not)."""

    @abstractmethod
    def stalled(self, state: Tensor) -> Tensor:
        """``(n,)`` problems whose damping has blown up (they stop, not converged)."""


@dataclass
class Marquardt(DampingRule):
    """``mu / decrease`` (at least ``minimum``) after an accepted trial, ``mu * increase`` (at
    most ``maximum``) after a rejected one; a problem stalls at ``mu >= stall``."""

    initial: float = 1e-3
    decrease: float = 3.0
    increase: float = 4.0
    minimum: float = 1e-9
    maximum: float = 1e9
    stall: float | None = None  # None: maximum

    def start(self, n: int, dtype: torch.dtype, device) -> Tensor:
        return torch.full((n,), float(self.initial), dtype=dtype, device=device)

    def update(self, state: Tensor, accepted: Tensor, gain: Tensor | None) -> Tensor:
        return torch.where(accepted, (state / self.decrease).clamp_min(self.minimum),
                           (state * self.increase).clamp_max(self.maximum))

    def stalled(self, state: Tensor) -> Tensor:
        return state >= (self.maximum if self.stall is None else self.stall)


@dataclass
class Nielsen(DampingRule):
    """Nielsen's rule: after an accepted trial of gain ratio ``rho``, ``mu * max(min_shrink,
    1 - (2 rho - 1)^3)`` and ``nu = 2``; after a rejected one ``mu * nu`` and ``nu * 2``. The state
    is ``(mu, nu)`` per problem; a problem stalls at ``mu >= maximum``."""

    initial: float = 1e-3
    min_shrink: float = 1.0 / 3.0
    maximum: float = 1e12

    def start(self, n: int, dtype: torch.dtype, device) -> Tensor:
        return torch.stack([torch.full((n,), float(self.initial), dtype=dtype, device=device),
                            torch.full((n,), 2.0, dtype=dtype, device=device)], 1)

    def update(self, state: Tensor, accepted: Tensor, gain: Tensor | None) -> Tensor:
        if gain is None:
            raise ValueError("gain: Nielsen's rule needs the trials' gain ratios")
        mu, nu = state.unbind(1)
        shrink = (1 - (2 * gain - 1) ** 3).clamp_min_(self.min_shrink)
        return torch.stack([torch.where(accepted, mu * shrink, mu * nu),
                            torch.where(accepted, 2.0, 2 * nu)], 1)

    def stalled(self, state: Tensor) -> Tensor:
        return state[:, 0] >= self.maximum


class DampedProblem(ABC):
    """``n`` independent damped least-squares problems (module docstring). Subclasses hold their
    working tensors; every ``rows`` argument indexes them (working rows)."""

    @abstractmethod
    def propose(self, mu: Tensor, rows: Tensor) -> Any:
        """Trial points of the problems ``rows``, from their models damped by ``mu (r,)``."""

    @abstractmethod
    def assess(self, trial: Any, mu: Tensor, rows: Tensor) -> Verdict:
        """Evaluate the trials of ``rows`` (``mu``: the damping they were proposed with)."""

    @abstractmethod
    def commit(self, trial: Any, accepted: Tensor, rows: Tensor) -> None:
        """Take the ``accepted (r,)`` trials of ``rows`` as the problems' points."""

    @abstractmethod
    def retire(self, done: Tensor, ids: Tensor) -> None:
        """Write out the problems ``done (n,)`` (a mask over the working rows); ``ids (n,)``
        are the working rows' indices in the original batch."""

    @abstractmethod
    def keep(self, mask: Tensor) -> None:
        """Drop the working rows not in ``mask (n,)`` from the working tensors."""

    #: take the derivatives of the accepted trials right after they are committed, also of the
    #: problems that finish in that iteration (before they leave the batch); else after the
    #: finished ones left, for the problems still running
    relinearize_retiring: bool = False

    def relinearize(self, accepted: Tensor) -> None:  # noqa: B027 (optional hook)
        """Take the derivatives at the new points of the working rows ``accepted (n,)`` (a
        mask; default: the problem computed them in :meth:`assess`)."""

    def stationary(self) -> Tensor | None:
        """``(n,)`` problems converged at their current points, before a step (default:
        None)."""
        return None

    def iterated(self, iteration: int, ids: Tensor) -> None:  # noqa: B027 (optional hook)
        """Called at the end of every iteration (e.g. to record the cost)."""


def compact_at_once(finished: int, running: int) -> bool:
    """Finished problems leave the batch in the iteration they finish."""
    return finished > 0


def compact_when_worthwhile(finished: int, running: int) -> bool:
    """Finished problems stay in the batch, frozen, until at least 16 of them or an eighth of
    the batch have finished (shrinking large working tensors has a cost)."""
    return finished >= max(16, running // 8)


@dataclass
class LeastSquaresRun:
    """What :func:`damped_least_squares` did.

    Attributes:
        converged: ``(n,)`` problems that converged (the others stalled, stopped or ran out of
            iterations).
        iterations: the iterations run (the largest over the batch).
    """

    converged: Tensor
    iterations: int


def damped_least_squares(problem: DampedProblem, n: int, iterations: int,
                         damping: DampingRule, *, retry: bool = False,
                         compact: Callable[[int, int], bool] = compact_at_once,
                         device=None, dtype: torch.dtype = torch.float64) -> LeastSquaresRun:
    """Run the damped least-squares iteration of ``problem``'s ``n`` problems (module
    docstring) for at most ``iterations`` iterations.

    Args:
        problem: the :class:`DampedProblem` (its derivatives taken at the start points).
        n: the number of problems.
        iterations: the most iterations.
        damping: the :class:`DampingRule`.
        retry: re-propose rejected trials with the raised damping within the iteration, until
            accepted or stalled.
        compact: ``compact(finished, running) -> bool``: whether the finished problems leave
            the batch at the end of an iteration (:func:`compact_at_once`,
            :func:`compact_when_worthwhile`); until then they stay, frozen (never accepted).
        device, dtype: of the damping (the problems' dtype).

    Returns:
        :class:`LeastSquaresRun`; the problems' results are what :meth:`DampedProblem.retire`
        wrote.
    """
    ids = torch.arange(n, device=device)
    state = damping.start(n, dtype, device)
    finished = torch.zeros(n, dtype=torch.bool, device=device)
    converged = torch.zeros(n, dtype=torch.bool, device=device)
    out_converged = torch.zeros(n, dtype=torch.bool, device=device)
    early = problem.relinearize_retiring
    it = 0
    def leave(ids, state, converged, accepted, finished):
        """The finished problems written out and dropped, when ``compact`` says so."""
        if not bool(finished.any()) or not compact(int(finished.sum()), ids.numel()):
            return ids, state, converged, accepted, finished
        problem.retire(finished, ids)
        out_converged[ids[finished]] = converged[finished]
        keep = ~finished
        problem.keep(keep)
        return ids[keep], state[keep], converged[keep], accepted[keep], finished[keep]

    accepted = torch.zeros(n, dtype=torch.bool, device=device)
    still = problem.stationary()
    if still is not None:
        converged, finished = converged | still, finished | still
    for it in range(1, iterations + 1):  # noqa: B007 (read after the loop)
        if bool(finished.all()):
            it -= 1
            break
        ids, state, converged, accepted, finished = leave(ids, state, converged, accepted,
                                                          finished)
        rows = torch.arange(ids.numel(), device=device)
        mu = damping.mu(state)
        trial = problem.propose(mu, rows)
        v = problem.assess(trial, mu, rows)
        accepted = v.accepted & ~finished
        problem.commit(trial, accepted, rows)
        state = damping.update(state, accepted, v.gain)
        conv = v.converged if v.converged is not None else torch.zeros_like(finished)
        stop = v.stop if v.stop is not None else torch.zeros_like(finished)
        if retry:  # rejected trials again with the raised damping, until accepted or stalled
            pending = ~accepted & ~finished & ~damping.stalled(state)
            while bool(pending.any()):
                sub = pending.nonzero().squeeze(1)
                mu_s = damping.mu(state[sub])
                t_s = problem.propose(mu_s, rows[sub])
                v_s = problem.assess(t_s, mu_s, rows[sub])
                problem.commit(t_s, v_s.accepted, rows[sub])
                state = state.index_copy(0, sub, damping.update(state[sub], v_s.accepted,
                                                                 v_s.gain))
                accepted = accepted.index_copy(0, sub, v_s.accepted)
                if v_s.converged is not None:
                    conv = conv.index_copy(0, sub, v_s.converged)
                if v_s.stop is not None:
                    stop = stop.index_copy(0, sub, v_s.stop)
                pending = pending.index_copy(
                    0, sub, ~v_s.accepted & ~damping.stalled(state[sub]))
        converged = converged | (conv & ~finished)
        finished = finished | converged | damping.stalled(state) | stop
        problem.iterated(it, ids)
        if early:
            problem.relinearize(accepted)
        if it == iterations or bool(finished.all()):
            break
        ids, state, converged, accepted, finished = leave(ids, state, converged, accepted,
                                                          finished)
        if not early:
            problem.relinearize(accepted)
        still = problem.stationary()
        if still is not None:
            converged = converged | (still & ~finished)
            finished = finished | still
    everyone = torch.ones_like(finished)
    problem.retire(everyone, ids)
    out_converged[ids] = converged
    return LeastSquaresRun(converged=out_converged, iterations=it)
