"""What a worker measures of the nodes it hosts, and the ``stats/<stage>`` messages it publishes.

Per hosted node: messages received, processed, published, refused as bad input and lost to
internal errors (with their causes, bounded), tau_i and the queueing time (bounded memory), and
the process's CPU, RSS and PSS. The monitor and the supervisor read these messages.
"""

from __future__ import annotations

import logging
import os
import time
from collections import defaultdict
from typing import Any

import numpy as np

from .bus import ControlGate, InputQueue, key_for
from .messages import Message, encode
from .node import Node

log = logging.getLogger("neoslam.worker")


class ServiceStats:
    """Per-stage service and queueing times (seconds) with bounded memory and bounded cost.

    Samples live in two preallocated arrays; when they are full the older half is dropped, so
    the percentiles cover the newest ``MAX_SAMPLES // 2`` to ``MAX_SAMPLES`` frames. Stats go out
    twice a second from the worker's own thread, between two frames, and percentiles over that
    many samples would delay a frame each time, so the whole-run ones are recomputed only when the
    samples have grown by ``REFRESH_GROWTH`` since the last time (their cost, amortised, stays a
    few operations per frame), the recent ones every time, and all of them exactly in the final
    stats (``summary(exact=True)``)."""

    MAX_SAMPLES = 200_000
    #: the recent percentiles cover the newest this many frames (the scaling curve's step)
    RECENT = 1000
    #: between two recomputations the live whole-run percentiles leave out at most this fraction
    #: of the samples (the newest)
    REFRESH_GROWTH = 0.125

    def __init__(self) -> None:
        self._tau = np.empty(self.MAX_SAMPLES)
        self._wait = np.empty(self.MAX_SAMPLES)
        self._k = 0  # samples held
        self.tau_sum = 0.0
        self.n = 0
        self.tau_max = 0.0
        #: the whole-run percentiles (tau p50, p95, queue p50, p95, in s) and the count they were taken at
        self._whole: tuple[float, ...] = ()
        self._whole_n = 0

    @property
    def tau(self) -> np.ndarray:
        """The service times held (s), oldest first."""
        return self._tau[: self._k]

    @property
    def wait(self) -> np.ndarray:
        """The queueing times held (s), oldest first."""
        return self._wait[: self._k]

    def add(self, tau: float, wait: float) -> None:
        self.n += 1
        self.tau_sum += tau
        self.tau_max = max(self.tau_max, tau)
        if self._k >= self.MAX_SAMPLES:  # keep the newest half: memory stays bounded
            drop = self.MAX_SAMPLES // 2
            keep = self._k - drop
            self._tau[:keep] = self._tau[drop: self._k]
            self._wait[:keep] = self._wait[drop: self._k]
            self._k = keep
        self._tau[self._k] = tau
        self._wait[self._k] = wait
        self._k += 1

    def summary(self, exact: bool = False) -> dict[str, float]:
        if self._k == 0:
            return {"tau_mean_ms": 0.0, "tau_p50_ms": 0.0, "tau_p95_ms": 0.0, "tau_max_ms": 0.0,
                    "tau_recent_p50_ms": 0.0, "tau_recent_p95_ms": 0.0,
                    "queue_p50_ms": 0.0, "queue_p95_ms": 0.0}
        if exact or not self._whole or self.n > self._whole_n * (1 + self.REFRESH_GROWTH):
            self._whole = (*np.percentile(self.tau, [50, 95]), *np.percentile(self.wait, [50, 95]))
            self._whole_n = self.n
        t50, t95, w50, w95 = self._whole
        r50, r95 = np.percentile(self._tau[max(0, self._k - self.RECENT): self._k], [50, 95])
        return {"tau_mean_ms": self.tau_sum / self.n * 1e3,
                "tau_p50_ms": float(t50) * 1e3, "tau_p95_ms": float(t95) * 1e3,
                "tau_recent_p50_ms": float(r50) * 1e3, "tau_recent_p95_ms": float(r95) * 1e3,
                "tau_max_ms": self.tau_max * 1e3,
                "queue_p50_ms": float(w50) * 1e3, "queue_p95_ms": float(w95) * 1e3}


class StageRuntime:
    """One hosted node with its counters and its topic names on the bus."""

    def __init__(self, node: Node, remap: dict[str, str] | None = None) -> None:
        self.node = node
        self.name = node.name
        remap = remap or {}
        self.inputs = [remap.get(t, t) for t in node.inputs]
        #: the inputs that arrive once per frame (checkpoint cuts wait for them)
        self.ordered_inputs = [remap.get(t, t) for t in node.inputs if t not in node.unordered_inputs]
        self.outputs = [remap.get(t, t) for t in node.outputs]
        #: bus topic -> the node's own name for it, and back (NodeSpec.remap)
        self.to_node = {remap.get(t, t): t for t in node.inputs}
        self.to_bus = {t: remap.get(t, t) for t in node.outputs}
        self.received = 0
        self.processed = 0
        self.published: dict[str, int] = defaultdict(int)
        self.errors = 0
        self.error_causes: dict[str, int] = {}
        #: exceptions that are no input error: bugs (see Worker._process)
        self.internal_errors = 0
        self.internal_error_causes: dict[str, int] = {}
        self.times = ServiceStats()
        self.last_frame = -1
        #: the oldest frame this life processed (a restarted stage's lives leave a gap between them)
        self.first_frame = -1
        #: the newest frame number accepted on any input (the base of ``max_frame_jump``)
        self.frame_seen = -1
        self.checkpoint_index = 0
        #: multi-input stages with checkpoints: messages at or beyond the next cut, held until
        #: every input has reached the cut (worker_cuts.CheckpointCuts), and how far each input got
        self.deferred: list[tuple[str, Message, float]] = []
        self.reached: dict[str, int] = {}

    #: distinct causes kept per stage; the others are counted under OTHER_CAUSES
    MAX_CAUSES = 50
    OTHER_CAUSES = "(other causes)"

    def record_error(self, cause: str, n: int = 1) -> None:
        """``n`` messages refused as bad input for ``cause`` (each counted once)."""
        self.errors += n
        if _count_cause(self.error_causes, cause, n, self.MAX_CAUSES, self.OTHER_CAUSES):
            log.warning("stage %s: skipped a message: %s", self.name, cause)

    def record_bug(self, cause: str, n: int = 1) -> bool:
        """``n`` messages lost to an exception that is no input error; True for a new cause (the
        caller logs its traceback)."""
        self.internal_errors += n
        return _count_cause(self.internal_error_causes, cause, n, self.MAX_CAUSES, self.OTHER_CAUSES)


