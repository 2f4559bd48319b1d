"""Batched tracking: ``B`` tracks in one process, the particles of all of them in one energy batch.

A sweep over seeds runs the same tracker on the same sequence ``B`` times. Three quarters of a
frame are the likelihood's energy evaluations; here the ``B`` tracks advance frame by frame in
lockstep and, whenever each of them asks for the energy of its ``P`` particles, the ``B × P``
particles are evaluated in one call of the frame's energy. Everything else — proposals,
selection, annealing schedules, estimates, the per-track random generator — stays per track and
is the unmodified code of the tracker's own components, so the weights of a track are normalised
and resampled among its own particles only, and **track ``b`` follows the arithmetic of the separate
run with seed ``b``** except for the energy call itself: a call on ``B x P`` rows may round the
last bit of a row differently than one on ``P`` rows (kernels chosen by batch size and CPU).
Each energy equals the separate run's to float rounding, so tracks agree on short horizons and
are statistically equivalent; over many frames a particle tracker amplifies the rounding (the
local descent of the refined presets most), so bit-identical tracks are not promised.

How: each track's :meth:`~torchmocap.filters.Tracker.step` runs as a cooperative task in its own
thread; exactly one task runs at a time (no data race, no extra CPU use: the threads take turns,
in group order). A task's energy call hands its particles to the scheduler and waits; when every
running task waits, the scheduler concatenates their particles by frame energy, evaluates each
batch once (under ``torch.no_grad``, as the inference itself asks) and hands every task its
slice. Energy calls that need gradients (local descent) are evaluated directly, unbatched.

* :func:`track_seeds` — ``B`` seeds of one tracker on one sequence (shared components, one energy
  per frame: the batched case).
* :func:`track_groups` — any list of :class:`BatchGroup` (tracker, sequence, seed): groups that
  share a tracker and a sequence share the energy; different sequences each need their own
  tracker (its sensor calibration and body are the sequence's) and are tracked side by side
  in one process, their energies evaluated per sequence (a likelihood binds one frame's
  observations).

Groups that share a tracker share its components: its first frame is set up once (the sensor
calibration of eq. 8, a body fit) and each group gets its own generator. ``refine_first_frame``
(a randomised first-frame search) needs a tracker per seed.

Example:
    >>> tracks = track_seeds(tracker, sequence, seeds=[0, 1, 2, 3])   # doctest: +SKIP
    >>> [t.theta.shape for t in tracks]                                 # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from torchmocap.filters.tracking.state import Track
from torchmocap.filters.tracking.tracker import Tracker, check_seed, check_working_memory
from torchmocap.likelihoods.base import FrameEnergy

__all__ = ["BatchGroup", "Lockstep", "track_groups", "track_seeds"]

_MAIN = -1


class _Aborted(Exception):
    """Raised inside a task whose batch was abandoned (another task failed)."""


class Lockstep:
    """Runs ``size`` jobs as cooperative tasks, one at a time, in persistent threads, and
    evaluates the tasks' :meth:`request` calls of the same key as one batch.

    Each round of :meth:`run` gives task ``i`` the job ``jobs[i]`` (or none); tasks run in index
    order until they finish or call :meth:`request`; then the waiting requests are grouped by
    key, each group's tensors are concatenated (in task order) along dim 0, evaluated once by
    the group's function (in chunks of at most ``max_batch`` rows when given) and split back.
    Deterministic: the order of everything is fixed.
    """

    def __init__(self, size: int, max_batch: int | None = None) -> None:
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"size: expected an int >= 1, got {size!r}")
        if max_batch is not None and (isinstance(max_batch, bool)
                                      or not isinstance(max_batch, int) or max_batch < 1):
            raise ValueError(f"max_batch: expected an int >= 1 or None, got {max_batch!r}")
        self.size = size
        self.max_batch = max_batch
        self._cv = threading.Condition()
        self._turn = _MAIN
        self._closed = False
        self._jobs: list[Callable[[], Any] | None] = [None] * size
        self._requests: dict[int, tuple[Any, Callable, torch.Tensor]] = {}
        self._replies: dict[int, tuple[bool, Any]] = {}
        self._done: dict[int, tuple[bool, Any]] = {}
        self._abort = False
        self._num_threads = torch.get_num_threads()
        self._threads = [threading.Thread(target=self._worker, args=(i,), daemon=True,
                                          name=f"torchmocap-lockstep-{i}") for i in range(size)]
        for t in self._threads:
            t.start()

    # ------------------------------------------------------------------ task side
    def _worker(self, i: int) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._turn == i or self._closed)
                if self._closed:
                    return
                job = self._jobs[i]
            # OpenMP's thread count is per thread: follow the scheduler's (a ThreadGovernor
            # may have changed it between rounds)
            if torch.get_num_threads() != self._num_threads:
                torch.set_num_threads(self._num_threads)
            try:
                out = (True, job())
            except BaseException as e:  # delivered to run()
                out = (False, e)
            with self._cv:
                self._jobs[i] = None
                self._done[i] = out
                self._turn = _MAIN
                self._cv.notify_all()

    def request(self, index: int, key: Any, fn: Callable[[torch.Tensor], torch.Tensor],
                x: torch.Tensor) -> torch.Tensor:
        """From task ``index``: ``fn(x)``, evaluated together with the other tasks' requests
        of the same ``key`` (``fn`` must act on each row of ``x`` independently)."""
        with self._cv:
            if self._abort:
                raise _Aborted()
            self._requests[index] = (key, fn, x)
            self._turn = _MAIN
            self._cv.notify_all()
            self._cv.wait_for(lambda: self._turn == index or self._closed)
            if self._closed or self._abort:
                raise _Aborted()
            ok, value = self._replies.pop(index)
        if not ok:
            raise value
        return value

    # ------------------------------------------------------------------ scheduler side
    def _resume(self, i: int) -> None:
        with self._cv:
            self._turn = i
            self._cv.notify_all()
            self._cv.wait_for(lambda: self._turn == _MAIN)

    def _evaluate(self, waiting: list[int]) -> None:
        batches: dict[Any, list[int]] = {}
        for i in waiting:
            batches.setdefault(self._requests[i][0], []).append(i)
        for idx in batches.values():
            fn = self._requests[idx[0]][1]
            xs = [self._requests[i][2] for i in idx]
            try:
                with torch.no_grad():
                    x = xs[0] if len(xs) == 1 else torch.cat(xs)
                    m = self.max_batch
                    v = fn(x) if m is None or x.shape[0] <= m else \
                        torch.cat([fn(c) for c in torch.split(x, m)])
                parts = [v] if len(xs) == 1 else \
                    list(torch.split(v, [x.shape[0] for x in xs]))
                replies = [(True, p) for p in parts]
            except Exception as e:  # raised in every task of the batch, where it asked
                replies = [(False, e)] * len(idx)
            for i, r in zip(idx, replies):
                self._requests.pop(i)
                self._replies[i] = r

    def run(self, jobs: Sequence[Callable[[], Any] | None]) -> list[Any]:
        """One round: run ``jobs`` (``None``: task idle) to completion; their results in
        order. The first job that raised re-raises here, after the others were abandoned."""
        if len(jobs) != self.size:
            raise ValueError(f"jobs: expected {self.size}, got {len(jobs)}")
        if self._closed:
            raise RuntimeError("Lockstep: closed")
        self._done.clear()
        self._num_threads = torch.get_num_threads()
        active = [i for i, j in enumerate(jobs) if j is not None]
        for i in active:
            self._jobs[i] = jobs[i]
        error = None
        while active:
            for i in active:
                self._resume(i)
            active = [i for i in active if i not in self._done]
            failed = [i for i in sorted(self._done) if not self._done[i][0]
                      and not isinstance(self._done[i][1], _Aborted)]
            if failed and error is None:
                error = self._done[failed[0]][1]
                self._abort = True
                self._requests.clear()
            if active and not self._abort:
                self._evaluate(active)
        self._abort = False
        self._requests.clear()
        self._replies.clear()
        if error is not None:
            raise error
        return [self._done[i][1] if i in self._done else None for i in range(self.size)]

    def close(self) -> None:
        """Stop the task threads."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        for t in self._threads:
            t.join()

    def __enter__(self) -> Lockstep:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _SharedEnergy(FrameEnergy):
    """A task's view of a frame energy shared by the tasks of a batch: calls under
    ``torch.no_grad`` on ``(P, D)`` particles are batched, anything else is evaluated directly
    (the other methods of the frame energy are its own)."""

    def __init__(self, energy: FrameEnergy, lockstep: Lockstep, index: int, key: Any) -> None:
        super().__init__(energy.likelihood, energy.observation, energy.skeleton)
        self._energy, self._lockstep, self._index, self._key = energy, lockstep, index, key

    def __call__(self, x, *args, **kwargs):
        if args or kwargs or torch.is_grad_enabled() or not isinstance(x, torch.Tensor) \
                or x.dim() != 2:
            return self._energy(x, *args, **kwargs)
        return self._lockstep.request(self._index, self._key, self._energy, x)


