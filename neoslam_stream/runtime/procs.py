"""Entry points of spawned processes.

This module imports nothing heavy at load time: a ``spawn`` child imports the module of its target
first, and thread-count environment variables (OpenBLAS, MKL, OpenMP, numba) only take effect if
they are set before numpy/torch/numba are loaded.
"""

from __future__ import annotations

import os
from typing import Any

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "NUMBA_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


def set_thread_budget(threads: int) -> None:
    """Limit every math library of this process to ``threads`` threads (call before importing them)."""
    n = str(max(1, int(threads)))
    for var in THREAD_VARS:
        os.environ[var] = n


def worker_entry(spec: Any) -> None:
    set_thread_budget(spec.threads)
    from .worker import run_worker

    run_worker(spec)


def source_entry(spec: Any) -> None:
    set_thread_budget(1)
    from .source_runner import run_source

    run_source(spec)


def monitor_entry(spec: Any) -> None:
    set_thread_budget(1)
    from .monitor import run_monitor

    run_monitor(spec)
