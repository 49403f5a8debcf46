"""Builds and supervises a run: the source, the stage workers and the monitor, each a process.

Topologies (DESIGN.md): ``pipeline`` runs one process per stage connected by zenoh pub/sub;
``monolithic`` runs every stage in one process, in sequence, and like the original blocking NeoSLAM
discards frames that arrive while it is busy except the newest (a small drop-oldest image ring).
Both host the very same nodes. The runtime knows no algorithm: the caller gives the
:class:`PipelinePlan` (``neoslam_stream.nodes.pipelines`` builds the named ones).

Every child is a zenoh peer that listens on its own loopback port and connects to all processes
started before it (a full mesh, so frames go directly from producer to consumer). The supervisor
(this process) is a zenoh router on its own port, so a tool attaching in client mode to that one
endpoint (``neoslam monitor RUN_DIR``, tests injecting messages) reaches every process. It waits until every worker announced readiness, starts the
source, restarts a crashed worker or monitor (bounded, reported), detects the end of the run
(source done and the pipeline drained), stops everything in order and completes ``report.json``.

Hardening (#13): every child dies with the supervisor (procs.follow_parent: it gets the
supervisor's pid in its spawn arguments); control messages carry a per-run secret token, handed to
the children in their specs and never sent alone over the bus, and every process refuses (and
counts) control messages without it (bus.ControlGate); the supervisor follows the stats and the
final topic itself, so the report's loss is measured over the whole run even when the monitor was
killed and restarted, and it writes report.json atomically (a full disk keeps the previous one).
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import secrets
import signal
import time
from collections.abc import Collection
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import yaml

from ..sources import source_factory
from .bus import ZENOH_CONFIG_ENV, ZENOH_TX_QUEUE_ENV, free_port, key_for, open_session
from .checkpoint import cut_dir, latest_complete_cut, latest_stage_state
from .messages import Message, encode
from .monitor import FinalTracker, MonitorSpec, StatsCollector, build_report, write_report
from .node import NodeSpec
from .procs import monitor_entry, source_entry, worker_entry
from .source_runner import SourceRunSpec, SourceSpec
from .worker import WorkerSpec

#: environment variable holding the control secret shared by every host of a split run: an
#: environment variable, not a flag, so that other local users do not read it in the process table
CONTROL_TOKEN_ENV = "NEOSLAM_CONTROL_TOKEN"

log = logging.getLogger("neoslam.topology")


@dataclass
class PipelinePlan:
    """The nodes of a run, the topic whose arrival marks a frame as done, and the image entry stages."""

    stages: list[NodeSpec]
    final_topic: str
    entry_stages: list[str] = field(default_factory=list)
    #: source topics with a consumer: the source waits for their subscribers before the first frame
    consumed_source_topics: list[str] = field(default_factory=lambda: ["image"])


class RunError(RuntimeError):
    """A run could not start or finish; the text says which process and why."""


@dataclass
class RunResult:
    run_dir: Path
    report: dict[str, Any]
    interrupted: bool = False
    restarts: dict[str, int] = field(default_factory=dict)
    #: the signal that interrupted the run (SIGINT, SIGTERM), if any
    signal: int | None = None


def group_workers(plan: PipelinePlan, topology: str) -> dict[str, list[NodeSpec]]:
    """Worker name -> its NodeSpecs: all in one for ``monolithic``; one each for ``pipeline``,
    except that a node with ``host`` joins the worker of the node it names."""
    if topology == "monolithic":
        return {"monolithic": list(plan.stages)}
    if topology != "pipeline":
        raise ValueError(f"unknown topology {topology!r} (pipeline or monolithic)")
    groups: dict[str, list[NodeSpec]] = {}
    for s in plan.stages:
        if s.host:
            if s.host not in groups:
                raise ValueError(f"node {s.name!r} is to be hosted by {s.host!r}, which is not before it")
            groups[s.host].append(s)
        else:
            groups[s.name] = [s]
    return groups


def make_run_dir(cfg: Any, out: str | Path | None) -> tuple[str, Path]:
    name = cfg.run.name or f"{cfg.run.pipeline}-{cfg.run.topology}-{datetime.now():%Y%m%d-%H%M%S}"
    base = Path(out) if out is not None else Path(cfg.run.out) / name
    base.mkdir(parents=True, exist_ok=True)
    return name, base


class Supervisor:
    """Runs ``plan`` with the runtime sections of ``cfg`` (``run``, ``bus``, ``source``)."""

    def __init__(self, cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
                 resume: str | Path | None = None, map_path: str | Path | None = None) -> None:
        self.cfg = cfg
        self.plan = plan
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
        caps = dict(self.cfg.bus.capacity)
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
            resume_states=resume_states, expected_peers=self.order.index(wname), map_path=self.map_path,
            checkpoint_every=self.cfg.run.checkpoint_every,
            checkpoint_dir=str(self.run_dir / "checkpoint") if self.cfg.run.checkpoint_every else "",
            control_token=self.control_token)

    def source_spec(self, start_frame: int = 0) -> SourceRunSpec:
        src = self.cfg.source
        listen, connect = self._links("source")
        pacing = src.pacing
        if pacing == "auto":
            pacing = "fixed" if src.rate else ("asap" if self.lossless else "recorded")
        if pacing == "asap" and not self.lossless:
            raise RunError("pacing 'asap' needs lossless mode (real-time runs need a rate)")
        return SourceRunSpec(
            source=SourceSpec(source_factory(src.kind), dict(src.params)), run=self.run_id,
            run_dir=str(self.run_dir), lossless=self.lossless, listen=listen, connect=connect,
            shm=self.cfg.bus.shm, pacing=pacing, rate=src.rate, rate_multiplier=src.rate_multiplier,
            max_frames=src.max_frames, duration=src.duration, window=self.cfg.bus.window,
            final_topic=self.plan.final_topic, progress=self.cfg.run.live, start_frame=start_frame,
            expected_peers=len(self.order) - 1,
            wait_topics=list(getattr(self.plan, "consumed_source_topics", ["image"])),
            control_token=self.control_token)

    def monitor_spec(self) -> MonitorSpec:
        listen, connect = self._links("monitor")
        meta = {"topology": self.cfg.run.topology, "mode": self.cfg.run.mode,
                "pipeline": self.cfg.run.pipeline, "run": self.name, "rate": self.cfg.source.rate,
                "final_topic": self.plan.final_topic}
        return MonitorSpec(run=self.run_id, run_dir=str(self.run_dir), final_topic=self.plan.final_topic,
                           entry_stages=self.plan.entry_stages,
                           workers={w: [s.name for s in specs] for w, specs in self.groups.items()},
                           meta=meta, listen=listen, connect=connect, shm=self.cfg.bus.shm,
                           live=self.cfg.run.live, control_token=self.control_token)

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

    def _start(self, name: str, target: Any, spec: Any) -> None:
        # the supervisor's pid: the child stops when this process dies (procs.follow_parent)
        p = self.ctx.Process(target=target, args=(spec, os.getpid(), self.scheduling(name)), name=f"neoslam-{name}",
                             daemon=False)
        p.start()
        self.procs[name] = p

    def _alive_tokens(self) -> set[str]:
        names = set()
        for reply in self.session.liveliness().get(key_for(self.run_id, "alive/*"), timeout=1.0):
            try:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
            except Exception:
                continue
        return names

    def _wait_ready(self, names: list[str], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            alive = self._alive_tokens()
            if all(n in alive for n in names):
                return
            for n in names:
                p = self.procs.get(n)
                if p is not None and not p.is_alive() and not self.interrupts:  # Ctrl-C: no restart
                    if n in self.groups and self.restarts.get(n, 0) < self.cfg.run.max_restarts:
                        self._restart(n, p.exitcode)
                        continue
                    raise RunError(f"process {n!r} exited with code {p.exitcode} during start-up "
                                   f"(see its log above)")
            if time.monotonic() > deadline or self.interrupts:
                missing = [n for n in names if n not in alive]
                raise RunError(f"processes not ready after {timeout:.0f} s: {missing}")
            time.sleep(0.2)

    def _control(self, command: str, target: str | None = None, **extra: Any) -> None:
        data = {"command": command, "token": self.control_token, **extra}
        if target is not None:
            data["target"] = target
        self.session.put(key_for(self.run_id, "control"), encode(Message("control", 0, time.time(), data)))

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.interrupts += 1
        self.last_signal = signum
        if self.interrupts >= 2:
            log.warning("second interrupt: killing every process of the run")
            for p in self.procs.values():
                if p.is_alive():
                    p.kill()

    # ------------------------------------------------------------------ the run
    def run(self) -> RunResult:
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
        try:
            self._select_hosted()
            if self.is_primary:
                self._start("monitor", monitor_entry, self.monitor_spec())
                self._wait_ready(["monitor"], 60.0)
            for w in self.hosted:
                self._start(w, worker_entry, self.worker_spec(w))
            # every worker of the run, those of other hosts included (their tokens come through the router)
            self._wait_ready(list(self.groups), self.cfg.run.startup_timeout)
            if self.is_primary:
                start_frame = self._resume_frame()
                self._start("source", source_entry, self.source_spec(start_frame))
            interrupted = self._supervise()
        except RunError:
            if not self.interrupts:
                raise
            interrupted = True  # Ctrl-C during start-up or a crash while stopping: an interrupted run
        finally:
            self._shutdown()
            stats_sub.undeclare()
            final_sub.undeclare()
            self.session.close()
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)
        report = self._complete_report(interrupted)
        if self.source_failure:
            raise RunError(f"the source failed: {self.source_failure} (report: {self.run_dir / 'report.json'})")
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
                if self.collector.quiet(self._stage_names(), for_s=1.0, fresh_s=1.5):
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

    def _restart_crashed(self, stopped: Collection[str] = ()) -> None:
        """Restart the hosted workers that died (bounded); ``stopped``: workers that ended on
        purpose (a split run's primary stopped them), not to be restarted."""
        for w in self.hosted:
            p = self.procs.get(w)
            if w in stopped or p is None or p.is_alive():
                continue
            n = self.restarts.get(w, 0)
            if n >= self.cfg.run.max_restarts:
                raise RunError(f"worker {w!r} died (exit code {p.exitcode}) and was already restarted "
                               f"{n} times; giving up")
            self._restart(w, p.exitcode)
            self._wait_ready([w], self.cfg.run.startup_timeout)

    def _restart_monitor(self) -> None:
        """A dead monitor is started again (bounded, reported like a worker's restart). Its figures
        are not lost: the supervisor follows the stats and the final topic itself."""
        p = self.procs.get("monitor")
        if p is None or p.is_alive():
            return
        n = self.restarts.get("monitor", 0)
        if n >= self.cfg.run.max_restarts:
            if not getattr(self, "_monitor_given_up", False):
                self._monitor_given_up = True
                log.error("the monitor died (exit code %s) and was already restarted %d times; the run "
                          "goes on without it (the supervisor still writes the report)", p.exitcode, n)
            return
        log.warning("the monitor died with exit code %s; restarting (%d/%d)", p.exitcode, n + 1,
                    self.cfg.run.max_restarts)
        self.restarts["monitor"] = n + 1
        self.restart_events.append({"worker": "monitor", "time_s": round(time.time() - self.t_start, 3),
                                    "exit_code": p.exitcode, "resumed_from_cut": None,
                                    "frames_in_at_restart": self.collector.snapshot().get("source", {})
                                    .get("frames_in")})
        self._start("monitor", monitor_entry, self.monitor_spec())

    def _restart(self, w: str, exitcode: int | None) -> None:
        """Start worker ``w`` again, with each stage's newest checkpointed state when there is one."""
        n = self.restarts.get(w, 0)
        log.warning("worker %s died with exit code %s; restarting (%d/%d)", w, exitcode, n + 1,
                    self.cfg.run.max_restarts)
        self.restarts[w] = n + 1
        spec = self.worker_spec(w)
        cuts = []
        for s in spec.stages:
            path = latest_stage_state(self.run_dir / "checkpoint", s.name)
            if path is not None:
                spec.resume_states[s.name] = str(path)
                cuts.append(int(path.parent.name))
        src = self.collector.snapshot().get("source", {}) if self.collector is not None else {}
        # what the report says about the crash: when, how, which state came back, and the source's
        # frame count then (the frames lost in between are those the stage never saw)
        self.restart_events.append({
            "worker": w, "time_s": round(time.time() - self.t_start, 3), "exit_code": exitcode,
            "resumed_from_cut": min(cuts) if cuts else None, "frames_in_at_restart": src.get("frames_in")})
        self._start(w, worker_entry, spec)

    def _shutdown(self) -> None:
        """Stop the source, then the workers (they flush), then the monitor; nothing left behind."""
        def stop(names: list[str], timeout: float) -> None:
            for n in names:
                self._control("stop", n)
            deadline = time.monotonic() + timeout
            for n in names:
                p = self.procs.get(n)
                if p is None:
                    continue
                p.join(max(0.1, deadline - time.monotonic()))
                if p.is_alive():
                    log.warning("%s did not stop in time; terminating", n)
                    p.terminate()
                    p.join(5)
                if p.is_alive():
                    p.kill()
                    p.join(2)
            self._wait_remote_stopped([n for n in names if n in self.groups and n not in self.hosted],
                                      deadline)

        try:
            # the primary of a run split over hosts stops the other hosts' workers too, in order
            workers = [w for w in self.groups if w in self.procs or (self.is_primary and w not in self.hosted)]
            # processes that host a watcher (the recorder) go last: what the others publish up to
            # their end (a stage's last frame, the pose cells' final actions) is still recorded
            watchers = [w for w in workers if any(s.observer for s in self.groups[w])]
            others = [w for w in workers if w not in watchers]
            if self.lossless:
                if "source" in self.procs:
                    stop(["source"], 10)
                stop(others, 60)
            else:  # a live run ends at once: what is still in flight when the camera stops is lost
                stop([n for n in ("source", *others) if n in self.procs], 60)
            stop(watchers, 60)
            if "monitor" in self.procs:
                stop(["monitor"], 30)
        finally:
            for p in self.procs.values():
                if p.is_alive():
                    p.kill()
                    p.join(2)

    def _wait_remote_stopped(self, names: list[str], deadline: float) -> None:
        """Wait until the workers ``names`` of other hosts have withdrawn their liveliness tokens."""
        while names and time.monotonic() < deadline:
            if not set(names) & self._alive_tokens():
                return
            time.sleep(0.2)

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
        report["run_dir"] = str(self.run_dir)
        report["workers"] = {w: [s.name for s in specs] for w, specs in self.groups.items()}
        write_report(path, report)
        return report


def run_plan(cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
             resume: str | Path | None = None, map_path: str | Path | None = None) -> RunResult:
    """Run ``plan`` to the end (or until interrupted) and return the report. ``resume``: a run
    folder to continue from its last complete checkpoint; ``map_path``: an exported map to start
    from (a new session on an old map)."""
    return Supervisor(cfg, plan, run_dir, resume, map_path).run()
