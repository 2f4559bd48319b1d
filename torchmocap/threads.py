"""How many threads torch may use: the thread policy of the commands (``threads: auto``).

Why a policy at all: torch's CPU kernels split work over ``torch.get_num_threads()`` OpenMP
threads (by default one per physical core) and wait at the end of every parallel region for the
slowest of them. When another process keeps one of those cores busy, the thread that shares its
core runs only in the scheduler's time slices, every parallel region waits for it, and a tracker
frame of 0.2 s takes 4–13 s (10–50× slower). The OpenMP wait policy does not cure this: a
passive wait stops the waiting threads from burning cycles, but the region still ends only when
the descheduled thread has done its share. What does cure it is not to ask for a core that is
busy. So, with ``threads: auto``:

* ``threads = min(cores per job, free cores)``, at least 1, where
* **cores per job** are the cores this process may run on (``os.sched_getaffinity``: a SLURM
  job's allocation, a ``taskset``) divided by the jobs a multirun launcher runs at the same time
  on this machine (joblib's ``n_jobs``; a ``submitit``/``ray`` job's ``cpus_per_task`` /
  ``num_cpus``), and
* **free cores** are those cores minus the ones other processes keep busy, measured from the
  kernel's per-CPU counters (``/proc/stat``) over a short interval, less this process's own CPU
  time; elsewhere the load average stands in.
* An explicit choice wins: ``threads: N``, or ``OMP_NUM_THREADS`` set in the environment (the
  SLURM preset sets it to the job's CPUs).

:class:`ThreadGovernor` re-applies the policy between frames (every ``interval`` seconds) so that
a load arriving mid-run — another sweep's jobs starting — drops the tracker to fewer threads,
and a load leaving gives them back. The OpenMP wait policy is left at the runtime's default: with
one thread per free core a short active wait costs nothing, and ``OMP_WAIT_POLICY=PASSIVE`` made
idle frames slower without fixing the busy case (``experiments/benchmarks/under_load.py``
measures both).

:func:`choose_threads` is the pure decision (tested on its own); :func:`busy_cores` and
:func:`launcher_share` gather its inputs; :func:`apply_thread_policy` does all three and calls
``torch.set_num_threads``.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = [
    "CpuSample",
    "ThreadChoice",
    "ThreadGovernor",
    "apply_thread_policy",
    "available_cores",
    "busy_cores",
    "choose_threads",
    "launcher_share",
    "parse_threads",
]

#: a core counts as busy when other processes use more than this fraction of it
BUSY_THRESHOLD = 0.5


@dataclass(frozen=True)
class ThreadChoice:
    """A decision of :func:`choose_threads`: ``threads`` and why (one line, for logs)."""

    threads: int
    reason: str


def parse_threads(value: Any) -> int | None:
    """``"auto"`` (or None) -> None; a positive integer (or its string) -> that integer;
    anything else -> ``ValueError`` naming ``threads``."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "auto"):
        return None
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"threads: expected 'auto' or an integer >= 1, got {value!r}")
    return value


