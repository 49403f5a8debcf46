"""A worker process: hosts a chain of one or more nodes and measures them.

In the ``pipeline`` topology every worker hosts one stage's node (light observer nodes such as the
recorder may join it); in the ``monolithic`` topology one worker hosts them all and routes the
chain's internal topics directly, as the original blocking NeoSLAM does. Per hosted node it counts
messages received, processed, published, refused (with their causes), strided and evicted, and
measures tau_i, the queueing time and the process's memory, published on ``stats/<stage>`` by the
:class:`~neoslam_stream.runtime.worker_stats.WorkerStats` it owns; its stages' checkpoint cuts are
saved by the :class:`~neoslam_stream.runtime.worker_cuts.CheckpointCuts` it owns.

A worker never dies from one message: bad input (:func:`~neoslam_stream.runtime.node.is_input_error`,
or a frame number far ahead of the stage's last one) is counted under ``errors``, logged once per
cause and skipped; any other exception is a bug, logged with its traceback and counted apart under
``internal_errors``, and the worker goes on. SIGINT/SIGTERM or the run's ``stop`` control message
end it cleanly: queued messages processed, nodes flushed, final stats published
(docs/reliability.md).
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import sys
import time
import traceback
from collections import defaultdict, deque
from dataclasses import dataclass, field
from typing import Any

from . import runlog
from .bus import Bus, ControlGate, InputQueue, key_for, open_session, wait_for_peers
from .checkpoint import StateFormatError, load_map_file, load_state_file
from .messages import Message, MessageError, Topic, decode, encode, register_topics
from .node import NodeSpec, is_input_error
from .worker_cuts import CheckpointCuts
from .worker_stats import StageRuntime, WorkerStats

log = logging.getLogger("neoslam.worker")

#: a worker's exit code when a stage refused the saved state it was given (a checkpoint or a map
#: made with other parameters): restarting cannot help, so the supervisor stops the run at once
EXIT_STATE_REFUSED = 3


class StateRefused(RuntimeError):
    """A stage refused the saved state it was given; the text says which stage, file and why."""


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
    #: stage name -> ms it may wait for a second frame of a batch (RunSection.batch_wait_ms)
    batch_wait_ms: dict[str, float] = field(default_factory=dict)
    #: topics that are published even when consumed inside the chain.
    publish_internal: list[str] = field(default_factory=list)
    log_level: str = "WARNING"
    #: node state to load before processing (stage name -> path of a state file), see checkpoint.py
    resume_states: dict[str, str] = field(default_factory=dict)
    #: an exported map (``neoslam map export``) to start from: each stage loads its own state from
    #: it, then starts a new session (see Node.new_session)
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
    #: the message types of the run with their schemas (the plan's), registered at the start
    topics: list[Topic] = field(default_factory=list)
    #: take each input only as its producer sent it, of this epoch (bus.InputQueue's ``strict``):
    #: a lossless run split over hosts, which rolls back rather than skip a frame a link lost
    strict_order: bool = False
    epoch: int = 0


class Worker:
    """The body of a worker process (also usable in-process by tests): builds its nodes, takes
    its inputs from the bus and routes each through its chain of stages. It owns its stats
    (:class:`WorkerStats`) and its checkpoint cuts (:class:`CheckpointCuts`)."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        register_topics(spec.topics)  # decoding validates them; a type nobody registered is refused
        self.stop_requested = False
        self.stages: list[StageRuntime] = []
        self.consumers: dict[str, list[int]] = defaultdict(list)  # topic -> stage indices
        #: per topic of a stage with a batch wait: arrival times of its latest frames (_batch_partners)
        self._arrivals: dict[str, deque[float]] = {}
        #: topics a stage of this worker produces for a later stage of it: routed directly
        self.produced_here: set[str] = set()
        #: those of them that a non-observer consumes: not published on the bus (monolithic)
        self.produced_inside: set[str] = set()
        self.bus: Bus | None = None
        self.queue: InputQueue | None = None
        self.stats = WorkerStats(spec.name, spec.run, spec.epoch)
        self.cuts = CheckpointCuts(spec.checkpoint_every, spec.checkpoint_dir, spec.run_dir)
        self.control = ControlGate(spec.control_token, f"worker {spec.name}")

    # ------------------------------------------------------------------ set-up
    def build(self) -> None:
        for s in self.spec.stages:
            node = s.build()
            out_dir = os.path.join(self.spec.run_dir, s.output_subdir) if s.output_subdir else self.spec.run_dir
            os.makedirs(out_dir, exist_ok=True)
            node.run_dir = out_dir
            node.run_id = self.spec.run
            self.stages.append(StageRuntime(node, s.remap))
        for i, st in enumerate(self.stages):
            for t in st.inputs:
                self.consumers[t].append(i)
        for i, st in enumerate(self.stages):
            for t in st.outputs:
                later = [j for j in self.consumers.get(t, []) if j > i]
                if later:
                    self.produced_here.add(t)
                if any(not self.stages[j].node.observer for j in later):
                    self.produced_inside.add(t)

    def setup(self) -> None:
        """Heavy initialisation of every node, then an imported map or a state to resume from."""
        imported = load_map_file(self.spec.map_path)["stages"] if self.spec.map_path else {}
        for st in self.stages:
            st.node.setup()
            if not self.spec.lossless and st.node.batchable:
                st.node.warm_up(self.spec.max_batch)
            path = self.spec.resume_states.get(st.name)
            if path:
                try:
                    state = load_state_file(path)
                except StateFormatError as exc:  # written by another version: one line, no restart
                    raise StateRefused(f"stage {st.name}: {exc}") from None
                self._load_state(st, state, path)
                self.cuts.resumed(st, path)
            elif st.name in imported:
                self._load_state(st, imported[st.name], str(self.spec.map_path))
                st.node.new_session()

    @staticmethod
    def _load_state(st: StageRuntime, state: Any, origin: str) -> None:
        """A saved state into a stage; a stage that refuses it (made with other parameters: a
        ``ValueError`` naming them) ends the worker with :data:`EXIT_STATE_REFUSED` and one line."""
        try:
            st.node.load_state_dict(state)
        except ValueError as exc:
            raise StateRefused(f"stage {st.name} refuses the state in {origin}: {exc}") from None

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
        self.bus = Bus(session, self.spec.run, self.spec.lossless, epoch=self.spec.epoch)
        caps = {t: self.spec.capacities.get(t, self.spec.default_capacity) for t in self.external_inputs}
        self.queue = InputQueue(caps, lossless=self.spec.lossless, strict=self.spec.strict_order,
                                epoch=self.spec.epoch)
        for t in self.external_inputs:
            self.bus.subscribe(t, self.queue)
        self.bus.subscribe_callback(key_for(self.spec.run, "control"), self._on_control)
        for st in self.stages:
            for t in st.outputs:
                if t not in self.produced_inside or t in self.spec.publish_internal:
                    self.bus.publisher(t)
            # a node that publishes outside the run's topics (ROS 2 output) gets the session itself
            bind = getattr(st.node, "bind_session", None)
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
        if self.cuts.enabled and len(st.inputs) > 1:
            n_in = len(msgs)
            msgs, received = self.cuts.hold(st, topic, msgs, received)
            if msgs:
                self._process(idx, topic, msgs, received)
            self.cuts.release(st, lambda t, m, r: self._process(idx, t, m, r), budget=n_in)
            return
        self.cuts.maybe_save(st, min(m.frame for m in msgs))
        self._process(idx, topic, msgs, received)

    def _process(self, idx: int, topic: str, msgs: list[Message], received: list[float]) -> None:
        st = self.stages[idx]
        started = time.time()
        local = st.to_node.get(topic, topic)
        try:
            if len(msgs) == 1:
                outputs = st.node.process(local, msgs[0])
            else:
                outputs = st.node.process_batch(local, msgs)
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
            st.first_frame = m.frame if st.first_frame < 0 else min(st.first_frame, m.frame)
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
        self.bus.put(topic, payload, msg.frame)
        st.published[topic] += 1

    def handle(self, topic: str, payload: bytes, received: float) -> None:
        """Decode one external message (plus any same-topic messages waiting, for batching)."""
        idxs = self.consumers.get(topic, [])
        if not idxs:
            return
        first = idxs[0]
        batch = [(payload, received)]
        node = self.stages[first].node
        if node.batchable and self.spec.max_batch > 1 and self.queue is not None:
            batch += self.queue.get_more(topic, self.spec.max_batch - 1)
            wait_s = self.spec.batch_wait_ms.get(self.stages[first].name, 0.0) / 1000.0
            if wait_s > 0:
                if len(batch) == 1:
                    batch += self._batch_partners(topic, received, wait_s)
                self._note_arrivals(topic, [r for _p, r in batch])
        msgs: list[Message] = []
        recv: list[float] = []
        expected = self.stages[first].to_node.get(topic, topic)
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

    def _note_arrivals(self, topic: str, received: list[float]) -> None:
        """Keep the arrival times of a batchable topic's last ``max_batch`` + 1 frames."""
        times = self._arrivals.setdefault(topic, deque(maxlen=self.spec.max_batch + 1))
        times.extend(sorted(received))

    def _batch_partners(self, topic: str, received: float, wait_s: float) -> list[tuple[bytes, float]]:
        """A frame found alone waits for a second one (up to ``wait_s``, its stage's
        ``batch_wait_ms``, counted from its arrival) while frames have been arriving at least that
        often; then every frame waiting joins its batch. Nothing when they come too rarely: the
        wait would only add latency."""
        assert self.queue is not None
        times = self._arrivals.get(topic)
        if not times or len(times) < 2:
            return []
        gap = (times[-1] - times[0]) / (len(times) - 1)  # the mean interval between recent arrivals
        if gap > wait_s or not self.queue.wait_for(topic, received + wait_s - time.time()):
            return []
        return self.queue.get_more(topic, self.spec.max_batch - 1)

    # ------------------------------------------------------------------ stats
    def stats_messages(self, final: bool = False) -> list[Message]:
        """This worker's ``stats/<stage>`` messages now (``final``: at shutdown, exact percentiles)."""
        return self.stats.messages(self.stages, self.consumers, self.queue, self.control, final)

    def publish_stats(self, final: bool = False) -> None:
        assert self.bus is not None
        self.stats.publish(self.bus.session, self.stats_messages(final))

    # ------------------------------------------------------------------ main loop
    def loop(self) -> None:
        assert self.queue is not None
        period = 1.0 / self.spec.stats_hz
        next_stats = time.monotonic()
        worked = False  # handled a message since the last stats
        while True:
            item = self.queue.get(timeout=0.1)
            if item is not None:
                self.handle(*item)
                worked = True
            elif self.stop_requested:
                break
            # on the period; and in a lossless run also as soon as the worker falls idle after work,
            # so that the supervisor sees the pipeline drained without waiting for the next period
            if time.monotonic() >= next_stats or (worked and item is None and self.spec.lossless):
                self.publish_stats()
                worked = False
                next_stats = time.monotonic() + period
            if self.stop_requested and not self.spec.lossless:
                break

    def shutdown(self) -> None:
        """Flush every stage, the stages that learn first: their final states are saved before a
        watcher (the recorder) writes its files, which on a long run may take longer than the
        supervisor waits; a worker stopped then has its learned state saved all the same."""
        learners = [i for i, st in enumerate(self.stages) if not st.node.observer]
        for i in learners:
            self._flush(i)
        self.cuts.save_final_states(self.stages, self.spec.name)
        for i in range(len(self.stages)):
            if i not in learners:
                self._flush(i)
        self.publish_stats(final=True)
        # samples still in flight are lost if the session closes at once
        time.sleep(0.3)
        for st in self.stages:
            try:
                st.node.close()
            except Exception as exc:
                log.error("stage %s close failed: %s", st.name, exc)

    def _flush(self, i: int) -> None:
        """Stage i at the stream's end: what it deferred, then its flush, published."""
        st = self.stages[i]
        held, st.deferred = st.deferred, []
        for t, m, r in held:  # the stream ended before every input reached the next cut
            self._process(i, t, [m], [r])
        try:
            outs = st.node.flush()
        except Exception as exc:
            log.error("stage %s flush failed: %s", st.name, exc)
            outs = []
        now = time.time()
        self._emit(i, outs, st.name, {}, now, now)


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
    assert worker.bus is not None
    logs = runlog.attach(worker.bus.session, spec.run, spec.name)  # the run's log lines, on the bus
    try:
        worker.setup()
    except StateRefused as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        runlog.detach(logs)
        worker.bus.close()
        worker.bus.session.close()
        sys.exit(EXIT_STATE_REFUSED)
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
        runlog.detach(logs)
        worker.bus.close()
        worker.bus.session.close()