@dataclass
class BatchGroup:
    """One track of a batch.

    Attributes:
        tracker: the tracker (groups that share it and the sequence share the frame energy).
        sequence: the observations.
        seed: the seed of this track's generator (default: the tracker's ``seed``).
        theta0: the first pose (default: as :meth:`Tracker.run` finds it).
    """

    tracker: Tracker
    sequence: Any
    seed: int | None = None
    theta0: torch.Tensor | None = None


def _check_groups(groups: Sequence[BatchGroup]) -> None:
    if not groups:
        raise ValueError("groups: expected at least one group")
    seen: dict[int, int] = {}
    for b, g in enumerate(groups):
        if not isinstance(g, BatchGroup):
            raise TypeError(f"groups[{b}]: expected a BatchGroup, got {type(g).__name__}")
        if not isinstance(g.tracker, Tracker):
            raise TypeError(f"groups[{b}].tracker: expected a Tracker, got "
                            f"{type(g.tracker).__name__}")
        if g.seed is not None:
            check_seed(g.seed, f"groups[{b}].seed")
        first = seen.setdefault(id(g.tracker), b)
        if first == b:
            continue
        other = groups[first]
        if g.sequence is not other.sequence:
            raise ValueError(
                f"groups[{b}]: shares its tracker with groups[{first}] but tracks another "
                "sequence; build one tracker per sequence (its sensor calibration and body "
                "belong to the sequence)")
        if g.tracker.refine_first_frame:
            raise ValueError(
                f"groups[{b}]: tracker {g.tracker.name!r} refines the first frame (a randomised "
                "search that calibrates the tracker); build one tracker per seed")
        same = (g.theta0 is None and other.theta0 is None) or (
            g.theta0 is not None and other.theta0 is not None
            and torch.equal(torch.as_tensor(g.theta0), torch.as_tensor(other.theta0)))
        if not same:
            raise ValueError(f"groups[{b}]: shares its tracker with groups[{first}] but starts "
                             "from another theta0")