def _count_cause(causes: dict[str, int], cause: str, n: int, limit: int, other: str) -> bool:
    """Add ``n`` to ``cause`` (its first 200 characters) in ``causes``, or to ``other`` once
    ``limit`` causes are known, so that the counts always add up to the total. True when a key is
    new (a new cause, or the first one counted under ``other``): the caller logs it."""
    key = cause[:200]
    if key not in causes and len(causes) >= limit:
        key = other
    new = key not in causes
    causes[key] = causes.get(key, 0) + n
    return new


class WorkerStats:
    """The ``stats/<stage>`` messages of one worker process: per hosted stage its counters and
    times (:class:`StageRuntime`), with the process's CPU and memory, which it reads itself (PSS
    at most every ``PSS_PERIOD_S``: reading it costs a few ms). The worker owns one and hands it
    its stages, input queue and control gate when it takes stats."""

    #: seconds between two PSS readings (reading /proc/<pid>/smaps_rollup costs a few ms)
    PSS_PERIOD_S = 5.0

    def __init__(self, worker: str, run: str, epoch: int = 0) -> None:
        self.worker = worker
        self.run = run
        self.epoch = epoch
        self.started = time.time()
        self._proc: Any = None
        self._pss_at = -1e9
        self._pss: float | None = None

    def messages(self, stages: list[StageRuntime], consumers: dict[str, list[int]], queue: InputQueue | None,
                 control: ControlGate, final: bool = False) -> list[Message]:
        """One stats message per stage; ``consumers``: topic -> the stages that take it (the
        first of them reports the input's queue), ``queue``: the worker's inputs (None before it
        is connected), ``control``: its gate (refused control messages, counted per process)."""
        import psutil

        if self._proc is None:
            self._proc = psutil.Process()
            self._proc.cpu_percent(None)
        cpu = self._proc.cpu_percent(None)
        rss = self._proc.memory_info().rss / 2**20
        pss = self._pss_mb()
        ct = self._proc.cpu_times()
        cpu_s = ct.user + ct.system
        counts = queue.counts() if queue else {}
        out = []
        now = time.time()
        for i, st in enumerate(stages):
            inputs = {}
            for t in st.inputs:
                if t in counts and consumers[t][0] == i:
                    received, evicted, depth = counts[t]
                    inputs[t] = {"received": received, "evicted": evicted, "depth": depth}
            try:
                info = st.node.info()
            except Exception as exc:  # info is diagnostic: never let it break stats
                info = {"info_error": str(exc)}
            data = {"stage": st.name, "worker": self.worker, "pid": os.getpid(), "time": now,
                    "started": self.started, "received": st.received, "processed": st.processed,
                    "published": dict(st.published), "errors": st.errors,
                    "error_causes": dict(st.error_causes), "counters": dict(st.node.counters),
                    "internal_errors": st.internal_errors,
                    "internal_error_causes": dict(st.internal_error_causes),
                    "inputs": inputs, "outputs": list(st.outputs),
                    "consumes": list(st.inputs), "last_frame": st.last_frame, "first_frame": st.first_frame,
                    "info": info, "cpu_percent": cpu, "cpu_s": cpu_s, "rss_mb": rss, "pss_mb": pss,
                    "final": final,
                    # per process: the worker's first stage carries it (the report sums processes)
                    "control_refused": control.refused if i == 0 else 0,
                    "control_refused_causes": dict(control.causes) if i == 0 else {},
                    # strict inputs (a lossless run over hosts): holes a link made, older epochs
                    "holes": dict(queue.holes) if queue and i == 0 else {},
                    "stale_refused": queue.refused_stale if queue and i == 0 else 0,
                    "epoch": self.epoch,
                    "n_stages_in_worker": len(stages), **st.times.summary(exact=final)}
            out.append(Message("stats", 0, now, data))
        return out

    def _pss_mb(self) -> float | None:
        """Proportional set size (MB): pages shared between processes (libraries, the parent's
        pages after a fork) count once in the sum over processes, unlike RSS. None where the
        platform does not report it."""
        now = time.monotonic()
        if now - self._pss_at >= self.PSS_PERIOD_S:
            self._pss_at = now
            try:
                self._pss = self._proc.memory_full_info().pss / 2**20
            except Exception:  # psutil.AccessDenied, no smaps on this platform...
                self._pss = None
        return self._pss

    def publish(self, session: Any, messages: list[Message]) -> None:
        """Put each message on its stage's ``stats/<stage>``; a failure is logged, never raised."""
        for m in messages:
            try:
                session.put(key_for(self.run, f"stats/{m.data['stage']}"), encode(m, validate=False))
            except Exception as exc:  # stats must never stop the work
                log.warning("stats not published: %s", exc)
