"""Timing helper shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np


def p50(fn: Callable[[], object], reps: int) -> float:
    """Median wall time of ``fn()`` over ``reps`` calls, in milliseconds."""
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3
