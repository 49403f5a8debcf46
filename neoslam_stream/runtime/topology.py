"""Builds and supervises a run: the source, the stage workers and the monitor, each a process.

Topologies (DESIGN.md): ``pipeline`` runs one process per stage connected by zenoh pub/sub;
``monolithic`` runs every stage in one process, in sequence, and like the original blocking NeoSLAM
keeps only the newest frame that arrived while it was busy. Both host the very same nodes. The
runtime knows no algorithm and no source: the caller gives the :class:`PipelinePlan` (plan.py: its
nodes, final topic, message types and capacities) and the factory of the run's source.

Every child is a zenoh peer linked to all processes started before it (a full mesh); the supervisor
is a zenoh router, so a tool attaching in client mode to its one endpoint reaches every process. It
waits until every worker announced readiness, starts the source, restarts a crashed worker or
monitor (bounded, reported), ends the run once the source is done and the pipeline drained, stops
everything in order and completes ``report.json`` with the figures it measured itself (they survive
a killed monitor). Children die with it; control messages carry a per-run secret (docs/reliability.md).
Starting, restarting and stopping the processes: children.py.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import secrets
import signal
import time
from pathlib import Path
from typing import Any

import yaml

from .bus import ZENOH_CONFIG_ENV, ZENOH_TX_QUEUE_ENV, key_for, open_session
from .checkpoint import cut_dir, latest_complete_cut
from .children import ChildProcesses
from .collector import FinalTracker, StatsCollector
from .host import host_usage, sample_host
from .messages import register_topics
from .monitor import MonitorSpec
from .plan import PipelinePlan, RunError, RunResult, group_workers, make_run_dir
from .ports import free_port
from .procs import monitor_entry, source_entry, worker_entry
from .report import build_report, mark_status, write_report
from .source_runner import SourceRunSpec, SourceSpec
from .worker import WorkerSpec

#: environment variable holding the control secret shared by every host of a split run: an
#: environment variable, not a flag, so that other local users do not read it in the process table
CONTROL_TOKEN_ENV = "NEOSLAM_CONTROL_TOKEN"

log = logging.getLogger("neoslam.topology")


def queue_capacities(plan: PipelinePlan, configured: dict[str, int], monolithic: bool) -> dict[str, int]:
    """Input queue capacity per topic before a worker's own nodes raise it: the plan's, overridden
    by ``bus.capacity`` (``configured``). The monolithic process takes the source's topics at
    ``bus.default_capacity`` unless configured: the original design keeps the newest frames, not a
    batch."""
    caps = plan.capacity
    if monolithic:
        caps = {t: c for t, c in caps.items() if t not in plan.consumed_source_topics}
    return {**caps, **configured}


class Supervisor(ChildProcesses):
    """Runs ``plan`` with the runtime sections of ``cfg`` (``run``, ``bus``, ``source``);
    ``source_factory``: the ``"module:callable"`` that builds ``cfg.source``'s source (``launch``
    resolves the source kind)."""

    def __init__(self, cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
                 resume: str | Path | None = None, map_path: str | Path | None = None,
                 source_factory: str | None = None) -> None:
        self.cfg = cfg
        self.plan = plan
        self.source_factory = source_factory
        register_topics(plan.topics)  # this process decodes the final topic too (FinalTracker)
        self.name, self.run_dir = make_run_dir(cfg, run_dir)
        # a run split over several hosts (runtime/parts.py) shares one id, given to every part
        self.run_id = getattr(cfg.run, "run_id", None) or f"r{secrets.token_hex(4)}"
        #: the control topic's secret: only this supervisor's commands are obeyed (bus.ControlGate);
        #: the hosts of a split run share one through CONTROL_TOKEN_ENV (runtime/parts.py)
        self.control_token = os.environ.get(CONTROL_TOKEN_ENV) or secrets.token_hex(16)
        self.final = FinalTracker(entry_stages=set(plan.entry_stages))
        self.lossless = cfg.run.mode == "lossless"
        self.ctx = mp.get_context("spawn")
        self.groups = group_workers(self.plan, cfg.run.topology)
        #: the workers this supervisor starts (all but where other hosts run some: runtime/parts.py),
        #: and whether it runs the source and the monitor
        self.hosted: list[str] = list(self.groups)
        self.is_primary = True
        self.runs_source = True
        self.procs: dict[str, Any] = {}
        self.restarts: dict[str, int] = {}
        self.interrupts = 0
        self.last_signal: int | None = None
        self.restart_events: list[dict[str, Any]] = []
        self.source_failure: str | None = None
        self.t_start = time.time()
        self.resume = Path(resume) if resume else None
        self.resume_cut: int | None = None
        if self.resume is not None:
            names = [s.name for s in self.plan.stages]
            self.resume_cut = latest_complete_cut(self.resume / "checkpoint", names)
            if self.resume_cut is None:
                raise RunError(f"no complete checkpoint in {self.resume / 'checkpoint'} "
                               f"(every stage of {names} must have saved the same cut)")
        self.map_path = ""
        if map_path is not None:
            if self.resume is not None:
                raise RunError("--map and --resume exclude each other (a resumed run has its own state)")
            from .checkpoint import load_map_file

            try:
                stored = load_map_file(map_path)["stages"]
            except (OSError, ValueError) as exc:
                raise RunError(f"cannot use map {map_path}: {exc}") from None
            names = [s.name for s in self.plan.stages]
            if not set(stored) & set(names):
                raise RunError(f"map {map_path} holds stages {sorted(stored)}, none of this pipeline's {names}")
            for n in sorted(set(stored) - set(names)):
                log.warning("map %s: stage %s is not in this pipeline; ignored", map_path, n)
            self.map_path = str(Path(map_path).resolve())
        host = cfg.bus.host
        order = ["supervisor", "monitor", *self.groups, "source"]
        self.endpoints = {n: f"tcp/{host}:{free_port(host)}" for n in order}
        self.order = order

    # ------------------------------------------------------------------ specs
    def _links(self, name: str) -> tuple[list[str], list[str]]:
        i = self.order.index(name)
        listen = [self.endpoints[name], *self.cfg.bus.listen]
        connect = [self.endpoints[n] for n in self.order[:i]] + list(self.cfg.bus.connect)
        return listen, connect

    def worker_spec(self, wname: str) -> WorkerSpec:
        specs = self.groups[wname]
        listen, connect = self._links(wname)
        connect += [e for s in specs for e in s.connect if e not in connect]
        caps = queue_capacities(self.plan, self.cfg.bus.capacity, wname == "monolithic")
        for s in specs:  # what a node needs at least (the recorder must not lose rows)
            for t, c in s.capacity.items():
                caps[t] = max(c, caps.get(t, self.cfg.bus.default_capacity))
        resume_states = {}
        if self.resume_cut is not None:
            for s in specs:
                resume_states[s.name] = str(cut_dir(self.resume / "checkpoint", self.resume_cut) /
                                            f"{s.name}.state")
        return WorkerSpec(
            name=wname, stages=specs, run=self.run_id, run_dir=str(self.run_dir), lossless=self.lossless,
            listen=listen, connect=connect, shm=self.cfg.bus.shm, capacities=caps,
            default_capacity=self.cfg.bus.default_capacity,
            threads=max(s.threads for s in specs) if wname != "monolithic" else max(
                1, max(s.threads for s in specs)),
            max_batch=self.cfg.run.max_batch, log_level=self.cfg.run.log_level,
            batch_wait_ms={s.name: self.cfg.run.batch_wait_ms[s.name] for s in specs
                           if s.name in self.cfg.run.batch_wait_ms},
            resume_states=resume_states, expected_peers=self.order.index(wname), map_path=self.map_path,
            checkpoint_every=self.cfg.run.checkpoint_every,
            checkpoint_dir=str(self.run_dir / "checkpoint") if self.cfg.run.checkpoint_every else "",
            control_token=self.control_token, topics=list(self.plan.topics))

    def source_spec(self, start_frame: int = 0) -> SourceRunSpec:
        src = self.cfg.source
        listen, connect = self._links("source")
        pacing = src.pacing
        if pacing == "auto":
            pacing = "fixed" if src.rate else ("asap" if self.lossless else "recorded")
        if pacing == "asap" and not self.lossless:
            raise RunError("pacing 'asap' needs lossless mode (real-time runs need a rate)")
        if self.source_factory is None:
            raise RunError(f"no factory given for the source kind {src.kind!r} (launch.run resolves it)")
        return SourceRunSpec(
            source=SourceSpec(self.source_factory, dict(src.params)), run=self.run_id,
            run_dir=str(self.run_dir), lossless=self.lossless, listen=listen, connect=connect,
            shm=self.cfg.bus.shm, pacing=pacing, rate=src.rate, rate_multiplier=src.rate_multiplier,
            max_frames=src.max_frames, duration=src.duration, window=self.cfg.bus.window,
            final_topic=self.plan.final_topic, progress=self.cfg.run.live, start_frame=start_frame,
            expected_peers=len(self.order) - 1,
            wait_topics=list(getattr(self.plan, "consumed_source_topics", ["image"])),
            control_token=self.control_token, topics=list(self.plan.topics))

    def monitor_spec(self) -> MonitorSpec:
        listen, connect = self._links("monitor")
        meta = {"topology": self.cfg.run.topology, "mode": self.cfg.run.mode,
                "pipeline": self.cfg.run.pipeline, "run": self.name, "rate": self.cfg.source.rate,
                "final_topic": self.plan.final_topic}
        return MonitorSpec(run=self.run_id, run_dir=str(self.run_dir), final_topic=self.plan.final_topic,
                           entry_stages=self.plan.entry_stages,
                           workers={w: [s.name for s in specs] for w, specs in self.groups.items()},
                           meta=meta, listen=listen, connect=connect, shm=self.cfg.bus.shm,
                           live=self.cfg.run.live, control_token=self.control_token,
                           topics=list(self.plan.topics))

    # ------------------------------------------------------------------ processes
    def export_bus_settings(self) -> None:
        """bus.zenoh_config and bus.tx_queue for every process of the run: spawned children
        inherit this process's environment, and bus.make_config reads it."""
        if self.cfg.bus.zenoh_config:
            os.environ[ZENOH_CONFIG_ENV] = self.cfg.bus.zenoh_config
        if self.cfg.bus.tx_queue:
            os.environ[ZENOH_TX_QUEUE_ENV] = str(self.cfg.bus.tx_queue)
        else:  # not left over from an earlier run of this process (a bench sweep)
            os.environ.pop(ZENOH_TX_QUEUE_ENV, None)

    def scheduling(self, name: str) -> dict[str, Any]:
        """run.nice and run.cpus of process ``name`` (a worker, "source" or "monitor"): its own key,
        else those of the stages it hosts (the lowest niceness, the union of their CPUs; a stage not
        named counts as niceness 0 on any CPU)."""
        run = self.cfg.run
        keys = [name] if name in run.nice or name in run.cpus or name not in self.groups \
            else [s.name for s in self.groups[name]]
        cpus = sorted({c for k in keys for c in run.cpus.get(k, [])})
        # a stage not named runs at niceness 0 and on any CPU, so its process does too
        any_cpu = any(k not in run.cpus for k in keys)
        return {"nice": min(run.nice.get(k, 0) for k in keys), "cpus": [] if any_cpu else cpus}

    # ------------------------------------------------------------------ the run
    def run(self) -> RunResult:
        self.host_start = sample_host()  # the host's own figures over the run (report.json's host)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(self.cfg.model_dump(mode="json"),
                                                                 sort_keys=False))
        old_int = signal.signal(signal.SIGINT, self._on_signal)
        old_term = signal.signal(signal.SIGTERM, self._on_signal)
        self.export_bus_settings()
        # a router, so that tools attaching in client mode (`neoslam monitor`) reach every process
        self.session = open_session([self.endpoints["supervisor"], *self.cfg.bus.listen,
                                     *self.cfg.bus.router_listen],
                                    list(self.cfg.bus.connect), self.cfg.bus.shm, mode="router")
        # written once the router listens: whoever reads it can connect at once
        tmp = self.run_dir / "endpoints.json.tmp"
        tmp.write_text(json.dumps({"run": self.run_id, "name": self.name,
                                   "connect": [self.endpoints["supervisor"]], "mode": "client"}, indent=2))
        os.replace(tmp, self.run_dir / "endpoints.json")
        self.collector = StatsCollector()
        stats_sub = self.session.declare_subscriber(key_for(self.run_id, "stats/**"),
                                                    self.collector.on_sample)
        # the supervisor's own count of the frames that arrived: it outlives a killed monitor
        final_sub = self.session.declare_subscriber(key_for(self.run_id, self.plan.final_topic),
                                                    self.final.on_sample)
        for name in ("timeline.csv", "stats.jsonl"):  # the monitor appends (it may be restarted)
            (self.run_dir / name).unlink(missing_ok=True)
        interrupted = False
        #: why the run failed (a process that refused its state, a worker given up on, the source)
        self.failure: str | None = None
        try:
            self._select_hosted()
            # the monitor and the workers start together: the monitor, far lighter, is ready long
            # before any worker publishes a stage's stats
            if self.is_primary:
                self._start("monitor", monitor_entry, self.monitor_spec())
            for w in self.hosted:
                self._start(w, worker_entry, self.worker_spec(w))
            if self.is_primary:
                self._wait_ready(["monitor"], 60.0)
            # every worker of the run, those of other hosts included (their tokens come through the router)
            self._wait_ready(list(self.groups), self.cfg.run.startup_timeout)
            if self.runs_source:
                start_frame = self._resume_frame()
                self._start("source", source_entry, self.source_spec(start_frame))
            interrupted = self._supervise()
        except RunError as exc:
            if not self.interrupts:
                self.failure = str(exc)  # the report says so before the error goes on
            else:
                interrupted = True  # Ctrl-C during start-up or a crash while stopping: an interrupted run
        finally:
            self._shutdown()
            stats_sub.undeclare()
            final_sub.undeclare()
            self.session.close()
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)
        if self.source_failure and not self.failure:
            self.failure = f"the source failed: {self.source_failure}"
        report = self._complete_report(interrupted)
        if self.failure:
            raise RunError(f"{self.failure} (report: {self.run_dir / 'report.json'})")
        return RunResult(self.run_dir, report, interrupted, dict(self.restarts),
                         self.last_signal if interrupted else None)

    def _select_hosted(self) -> None:
        """Which workers this supervisor starts; all of them here (runtime/parts.py overrides it)."""

    def _resume_frame(self) -> int:
        return self.resume_cut or 0

    def _stage_names(self) -> list[str]:
        return [s.name for specs in self.groups.values() for s in specs]

    def _supervise(self) -> bool:
        """Until the source is done and the pipeline drained; returns True when interrupted."""
        src_done_at: float | None = None
        while True:
            time.sleep(0.2)
            if self.interrupts:
                return True
            self._restart_crashed()
            self._restart_monitor()
            src = self.collector.snapshot().get("source", {})
            source_proc = self.procs["source"]
            if not source_proc.is_alive() and source_proc.exitcode not in (0, None) and not src.get("done"):
                err = self.run_dir / "source_error.txt"
                self.source_failure = (err.read_text().strip() if err.exists()
                                       else f"the source process died with exit code {source_proc.exitcode}")
                return False
            if src_done_at is None and (src.get("done") or not source_proc.is_alive()):
                src_done_at = time.monotonic()
            if src_done_at is None:
                continue
            waited = time.monotonic() - src_done_at
            if self.lossless:
                # drained: every stage's newest stats (taken between two messages) show everything
                # its upstream published received and nothing waiting, and the final topic's
                # messages all arrived here; no quiet period is needed on top
                if self.collector.quiet(self._stage_names(), for_s=0.0, fresh_s=1.5) and self._final_arrived():
                    return False
                # a message lost in transport would keep the strict check false for ever
                if waited > 20 and self.collector.quiet(self._stage_names(), for_s=10.0, fresh_s=1.5,
                                                        check_transport=False):
                    log.warning("pipeline idle but not every published message arrived; ending the run")
                    return False
                if waited > 600:
                    log.warning("pipeline did not drain within 600 s after the source ended")
                    return False
            elif waited >= self.cfg.run.drain_s:
                return False

    def _final_arrived(self) -> bool:
        """Whether every message a stage published on the final topic reached this process (the
        report's frames out and latencies are counted from them)."""
        topic = self.plan.final_topic
        sent = sum((st.get("published") or {}).get(topic, 0) for st in self.collector.snapshot().values())
        with self.final.lock:
            return self.final.messages >= sent

    def _complete_report(self, interrupted: bool) -> dict[str, Any]:
        """report.json: the monitor's (when it wrote one in this run), with every figure the
        supervisor measured itself on top: the stats and final frames over the whole run, whatever
        happened to the monitor. Written atomically; a full disk keeps the previous file."""
        path = self.run_dir / "report.json"
        report: dict[str, Any] = {}
        try:
            if path.stat().st_mtime >= self.t_start - 1:  # not a report of an earlier run here
                report = json.loads(path.read_text())
        except (OSError, ValueError):
            pass
        if not report:
            report["monitor_report"] = "the monitor wrote no report; figures measured by the supervisor"
        meta = self.monitor_spec().meta
        workers = {w: [s.name for s in specs] for w, specs in self.groups.items()}
        report.update(build_report(self.collector.snapshot(), self.final, workers, meta))
        report["restarts"] = dict(self.restarts)
        report["restart_events"] = list(self.restart_events)
        report["signal"] = self.last_signal if interrupted else None
        report["source_failure"] = self.source_failure
        report["interrupted"] = interrupted
        # a failed run says so, with its cause, and keeps no figure measured over nothing
        mark_status(report, getattr(self, "failure", None), interrupted, self.source_failure)
        report["run_dir"] = str(self.run_dir)
        report["workers"] = {w: [s.name for s in specs] for w, specs in self.groups.items()}
        report["host"] = host_usage(self.host_start, sample_host())  # run() sampled its start
        write_report(path, report)
        return report


def run_plan(cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
             resume: str | Path | None = None, map_path: str | Path | None = None,
             source_factory: str | None = None) -> RunResult:
    """Run ``plan`` to the end (or until interrupted) and return the report. ``resume``: a run
    folder to continue from its last complete checkpoint; ``map_path``: an exported map to start
    from (a new session on an old map); ``source_factory``: what builds the run's source."""
    return Supervisor(cfg, plan, run_dir, resume, map_path, source_factory).run()
