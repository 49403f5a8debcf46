"""The rate a topology sustains on a given number of cores, from measured per-worker service times.

The paper's eq. 2 (f_pipeline = min_i 1/tau_i) assumes every worker has a core of its own. With
fewer cores than busy processes the cores themselves bound the rate: each frame costs the CPU time
of every worker plus what moves and watches it (source, transport, monitor), and c cores supply c
CPU-seconds a second. So

    f(c) = min( 1 / max_w tau_w ,  c / C )

with tau_w a worker's service time per camera frame (the sum of the tau_i of the stages it hosts,
each times its messages per frame: the least of its measurements, :func:`least_service_ms`) and C
the CPU time per frame of the whole run under load. The monolithic topology is the same formula
with one worker hosting every stage. How well it holds at 1 and 2 cores: docs/performance.md,
"Beyond two cores".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def sustainable_rate(worker_ms: Mapping[str, float], cpu_ms_per_frame: float, cores: float) -> dict[str, Any]:
    """The predicted sustainable frame rate (Hz) and what bounds it: ``worker`` (the slowest
    worker's service time; its name in ``bottleneck``) or ``cores`` (the CPU time per frame)."""
    if not worker_ms:
        raise ValueError("no worker service times")
    values = [*worker_ms.values(), cpu_ms_per_frame]
    if cores <= 0 or any(not math.isfinite(v) or v < 0 for v in values):
        raise ValueError(f"cores must be > 0 and times finite and >= 0 (cores {cores}, "
                         f"CPU {cpu_ms_per_frame} ms, {dict(worker_ms)})")
    slowest = max(worker_ms, key=lambda w: worker_ms[w])
    f_worker = 1e3 / worker_ms[slowest] if worker_ms[slowest] > 0 else math.inf
    f_cores = 1e3 * cores / cpu_ms_per_frame if cpu_ms_per_frame > 0 else math.inf
    bound = "worker" if f_worker <= f_cores else "cores"
    return {"rate_hz": min(f_worker, f_cores), "bound": bound, "bottleneck": slowest,
            "worker_bound_hz": f_worker, "cores_bound_hz": f_cores}


def worker_service_ms(report: Mapping[str, Any]) -> dict[str, float]:
    """Each worker's busy time per camera frame (ms) from a run's report.json: tau_mean of each
    stage it hosts times that stage's messages per frame (a stage fed by two topics serves two)."""
    frames = report.get("frames_out") or 0
    if frames <= 0:
        raise ValueError("the run processed no frame: no service time to read")
    out: dict[str, float] = {}
    for name, st in report.get("stages", {}).items():
        if st.get("missing") or not st.get("processed"):
            continue
        worker = st.get("worker", name)
        out[worker] = out.get(worker, 0.0) + st["tau_mean_ms"] * st["processed"] / frames
    return out


def least_service_ms(*runs: Mapping[str, float]) -> dict[str, float]:
    """Each worker's least service time over several runs' :func:`worker_service_ms`: a saturated
    worker takes micro-batches, which cost less per frame than one frame at a time, and a worker
    sharing a core waits for it, which costs more; the least measured is the closest to what the
    worker needs on a core of its own."""
    out: dict[str, float] = {}
    for run in runs:
        for worker, ms in run.items():
            out[worker] = min(ms, out.get(worker, math.inf))
    return out
