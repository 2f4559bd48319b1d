"""Shared timing helper of the benchmark scripts (run as ``python experiments/benchmarks/X.py``,
which puts this folder on ``sys.path``)."""

from __future__ import annotations

import statistics
import time


def median_ms(fn, repeats: int, warmup: int = 2) -> float:
    """Median wall time of ``fn()`` in milliseconds over ``repeats`` calls, after ``warmup``
    untimed calls."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)
