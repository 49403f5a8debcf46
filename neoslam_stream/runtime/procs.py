"""Entry points of spawned processes.

This module imports nothing heavy at load time: a ``spawn`` child imports the module of its target
first, and thread-count environment variables (OpenBLAS, MKL, OpenMP, numba) only take effect if
they are set before numpy/torch/numba are loaded.

Every child of a run dies with its supervisor (a ``kill -9`` of ``neoslam run`` must not leave six
workers, a source and a monitor running for ever): :func:`follow_parent` asks Linux for a signal
when the parent dies (``prctl(PR_SET_PDEATHSIG)``) and, on every platform, starts a watchdog thread
that notices the parent is gone by polling ``os.getppid()``. Either way the child gets SIGTERM,
which every entry point handles as a clean stop (queued frames processed, outputs flushed, the
monitor's report written), and it exits by force if that stop does not end it in time.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Any

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "NUMBA_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


def set_thread_budget(threads: int) -> None:
    """Limit every math library of this process to ``threads`` threads (call before importing them).

    A ``spawn`` child imports its parent's main script before it reaches the entry point, so a
    script that imports the package at its top (a bench, a user's own) has loaded numba here
    already, with the parent's thread count. numba reads its environment again before every
    compilation and refuses a changed count once its pool runs; so it re-reads it now, while no
    pool runs yet, or the first uncached compilation in this process would fail.
    """
    n = str(max(1, int(threads)))
    for var in THREAD_VARS:
        os.environ[var] = n
    if "numba" in sys.modules:
        from numba.core import config as numba_config

        numba_config.reload_config()


#: prctl option: the signal this process gets when its parent dies (linux/prctl.h)
PR_SET_PDEATHSIG = 1
#: seconds between two looks of the watchdog at the parent's pid
WATCH_PERIOD_S = 0.5
#: after the parent's death, a clean stop gets this long before the process exits by force
STOP_GRACE_S = 60.0


def _set_pdeathsig(sig: int) -> bool:
    """Linux only: ``sig`` to this process when the thread that forked it ends. True if set."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def follow_parent(parent_pid: int | None, grace_s: float = STOP_GRACE_S) -> None:
    """Make this process stop when ``parent_pid`` (the supervisor) dies.

    PR_SET_PDEATHSIG fires when the *thread* that forked this process ends, not the process: the
    supervisor starts (and restarts) its children from its main thread, whose end is the process's
    end, so the signal means the supervisor is gone. It is set here, in the child, after the
    fork; the parent may have died before, which the check of ``os.getppid()`` right after
    catches. The watchdog thread covers platforms without prctl and any case the signal misses (a
    child started from another thread).
    """
    if parent_pid is None:
        return
    _set_pdeathsig(signal.SIGTERM)

    def _parent_gone() -> None:
        os.kill(os.getpid(), signal.SIGTERM)  # the entry point's handler: a clean stop
        time.sleep(grace_s)
        os._exit(1)  # the clean stop hung: nothing may outlive the run for ever

    if os.getppid() != parent_pid:
        threading.Thread(target=_parent_gone, name="parent-gone", daemon=True).start()
        return

    def _watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(WATCH_PERIOD_S)
        _parent_gone()

    threading.Thread(target=_watch, name="parent-watchdog", daemon=True).start()


def apply_scheduling(name: str, nice: int = 0, cpus: list[int] | None = None) -> list[str]:
    """Name this process ``neoslam-<name>`` (top, ps -o comm), raise its niceness by ``nice`` and
    restrict it to ``cpus`` (run.nice, run.cpus). A setting the system refuses (a CPU this machine
    lacks) is skipped; returns one line per refusal, which the caller logs."""
    problems: list[str] = []
    try:
        with open("/proc/self/comm", "w") as fh:  # linux; 15 characters are kept
            fh.write(f"neoslam-{name}"[:15])
    except OSError:
        pass
    if nice:
        try:
            os.nice(int(nice))
        except OSError as exc:
            problems.append(f"{name}: niceness +{nice} refused: {exc}")
    if cpus:
        try:
            os.sched_setaffinity(0, set(cpus))
        except (OSError, ValueError, AttributeError) as exc:
            problems.append(f"{name}: CPUs {sorted(cpus)} refused (this machine has "
                            f"{os.cpu_count()}): {exc}; running on any CPU")
    return problems


def _scheduled(name: str, sched: dict[str, Any] | None) -> None:
    for line in apply_scheduling(name, **(sched or {})):
        print(f"warning: {line}", file=sys.stderr, flush=True)


def worker_entry(spec: Any, parent_pid: int | None = None, sched: dict[str, Any] | None = None) -> None:
    set_thread_budget(spec.threads)
    _scheduled(spec.name, sched)
    follow_parent(parent_pid)
    from .worker import run_worker

    run_worker(spec)


def source_entry(spec: Any, parent_pid: int | None = None, sched: dict[str, Any] | None = None) -> None:
    set_thread_budget(1)
    _scheduled("source", sched)
    follow_parent(parent_pid)
    from .source_runner import run_source

    run_source(spec)


def monitor_entry(spec: Any, parent_pid: int | None = None, sched: dict[str, Any] | None = None) -> None:
    set_thread_budget(1)
    _scheduled("monitor", sched)
    follow_parent(parent_pid)
    from .monitor import run_monitor

    run_monitor(spec)