def choose_threads(cores: int, busy: float = 0.0, jobs: int = 1, cpus_per_job: int | None = None,
                   requested: Any = "auto", omp_num_threads: str | None = None) -> ThreadChoice:
    """The thread count for one tracking process (pure: no measurement, no side effect).

    Args:
        cores: cores this process may run on (its CPU affinity), >= 1.
        busy: cores kept busy by *other* processes (a float, e.g. 0.97 for one busy loop).
        jobs: jobs of a sweep that run at the same time on these cores (joblib ``n_jobs``).
        cpus_per_job: cores a launcher allots to each job (``submitit``'s ``cpus_per_task``).
        requested: ``"auto"`` or an explicit integer (the ``threads`` setting).
        omp_num_threads: the ``OMP_NUM_THREADS`` environment variable, if set.

    Example:
        >>> choose_threads(cores=2, busy=0.97).threads   # one core busy: stay off it
        1
        >>> choose_threads(cores=16, jobs=4).threads      # 4 parallel jobs share 16 cores
        4
    """
    explicit = parse_threads(requested)
    if explicit is not None:
        return ThreadChoice(explicit, f"threads={explicit} (set)")
    if omp_num_threads is not None and str(omp_num_threads).strip():
        try:
            n = parse_threads(str(omp_num_threads).strip())
        except ValueError:
            n = None
        if n is not None:
            return ThreadChoice(n, f"OMP_NUM_THREADS={n} (environment)")
    cores = max(1, int(cores))
    share = cores
    why = [f"{cores} cores"]
    if jobs > 1:
        share = max(1, cores // int(jobs))
        why.append(f"{jobs} parallel jobs -> {share} each")
    if cpus_per_job is not None and cpus_per_job >= 1:
        share = min(share, int(cpus_per_job))
        why.append(f"{cpus_per_job} cpus per job")
    busy = max(0.0, float(busy)) if math.isfinite(busy) else 0.0
    taken = math.floor(busy + (1.0 - BUSY_THRESHOLD))  # cores used > BUSY_THRESHOLD count
    free = max(1, cores - taken)
    if taken:
        why.append(f"{busy:.2f} busy elsewhere -> {free} free")
    threads = max(1, min(share, free))
    return ThreadChoice(threads, "auto: " + ", ".join(why))


def available_cores() -> list[int]:
    """CPU ids this process may run on (its affinity; all CPUs where that is unknown)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return list(range(os.cpu_count() or 1))


@dataclass(frozen=True)
class CpuSample:
    """Busy and total jiffies of some CPUs, this process's CPU seconds and the wall time."""

    busy: int
    total: int
    own: float
    wall: float


def _read_proc_stat(cpus: list[int]) -> tuple[int, int] | None:
    try:
        with open("/proc/stat", encoding="ascii") as f:
            lines = f.readlines()
    except OSError:
        return None
    want = {f"cpu{c}" for c in cpus}
    busy = total = 0
    found = 0
    for line in lines:
        parts = line.split()
        if not parts or parts[0] not in want:
            continue
        v = [int(x) for x in parts[1:9]] + [0] * max(0, 8 - len(parts[1:9]))
        user, nice, system, idle, iowait, irq, softirq, steal = v[:8]
        b = user + nice + system + irq + softirq + steal
        busy += b
        total += b + idle + iowait
        found += 1
    return (busy, total) if found else None


def cpu_sample(cpus: list[int] | None = None) -> CpuSample | None:
    """A :class:`CpuSample` of ``cpus`` (default: this process's), None without ``/proc``."""
    got = _read_proc_stat(available_cores() if cpus is None else cpus)
    if got is None:
        return None
    return CpuSample(got[0], got[1], time.process_time(), time.monotonic())


def busy_between(a: CpuSample, b: CpuSample, cores: int) -> float:
    """Cores kept busy by other processes between two samples (this process's CPU time, its
    threads' spinning included, is taken out)."""
    dt = b.total - a.total
    if dt <= 0:
        return 0.0
    wall = max(b.wall - a.wall, 1e-9)
    used = cores * (b.busy - a.busy) / dt  # cores in use, all processes
    own = (b.own - a.own) / wall
    return max(0.0, used - own)


def busy_cores(interval: float = 0.25, cpus: list[int] | None = None) -> float:
    """Cores of ``cpus`` (default: this process's) that other processes keep busy, measured
    over ``interval`` seconds (this process sleeps meanwhile). Without ``/proc/stat`` (not
    Linux): the 1-minute load average, less one for this process, capped by the cores."""
    cpus = available_cores() if cpus is None else cpus
    a = cpu_sample(cpus)
    if a is None:
        try:
            load = os.getloadavg()[0]
        except (AttributeError, OSError):  # pragma: no cover
            return 0.0
        return min(float(len(cpus)), max(0.0, load - 1.0))
    time.sleep(interval)
    b = cpu_sample(cpus)
    return busy_between(a, b, len(cpus)) if b is not None else 0.0


def launcher_share(launcher: Mapping | None, cores: int) -> tuple[int, int | None]:
    """``(parallel jobs, cpus per job)`` of a Hydra launcher config (``hydra.launcher``).

    joblib runs ``n_jobs`` jobs at once on this machine (``-1`` = one per core, ``-2`` = all
    but one, as joblib counts); ``submitit`` jobs get ``cpus_per_task`` cores each and ray jobs
    ``num_cpus``; the basic launcher runs one job at a time.
    """
    if not launcher:
        return 1, None
    target = str(launcher.get("_target_", ""))
    if "Joblib" in target or "joblib" in target:
        n = launcher.get("n_jobs", -1)
        n = -1 if n is None else int(n)
        jobs = n if n > 0 else max(1, cores + 1 + n)
        return max(1, jobs), None
    if "submitit" in target:
        cpus = launcher.get("cpus_per_task")
        return 1, None if cpus is None else int(cpus)
    if "ray" in target.lower():
        ray = launcher.get("ray") or {}
        remote = ray.get("remote") if isinstance(ray, Mapping) else None
        cpus = remote.get("num_cpus") if isinstance(remote, Mapping) else None
        return 1, None if cpus is None else int(cpus)
    return 1, None


def apply_thread_policy(requested: Any = "auto", launcher: Mapping | None = None,
                        interval: float = 0.25) -> ThreadChoice:
    """Measure, decide (:func:`choose_threads`) and ``torch.set_num_threads``; returns the
    choice. ``launcher``: the Hydra launcher config of a multirun job (None otherwise)."""
    import torch

    cpus = available_cores()
    jobs, per_job = launcher_share(launcher, len(cpus))
    omp = os.environ.get("OMP_NUM_THREADS")
    explicit = parse_threads(requested) is not None or bool(omp and omp.strip())
    busy = 0.0 if explicit else busy_cores(interval, cpus)
    choice = choose_threads(len(cpus), busy, jobs, per_job, requested, omp)
    if choice.threads > len(cpus):  # oversubscribed: every thread waits for a core
        import warnings

        where = "threads" if parse_threads(requested) is not None else "OMP_NUM_THREADS"
        warnings.warn(f"{where}={choice.threads}: more threads than the {len(cpus)} cores this "
                      f"process may use; threads then wait for each other (many times slower): "
                      f"use at most {len(cpus)} (threads=auto chooses)", stacklevel=2)
    torch.set_num_threads(choice.threads)
    return choice


class ThreadGovernor:
    """Re-applies the ``auto`` policy between frames: a callback for
    :meth:`~torchmocap.filters.Tracker.run` (``callbacks=[governor]``).

    Every ``interval`` seconds it measures the other processes' load since its last look (from
    ``/proc/stat``, this process's own CPU time taken out: no sleeping) and sets the thread count
    when :func:`choose_threads` changes its mind. It does nothing for an explicit choice
    (``threads: N`` or ``OMP_NUM_THREADS``) or without ``/proc/stat``. ``changes`` lists
    ``(frame, threads, reason)`` of every switch.
    """

    def __init__(self, requested: Any = "auto", launcher: Mapping | None = None,
                 interval: float = 5.0) -> None:
        self.requested = requested
        self.cpus = available_cores()
        self.jobs, self.per_job = launcher_share(launcher, len(self.cpus))
        omp = os.environ.get("OMP_NUM_THREADS")
        self.active = parse_threads(requested) is None and not (omp and omp.strip())
        self.interval = float(interval)
        self.changes: list[tuple[int, int, str]] = []
        self._last = cpu_sample(self.cpus) if self.active else None
        self.initial: ThreadChoice | None = None

    @classmethod
    def start(cls, requested: Any = "auto", launcher: Mapping | None = None,
              interval: float = 5.0) -> ThreadGovernor:
        """:func:`apply_thread_policy` now, and a governor that keeps it up to date."""
        choice = apply_thread_policy(requested, launcher)
        gov = cls(requested, launcher, interval)
        gov.initial = choice
        return gov

    def summary(self) -> dict:
        """JSON-friendly record: the threads chosen at the start, why, and every switch."""
        first = self.initial
        return {"threads": None if first is None else first.threads,
                "reason": None if first is None else first.reason,
                "changes": [{"frame": f, "threads": n, "reason": r}
                            for f, n, r in self.changes]}

    def __call__(self, state=None, info=None) -> None:
        if self._last is None:
            return
        now = cpu_sample(self.cpus)
        if now is None or now.wall - self._last.wall < self.interval:
            return
        busy = busy_between(self._last, now, len(self.cpus))
        self._last = now
        choice = choose_threads(len(self.cpus), busy, self.jobs, self.per_job)
        import torch

        if choice.threads != torch.get_num_threads():
            torch.set_num_threads(choice.threads)
            if isinstance(state, list):  # batched tracking passes every group's state
                state = next((s for s in state if s is not None), None)
            frame = getattr(state, "frame", -1)
            self.changes.append((int(frame), choice.threads, choice.reason))