def _tracking(sequence):
    return None if sequence.imu is None else sequence.imu.tracking.nonzero()[:, 0]


def track_groups(groups: Sequence[BatchGroup], progress: bool = True,
                 callbacks: Sequence[Callable] = (), max_batch: int | None = None
                 ) -> list[Track]:
    """Track every group's sequence in lockstep; returns one :class:`Track` per group.

    Args:
        groups: the tracks (see :class:`BatchGroup` and the module docstring).
        progress: a tqdm progress bar over frames.
        callbacks: callables ``(states, infos)`` run after every frame with the groups'
            states and diagnostics (``None`` for a group whose sequence has ended), e.g. a
            :class:`~torchmocap.threads.ThreadGovernor`.
        max_batch: most particles per energy call (a larger batch is evaluated in chunks);
            None = all of them at once. On a CPU, blocks that outgrow the caches can cost
            more than the calls they save (``experiments/benchmarks/batched.py --max-batch``).

    A frame's ``FrameInfo.seconds`` is the wall time of the whole batch's frame; its
    ``batch_size`` is ``B``.
    """
    from tqdm import tqdm

    _check_groups(groups)
    check_working_memory([g.tracker for g in groups])
    B = len(groups)
    states: list = [None] * B
    first_state: dict[int, Any] = {}
    for b, g in enumerate(groups):
        tr, seq = g.tracker, g.sequence
        tr.check_sequence(seq)
        seed = tr.seed if g.seed is None else int(g.seed)
        if id(tr) in first_state:  # the shared first frame: set up once, own generator
            st = first_state[id(tr)]
            gen = torch.Generator(device=st.history.device).manual_seed(seed)
            states[b] = type(st)(history=st.history.clone(), frame=st.frame,
                                 generator_state=gen.get_state(),
                                 estimates=list(st.estimates),
                                 infos=[dataclasses.replace(st.infos[0])],
                                 particles=st.particles, log_weights=st.log_weights,
                                 carry=st.carry)
            continue
        theta0 = g.theta0 if g.theta0 is not None else tr.first_pose(seq)
        states[b] = first_state[id(tr)] = tr.init(theta0, tr.observe(seq.frame(0),
                                                                      _tracking(seq)), seed=seed)
    lengths = [g.sequence.num_frames for g in groups]
    T = max(lengths)
    infos: list = [None] * B
    with Lockstep(B, max_batch) as lock:
        for t in tqdm(range(1, T), disable=not progress, desc=f"track[batch of {B}]",
                      unit="frame"):
            energies: dict[tuple[int, int], tuple[Any, Any]] = {}
            jobs: list = [None] * B
            for b, g in enumerate(groups):
                if t >= lengths[b]:
                    infos[b] = None
                    continue
                key = (id(g.tracker), id(g.sequence))
                if key not in energies:
                    tr = g.tracker
                    frame = tr._on_device(tr.observe(g.sequence.frame(t),
                                                     _tracking(g.sequence)))
                    tr._check_frame(frame)
                    energies[key] = (frame, tr.frame_energy(frame))
                frame, energy = energies[key]
                shared = _SharedEnergy(energy, lock, b, key)
                jobs[b] = (lambda tr=g.tracker, st=states[b], fr=frame, e=shared:
                           tr.step(st, fr, energy=e))
            for b, out in enumerate(lock.run(jobs)):
                if out is not None:
                    states[b], _, infos[b] = out
                    infos[b].batch_size = B
            for cb in callbacks:
                cb(states, infos)
    tracks = []
    for g, st in zip(groups, states):
        secs = [i.seconds for i in st.infos[1:] if i.seconds is not None]
        tracks.append(g.tracker.finish(Track(
            theta=torch.stack(st.estimates), infos=st.infos,
            seconds_per_frame=float(sum(secs) / max(len(secs), 1)))))
    return tracks


def track_seeds(tracker: Tracker, sequence, seeds: Sequence[int],
                theta0: torch.Tensor | None = None, progress: bool = True,
                callbacks: Sequence[Callable] = (), max_batch: int | None = None
                ) -> list[Track]:
    """``B = len(seeds)`` tracks of ``sequence`` by ``tracker``, one per seed, their particles
    in one energy batch per annealing layer; track ``b`` follows ``tracker.run(sequence)`` with
    ``tracker.seed = seeds[b]`` (to float rounding of the batched energy: see the module
    docstring). See :func:`track_groups` for ``callbacks`` and
    ``max_batch``."""
    seeds = list(seeds)
    if not seeds:
        raise ValueError("seeds: expected at least one seed")
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int):
            raise ValueError(f"seeds: expected integers, got {s!r}")
    return track_groups([BatchGroup(tracker, sequence, s, theta0) for s in seeds],
                        progress=progress, callbacks=callbacks, max_batch=max_batch)
