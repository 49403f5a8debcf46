"""A worker process: hosts a chain of one or more nodes and measures them.

In the ``pipeline`` topology every worker hosts one stage's node (and light observer nodes such as
the recorder may join it); in the ``monolithic`` topology one worker hosts them all and routes the
chain's internal topics directly (no bus), which is the original NeoSLAM's blocking design. For
each hosted node the worker keeps counters (received, processed, published, errors with their
causes, strided, evicted from its input ring), the service time tau_i per frame, the queueing
time and the process's memory (RSS and PSS), and publishes them on ``stats/<stage>`` at
``stats_hz``.

A worker never dies from one message. Bad input (decoding faults: :class:`MessageError`; what a
node refuses: :class:`StageInputError` or an algorithm's ``InvalidInput``, see
:func:`~neoslam_stream.runtime.node.is_input_error`; a frame number far ahead of the stage's last
one: ``max_frame_jump``) is counted under ``errors`` / ``error_causes``, logged once per cause and
skipped. Any other exception raised by a node is a bug, not bad input: its traceback is logged (once
per cause), it is counted apart under ``internal_errors`` / ``internal_error_causes`` and the
message is skipped; the worker goes on with the node's state as it is (a restart would lose that
state without checkpoints, and the message that triggered the bug would not come again). A failed
checkpoint write (disk full) is logged once and counted under the node's ``write_errors`` counter;
the stage goes on. SIGINT/SIGTERM (also sent when the supervisor dies, see procs.follow_parent) or
a ``control`` message ``stop`` carrying the run's token (bus.ControlGate; others are counted under
``control_refused`` and ignored) end it cleanly: queued messages are processed, nodes flushed,
outputs and final stats published.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import time
import traceback
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bus import Bus, ControlGate, InputQueue, key_for, open_session, wait_for_peers
from .files import describe_write_error
from .messages import Message, MessageError, decode, encode
from .node import Node, NodeSpec, is_input_error

log = logging.getLogger("neoslam.worker")


@dataclass
class WorkerSpec:
    """Everything a worker process needs; plain data so it crosses a ``spawn``."""

    name: str
    stages: list[NodeSpec]
    run: str
    run_dir: str
    lossless: bool
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    shm: bool = False
    #: input ring/FIFO capacity per external topic; others get ``default_capacity``.
    capacities: dict[str, int] = field(default_factory=dict)
    default_capacity: int = 2
    threads: int = 1
    stats_hz: float = 2.0
    #: micro-batching: at most this many waiting frames of one topic are processed together.
    max_batch: int = 8
    #: topics that are published even when consumed inside the chain.
    publish_internal: list[str] = field(default_factory=list)
    log_level: str = "WARNING"
    #: adapter state to load before processing (stage name -> path of a state file), see checkpoint.py
    resume_states: dict[str, str] = field(default_factory=dict)
    #: an exported map (``neoslam map export``) to start from: each stage loads its part, then
    #: starts a new session (see Node.new_session)
    map_path: str = ""
    #: number of other processes this one should be linked to before it announces readiness
    expected_peers: int = 0
    #: save each stage's state at every multiple of this frame number (0 = never)
    checkpoint_every: int = 0
    checkpoint_dir: str = ""
    #: a message whose frame number is more than this ahead of the newest frame a stage has seen is
    #: refused as bad input (one message must not make a stage jump its frame counter, checkpoint
    #: cuts or buffers to the end of time); 0 = no limit
    max_frame_jump: int = 100_000
    #: the run's control secret (bus.ControlGate): control messages without it are refused
    control_token: str = ""


class ServiceStats:
    """Per-stage service and queueing times (seconds) with bounded memory."""

    MAX_SAMPLES = 200_000
    #: the recent percentiles cover the newest this many frames (the scaling curve's step)
    RECENT = 1000

    def __init__(self) -> None:
        self.tau: list[float] = []
        self.wait: list[float] = []
        self.tau_sum = 0.0
        self.n = 0
        self.tau_max = 0.0

    def add(self, tau: float, wait: float) -> None:
        self.n += 1
        self.tau_sum += tau
        self.tau_max = max(self.tau_max, tau)
        if len(self.tau) >= self.MAX_SAMPLES:  # keep the newest half: memory stays bounded
            del self.tau[: self.MAX_SAMPLES // 2]
            del self.wait[: self.MAX_SAMPLES // 2]
        self.tau.append(tau)
        self.wait.append(wait)

    def summary(self) -> dict[str, float]:
        if not self.tau:
            return {"tau_mean_ms": 0.0, "tau_p50_ms": 0.0, "tau_p95_ms": 0.0, "tau_max_ms": 0.0,
                    "tau_recent_p50_ms": 0.0, "tau_recent_p95_ms": 0.0,
                    "queue_p50_ms": 0.0, "queue_p95_ms": 0.0}
        t = np.asarray(self.tau) * 1e3
        w = np.asarray(self.wait) * 1e3
        recent = t[-self.RECENT:]
        return {"tau_mean_ms": self.tau_sum / self.n * 1e3,
                "tau_p50_ms": float(np.percentile(t, 50)), "tau_p95_ms": float(np.percentile(t, 95)),
                "tau_recent_p50_ms": float(np.percentile(recent, 50)),
                "tau_recent_p95_ms": float(np.percentile(recent, 95)),
                "tau_max_ms": self.tau_max * 1e3,
                "queue_p50_ms": float(np.percentile(w, 50)), "queue_p95_ms": float(np.percentile(w, 95))}


class StageRuntime:
    """One hosted node with its counters and its topic names on the bus."""

    def __init__(self, adapter: Node, remap: dict[str, str] | None = None) -> None:
        self.adapter = adapter
        self.name = adapter.name
        remap = remap or {}
        self.inputs = [remap.get(t, t) for t in adapter.inputs]
        #: the inputs that arrive once per frame (checkpoint cuts wait for them)
        self.ordered_inputs = [remap.get(t, t) for t in adapter.inputs if t not in adapter.unordered_inputs]
        self.outputs = [remap.get(t, t) for t in adapter.outputs]
        self.to_adapter = {remap.get(t, t): t for t in adapter.inputs}
        self.to_bus = {t: remap.get(t, t) for t in adapter.outputs}
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
        #: the newest frame number accepted on any input (the base of ``max_frame_jump``)
        self.frame_seen = -1
        self.checkpoint_index = 0
        #: multi-input stages with checkpoints: messages at or beyond the next cut, held until
        #: every input has reached the cut (see Worker._run_stage), and how far each input got
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


class Worker:
    """The body of a worker process (also usable in-process by tests)."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        self.stop_requested = False
        self.stages: list[StageRuntime] = []
        self.consumers: dict[str, list[int]] = defaultdict(list)  # topic -> stage indices
        #: topics a stage of this worker produces for a later stage of it: routed directly
        self.produced_here: set[str] = set()
        #: those of them that a non-observer consumes: not published on the bus (monolithic)
        self.produced_inside: set[str] = set()
        self.bus: Bus | None = None
        self.queue: InputQueue | None = None
        self._started = time.time()
        self._proc = None
        self.control = ControlGate(spec.control_token, f"worker {spec.name}")

    # ------------------------------------------------------------------ set-up
    def build(self) -> None:
        for s in self.spec.stages:
            adapter = s.build()
            out_dir = os.path.join(self.spec.run_dir, s.output_subdir) if s.output_subdir else self.spec.run_dir
            os.makedirs(out_dir, exist_ok=True)
            adapter.run_dir = out_dir
            adapter.run_id = self.spec.run
            self.stages.append(StageRuntime(adapter, s.remap))
        for i, st in enumerate(self.stages):
            for t in st.inputs:
                self.consumers[t].append(i)
        for i, st in enumerate(self.stages):
            for t in st.outputs:
                later = [j for j in self.consumers.get(t, []) if j > i]
                if later:
                    self.produced_here.add(t)
                if any(not self.stages[j].adapter.observer for j in later):
                    self.produced_inside.add(t)

    def setup(self) -> None:
        """Heavy initialisation of every adapter, then an imported map or a state to resume from."""
        from .checkpoint import load_map_file, load_state_file

        imported = load_map_file(self.spec.map_path)["stages"] if self.spec.map_path else {}
        for st in self.stages:
            st.adapter.setup()
            path = self.spec.resume_states.get(st.name)
            if path:
                st.adapter.load_state_dict(load_state_file(path))
                cut = Path(path).parent.name
                if cut.isdigit() and self.spec.checkpoint_every > 0:  # the next cut follows this one
                    st.checkpoint_index = int(cut) // self.spec.checkpoint_every
            elif st.name in imported:
                st.adapter.load_state_dict(imported[st.name])
                st.adapter.new_session()

    @property
    def external_inputs(self) -> list[str]:
        seen: list[str] = []
        for st in self.stages:
            for t in st.inputs:
                if t not in self.produced_here and t not in seen:
                    seen.append(t)
        return seen

    def connect(self) -> None:
        session = open_session(self.spec.listen, self.spec.connect, self.spec.shm)
        self.bus = Bus(session, self.spec.run, self.spec.lossless)
        caps = {t: self.spec.capacities.get(t, self.spec.default_capacity) for t in self.external_inputs}
        self.queue = InputQueue(caps, lossless=self.spec.lossless)
        for t in self.external_inputs:
            self.bus.subscribe(t, self.queue)
        self.bus.subscribe_callback(key_for(self.spec.run, "control"), self._on_control)
        for st in self.stages:
            for t in st.outputs:
                if t not in self.produced_inside or t in self.spec.publish_internal:
                    self.bus.publisher(t)
            # a node that publishes outside the run's topics (ROS 2 output) gets the session itself
            bind = getattr(st.adapter, "bind_session", None)
            if callable(bind):
                bind(self.bus.session)

    def announce(self) -> None:
        """Declare readiness once linked to every process of the run (or after a timeout)."""
        assert self.bus is not None
        wait_for_peers(self.bus.session, self.spec.expected_peers, timeout=10.0)
        self._token = self.bus.session.liveliness().declare_token(
            key_for(self.spec.run, f"alive/{self.spec.name}"))

    def _on_control(self, sample: Any) -> None:
        data = self.control.check(sample.payload.to_bytes())
        if data is None:  # not from this run's supervisor: counted, ignored
            return
        target = data.get("target")
        if data["command"] == "stop" and (target in (None, self.spec.name)):
            self.stop_requested = True
            if self.queue is not None and not self.spec.lossless:
                self.queue.close()

    # ------------------------------------------------------------------ processing
    def _maybe_checkpoint(self, st: StageRuntime, frame: int) -> None:
        """Save the stage's state as it is after every frame below the cut ``m * checkpoint_every``.

        Every stage cuts at the same frame numbers, so the files of one cut form a consistent
        snapshot of the whole pipeline (see checkpoint.py).
        """
        n = self.spec.checkpoint_every
        if n <= 0 or frame // n <= st.checkpoint_index:
            return
        # one cut per message at most: frames jumping over several cuts save the newest one only
        st.checkpoint_index = frame // n
        self._save_cut(st, st.checkpoint_index * n)

    def _save_cut(self, st: StageRuntime, cut: int) -> None:
        """Save the stage's state for ``cut``; a failed write (disk full) is logged once, counted
        under the node's ``write_errors`` counter, and the stage goes on without that cut."""
        from .checkpoint import cut_dir, save_stage_state

        try:
            save_stage_state(self.spec.checkpoint_dir, cut, st.name, st.adapter.state_dict())
        except OSError as exc:
            self._write_failed(st, cut_dir(self.spec.checkpoint_dir, cut) / f"{st.name}.state", exc)

    def _write_failed(self, st: StageRuntime, path: Any, exc: OSError) -> None:
        counters = st.adapter.counters
        if not counters.get("write_errors"):
            log.error("stage %s: %s (further write errors of this stage are counted, not logged)",
                      st.name, describe_write_error(path, exc))
        counters["write_errors"] = counters.get("write_errors", 0) + 1

    #: a multi-input stage holds at most this many messages for a cut; beyond, it cuts anyway
    #: (an input that never reaches the cut, e.g. no odometry at all, must not stall the stage)
    MAX_DEFERRED = 512

    def _hold_for_cut(self, idx: int, topic: str, msgs: list[Message],
                      received: list[float]) -> tuple[list[Message], list[float]]:
        """Multi-input stages: the state saved for cut C must hold every frame < C of *every*
        input and nothing beyond, but inputs run at different paces (odometry is ahead of the
        templates). Messages of frames >= C wait until each input has reached C; then the state
        is saved and they are processed. Returns the messages that may be processed now."""
        st = self.stages[idx]
        n = self.spec.checkpoint_every
        cut = (st.checkpoint_index + 1) * n
        ready_m, ready_r = [], []
        if topic not in st.ordered_inputs:  # a message at the end of the run, not a frame's
            return msgs, received
        for m, r in zip(msgs, received, strict=True):
            if m.frame >= cut:
                st.deferred.append((topic, m, r))
                st.reached[topic] = max(st.reached.get(topic, -1), m.frame)
            else:
                ready_m.append(m)
                ready_r.append(r)
        return ready_m, ready_r

    def _release_cut(self, idx: int, budget: int = 1) -> None:
        """Save the cut once every input has reached it (or too much is held), then process what
        was held. A loop, not a recursion: each round saves one cut and hands every held message
        below the next cut to the node; the cut saved is the newest one the held messages and the
        inputs' progress allow, so frames far ahead never make it save every multiple of N on the
        way (at most one cut per round, and a round ends with a held message processed or with
        the stage waiting for an input). At most ``budget`` rounds (the number of messages that
        came in): one message makes at most one cut folder, whatever its frame number; what is
        still held waits for the next message (each round processes at least the lowest held
        message, so the held list stays bounded)."""
        st = self.stages[idx]
        n = self.spec.checkpoint_every
        while st.deferred and budget > 0:
            cut = (st.checkpoint_index + 1) * n
            reached = all(st.reached.get(t, -1) >= cut for t in st.ordered_inputs)
            if not reached and len(st.deferred) < self.MAX_DEFERRED:
                return
            # nothing below the lowest held frame is still to come on an input that reached it:
            # the state now is that of every cut up to there (only empty cuts are skipped)
            bound = min(m.frame for _t, m, _r in st.deferred)
            if reached:
                bound = min(bound, *(st.reached.get(t, -1) for t in st.ordered_inputs))
            cut = max(cut, bound // n * n)
            st.checkpoint_index = cut // n
            self._save_cut(st, cut)
            budget -= 1
            held, st.deferred = st.deferred, []
            for t, m, r in held:  # in arrival order; the next cut may hold some of them again
                ready_m, ready_r = self._hold_for_cut(idx, t, [m], [r])
                if ready_m:
                    self._process(idx, t, ready_m, ready_r)

    def _refuse_jumps(self, st: StageRuntime, topic: str, msgs: list[Message],
                      received: list[float]) -> tuple[list[Message], list[float]]:
        """Messages whose frame number is more than ``max_frame_jump`` ahead of the newest frame
        the stage has seen are bad input: counted with their cause, not processed."""
        jump = self.spec.max_frame_jump
        ok_m, ok_r = [], []
        for m, r in zip(msgs, received, strict=True):
            if jump > 0 and st.frame_seen >= 0 and m.frame - st.frame_seen > jump:
                st.received += 1
                st.record_error(f"StageInputError: frame {m.frame} on {topic} is {m.frame - st.frame_seen} "
                                f"frames ahead of the newest frame seen ({st.frame_seen}), more than "
                                f"max_frame_jump={jump}")
                continue
            st.frame_seen = max(st.frame_seen, m.frame)
            ok_m.append(m)
            ok_r.append(r)
        return ok_m, ok_r

    def _run_stage(self, idx: int, topic: str, msgs: list[Message], received: list[float]) -> None:
        st = self.stages[idx]
        msgs, received = self._refuse_jumps(st, topic, msgs, received)
        if not msgs:
            return
        st.received += len(msgs)
        if self.spec.checkpoint_every > 0 and len(st.inputs) > 1:
            n_in = len(msgs)
            msgs, received = self._hold_for_cut(idx, topic, msgs, received)
            if msgs:
                self._process(idx, topic, msgs, received)
            self._release_cut(idx, budget=n_in)
            return
        self._maybe_checkpoint(st, min(m.frame for m in msgs))
        self._process(idx, topic, msgs, received)

    def _process(self, idx: int, topic: str, msgs: list[Message], received: list[float]) -> None:
        st = self.stages[idx]
        started = time.time()
        local = st.to_adapter.get(topic, topic)
        try:
            if len(msgs) == 1:
                outputs = st.adapter.process(local, msgs[0])
            else:
                outputs = st.adapter.process_batch(local, msgs)
        except Exception as exc:
            cause = f"{type(exc).__name__}: {exc}"
            if not is_input_error(exc):
                # a bug, not bad input: never hidden among the refused inputs. It must not kill the
                # worker either: log the traceback once per cause, count the messages it cost
                if st.record_bug(cause, len(msgs)):
                    log.error("stage %s: internal error (a bug, not bad input) on %s frame %s:\n%s",
                              st.name, topic, msgs[0].frame, traceback.format_exc())
                return
            if len(msgs) > 1:
                # retry one by one so one bad frame does not cost its batch-mates; each refused
                # frame is counted there, once
                for m, r in zip(msgs, received, strict=True):
                    self._process(idx, topic, [m], [r])
                return
            st.record_error(cause)
            return
        finished = time.time()
        per_frame = (finished - started) / max(1, len(msgs))
        for m, r in zip(msgs, received, strict=True):
            st.times.add(per_frame, max(0.0, started - r))
            st.last_frame = max(st.last_frame, m.frame)
        st.processed += len(msgs)
        self._emit(idx, outputs, st.name, dict(zip((m.frame for m in msgs), received, strict=False)),
                   started, finished)

    def _emit(self, idx: int, outputs: list[tuple[str, Message]], stage: str,
              received_by_frame: dict[int, float], started: float, finished: float) -> None:
        grouped: dict[str, list[Message]] = defaultdict(list)
        to_bus = self.stages[idx].to_bus
        for local, out in outputs:
            topic = to_bus.get(local, local)
            r = received_by_frame.get(out.frame, started)
            out.trace.append((stage, r, started, finished))
            if topic not in self.produced_inside or topic in self.spec.publish_internal:
                self._publish(idx, topic, out)
            if topic in self.produced_here:
                grouped[topic].append(out)
        for topic, msgs in grouped.items():
            for j in self.consumers[topic]:
                if j > idx:
                    now = time.time()
                    self._run_stage(j, topic, msgs, [now] * len(msgs))

    def _publish(self, idx: int, topic: str, msg: Message) -> None:
        st = self.stages[idx]
        try:
            payload = encode(msg)
        except MessageError as exc:
            st.record_error(f"output not encodable: {exc}")
            return
        assert self.bus is not None
        self.bus.put(topic, payload)
        st.published[topic] += 1

    def handle(self, topic: str, payload: bytes, received: float) -> None:
        """Decode one external message (plus any same-topic messages waiting, for batching)."""
        idxs = self.consumers.get(topic, [])
        if not idxs:
            return
        first = idxs[0]
        batch = [(payload, received)]
        adapter = self.stages[first].adapter
        if adapter.batchable and self.spec.max_batch > 1 and self.queue is not None:
            batch += self.queue.get_more(topic, self.spec.max_batch - 1)
        msgs: list[Message] = []
        recv: list[float] = []
        expected = self.stages[first].to_adapter.get(topic, topic)
        for p, r in batch:
            try:
                msg = decode(p)
                # a valid message on the wrong topic (types name their topic; emulated/1, emulated/2
                # ... carry the type "emulated")
                if msg.type.split("/")[0] != expected.split("/")[0]:
                    raise MessageError(f"message of type {msg.type!r} on topic {topic!r} "
                                       f"(expects {expected!r})")
                msgs.append(msg)
                recv.append(r)
            except MessageError as exc:
                self.stages[first].received += 1
                self.stages[first].record_error(f"MessageError on {topic}: {exc}")
        if not msgs:
            return
        for i in idxs:
            self._run_stage(i, topic, msgs, recv)

    # ------------------------------------------------------------------ stats
    def stats_messages(self, final: bool = False) -> list[Message]:
        import psutil

        if self._proc is None:
            self._proc = psutil.Process()
            self._proc.cpu_percent(None)
        cpu = self._proc.cpu_percent(None)
        rss = self._proc.memory_info().rss / 2**20
        pss = self._pss_mb()
        ct = self._proc.cpu_times()
        cpu_s = ct.user + ct.system
        depth = self.queue.depth() if self.queue else {}
        qstats = self.queue.stats if self.queue else {}
        out = []
        now = time.time()
        for i, st in enumerate(self.stages):
            inputs = {}
            for t in st.inputs:
                if t in qstats and self.consumers[t][0] == i:
                    inputs[t] = {"received": qstats[t].received, "evicted": qstats[t].evicted,
                                 "depth": depth.get(t, 0)}
            try:
                info = st.adapter.info()
            except Exception as exc:  # info is diagnostic: never let it break stats
                info = {"info_error": str(exc)}
            data = {"stage": st.name, "worker": self.spec.name, "pid": os.getpid(), "time": now,
                    "started": self._started, "received": st.received, "processed": st.processed,
                    "published": dict(st.published), "errors": st.errors,
                    "error_causes": dict(st.error_causes), "counters": dict(st.adapter.counters),
                    "internal_errors": st.internal_errors,
                    "internal_error_causes": dict(st.internal_error_causes),
                    "inputs": inputs, "outputs": list(st.outputs),
                    "consumes": list(st.inputs), "last_frame": st.last_frame,
                    "info": info, "cpu_percent": cpu, "cpu_s": cpu_s, "rss_mb": rss, "pss_mb": pss,
                    "final": final,
                    # per process: the worker's first stage carries it (the report sums processes)
                    "control_refused": self.control.refused if i == 0 else 0,
                    "control_refused_causes": dict(self.control.causes) if i == 0 else {},
                    "n_stages_in_worker": len(self.stages), **st.times.summary()}
            out.append(Message("stats", 0, now, data))
        return out

    #: seconds between two PSS readings (reading /proc/<pid>/smaps_rollup costs a few ms)
    PSS_PERIOD_S = 5.0

    def _pss_mb(self) -> float | None:
        """Proportional set size (MB): pages shared between processes (libraries, the parent's
        pages after a fork) count once in the sum over processes, unlike RSS. None where the
        platform does not report it."""
        now = time.monotonic()
        if now - getattr(self, "_pss_at", -1e9) >= self.PSS_PERIOD_S:
            self._pss_at = now
            try:
                self._pss_cache = self._proc.memory_full_info().pss / 2**20
            except Exception:  # psutil.AccessDenied, no smaps on this platform...
                self._pss_cache = None
        return getattr(self, "_pss_cache", None)

    def publish_stats(self, final: bool = False) -> None:
        assert self.bus is not None
        for m in self.stats_messages(final):
            try:
                self.bus.session.put(key_for(self.spec.run, f"stats/{m.data['stage']}"),
                                     encode(m, validate=False))
            except Exception as exc:  # stats must never stop the work
                log.warning("stats not published: %s", exc)

    # ------------------------------------------------------------------ main loop
    def loop(self) -> None:
        assert self.queue is not None
        period = 1.0 / self.spec.stats_hz
        next_stats = time.monotonic()
        while True:
            item = self.queue.get(timeout=0.1)
            if item is not None:
                self.handle(*item)
            elif self.stop_requested:
                break
            if time.monotonic() >= next_stats:
                self.publish_stats()
                next_stats = time.monotonic() + period
            if self.stop_requested and not self.spec.lossless:
                break

    def _save_final_states(self) -> None:
        """Every stateful stage's state at the end of the run, in RUN_DIR/state/ (the map that
        ``neoslam map export`` packs), written atomically."""
        from .checkpoint import save_state_file

        for st in self.stages:
            if st.adapter.observer:  # what a watcher holds (rows of output files) is no learned map
                continue
            path = Path(self.spec.run_dir) / "state" / f"{st.name}.state"
            try:
                state = st.adapter.state_dict()
                if state:
                    save_state_file(path, state)
            except OSError as exc:  # disk full: the previous file (if any) is intact; say so
                self._write_failed(st, path, exc)
            except Exception as exc:  # never lose the flush over it; say so
                log.error("stage %s: final state not saved: %s", st.name, exc)

    def shutdown(self) -> None:
        for i, st in enumerate(self.stages):
            held, st.deferred = st.deferred, []
            for t, m, r in held:  # the stream ended before every input reached the next cut
                self._process(i, t, [m], [r])
            try:
                outs = st.adapter.flush()
            except Exception as exc:
                log.error("stage %s flush failed: %s", st.name, exc)
                outs = []
            now = time.time()
            self._emit(i, outs, st.name, {}, now, now)
        self._save_final_states()
        self.publish_stats(final=True)
        # samples still in flight are lost if the session closes at once (research B.2)
        time.sleep(0.3)
        for st in self.stages:
            try:
                st.adapter.close()
            except Exception as exc:
                log.error("stage %s close failed: %s", st.name, exc)


def run_worker(spec: WorkerSpec) -> None:
    """Process entry: build, connect, announce readiness, loop until stopped, flush."""
    logging.basicConfig(level=getattr(logging, spec.log_level.upper(), logging.WARNING),
                        format=f"%(asctime)s {spec.name}[%(process)d] %(levelname)s %(message)s")
    worker = Worker(spec)

    def _stop(signum: int, _frame: Any) -> None:
        worker.stop_requested = True
        if worker.queue is not None and not spec.lossless:
            worker.queue.close()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    # no torch here: only the node that runs a network imports it (and sets its threads); the
    # environment's thread budget (procs.set_thread_budget) covers BLAS, OpenMP and numba
    worker.build()
    worker.connect()
    worker.setup()
    # first-call costs before the first frame: the stats path (psutil, percentiles), and a full
    # garbage collection whose survivors (models, matrices, compiled kernels) are then frozen out
    # of later collections, which would otherwise stall a frame now and then
    worker.stats_messages()
    gc.collect()
    gc.freeze()
    worker.announce()
    try:
        worker.loop()
    finally:
        worker.shutdown()
        if worker.queue is not None:
            worker.queue.close()
        assert worker.bus is not None
        worker.bus.close()
        worker.bus.session.close()
