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
The :class:`Supervisor` owns a :class:`~neoslam_stream.runtime.layout.RunLayout` (which processes run
here, how they link, the spec of each: layout.py) and a
:class:`~neoslam_stream.runtime.children.Children` (starting, restarting and stopping them:
children.py).
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import signal
import time
from pathlib import Path
from typing import Any

import yaml

from . import runlog
from .bus import ZENOH_CONFIG_ENV, ZENOH_TX_QUEUE_ENV, key_for, open_session
from .checkpoint import StateFormatError, check_state_file, cut_dir, latest_complete_cut, load_map_file
from .children import Children
from .collector import FinalTracker, StatsCollector
from .config import RunConfig
from .host import host_usage, sample_host
from .layout import RunLayout, queue_capacities
from .messages import register_topics
from .plan import PipelinePlan, RunError, RunResult, group_workers, make_run_dir
from .procs import monitor_entry, source_entry, worker_entry
from .report import build_report, mark_status, write_report
from .runlog import LOG_FILE

# what other modules take from here: the plan and its results, and how queues are sized
__all__ = ["CONTROL_TOKEN_ENV", "PipelinePlan", "RunError", "RunResult", "Supervisor", "group_workers",
           "make_run_dir", "queue_capacities", "run_plan"]

#: environment variable holding the control secret shared by every host of a split run: an
#: environment variable, not a flag, so that other local users do not read it in the process table
CONTROL_TOKEN_ENV = "NEOSLAM_CONTROL_TOKEN"

log = logging.getLogger("neoslam.topology")


def check_cut(checkpoint_dir: Path, cut: int, stages: list[str]) -> None:
    """Refuse to resume from a cut whose state files another version of neoslam wrote (one line
    naming the first such file), before any process starts."""
    for name in stages:
        try:
            check_state_file(cut_dir(checkpoint_dir, cut) / f"{name}.state")
        except StateFormatError as exc:
            raise RunError(f"cannot resume: {exc}") from None


class Supervisor:
    """Runs ``plan`` with the runtime sections of ``cfg`` (``run``, ``bus``, ``source``);
    ``source_factory``: the ``"module:callable"`` that builds ``cfg.source``'s source (``launch``
    resolves the source kind). It owns the run's layout (which processes, their specs), its child
    processes, and the figures it follows itself (``collector``, ``final``)."""

    def __init__(self, cfg: RunConfig, plan: PipelinePlan, run_dir: str | Path | None = None,
                 resume: str | Path | None = None, map_path: str | Path | None = None,
                 source_factory: str | None = None) -> None:
        self.cfg = cfg
        self.plan = plan
        register_topics(plan.topics)  # this process decodes the final topic too (FinalTracker)
        self.name, self.run_dir = make_run_dir(cfg, run_dir)
        # a run split over several hosts (runtime/share.py) shares one id, given to every host
        self.run_id = cfg.run.run_id or f"r{secrets.token_hex(4)}"
        #: the control topic's secret: only this supervisor's commands are obeyed (bus.ControlGate);
        #: the hosts of a split run share one through CONTROL_TOKEN_ENV (runtime/share.py)
        self.control_token = os.environ.get(CONTROL_TOKEN_ENV) or secrets.token_hex(16)
        self.final = FinalTracker(entry_stages=set(plan.entry_stages))
        self.collector = StatsCollector()
        self.lossless = cfg.run.mode == "lossless"
        self.source_failure: str | None = None
        #: why the run failed (a process that refused its state, a worker given up on, the source)
        self.failure: str | None = None
        self.t_start = time.time()
        names = [s.name for s in plan.stages]
        resume = Path(resume) if resume else None
        resume_cut: int | None = None
        if resume is not None:
            resume_cut = latest_complete_cut(resume / "checkpoint", names)
            if resume_cut is None:
                raise RunError(f"no complete checkpoint in {resume / 'checkpoint'} "
                               f"(every stage of {names} must have saved the same cut)")
            check_cut(resume / "checkpoint", resume_cut, names)
        stored_map = ""
        if map_path is not None:
            if resume is not None:
                raise RunError("--map and --resume exclude each other (a resumed run has its own state)")
            try:
                stored = load_map_file(map_path)["stages"]
            except (OSError, ValueError) as exc:
                raise RunError(f"cannot use map {map_path}: {exc}") from None
            if not set(stored) & set(names):
                raise RunError(f"map {map_path} holds stages {sorted(stored)}, none of this pipeline's {names}")
            for n in sorted(set(stored) - set(names)):
                log.warning("map %s: stage %s is not in this pipeline; ignored", map_path, n)
            stored_map = str(Path(map_path).resolve())
        self.layout = RunLayout(cfg, plan, self.name, self.run_id, self.run_dir, self.control_token,
                                source_factory, stored_map, resume, resume_cut)
        self.children = Children(self.layout, self.collector, self.t_start)

    def export_bus_settings(self) -> None:
        """bus.zenoh_config and bus.tx_queue for every process of the run: spawned children
        inherit this process's environment, and bus.make_config reads it."""
        if self.cfg.bus.zenoh_config:
            os.environ[ZENOH_CONFIG_ENV] = self.cfg.bus.zenoh_config
        if self.cfg.bus.tx_queue:
            os.environ[ZENOH_TX_QUEUE_ENV] = str(self.cfg.bus.tx_queue)
        else:  # not left over from an earlier run of this process (a bench sweep)
            os.environ.pop(ZENOH_TX_QUEUE_ENV, None)

    # ------------------------------------------------------------------ the run
    def run(self) -> RunResult:
        layout, children = self.layout, self.children
        self.host_start = sample_host()  # the host's own figures over the run (report.json's host)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(self.cfg.model_dump(mode="json"),
                                                                 sort_keys=False))
        old_int = signal.signal(signal.SIGINT, children.on_signal)
        old_term = signal.signal(signal.SIGTERM, children.on_signal)
        self.export_bus_settings()
        # a router, so that tools attaching in client mode (`neoslam monitor`) reach every process
        supervisor = layout.endpoints["supervisor"]
        self.session = open_session([supervisor, *self.cfg.bus.listen, *self.cfg.bus.router_listen],
                                    list(self.cfg.bus.connect), self.cfg.bus.shm, mode="router")
        children.session = self.session
        # written once the router listens: whoever reads it can connect at once
        tmp = self.run_dir / "endpoints.json.tmp"
        tmp.write_text(json.dumps({"run": self.run_id, "name": self.name,
                                   "connect": [supervisor], "mode": "client"}, indent=2))
        os.replace(tmp, self.run_dir / "endpoints.json")
        stats_sub = self.session.declare_subscriber(key_for(self.run_id, "stats/**"),
                                                    self.collector.on_sample)
        # the supervisor's own count of the frames that arrived: it outlives a killed monitor
        final_sub = self.session.declare_subscriber(key_for(self.run_id, self.plan.final_topic),
                                                    self.final.on_sample)
        for name in ("timeline.csv", "stats.jsonl", LOG_FILE):  # the monitor appends (it may be restarted)
            (self.run_dir / name).unlink(missing_ok=True)
        if layout.trace_path and layout.is_primary:  # so is the trace (run.trace)
            Path(layout.trace_path).unlink(missing_ok=True)
        logs = runlog.attach(self.session, self.run_id, "supervisor")  # its log lines on the bus too
        interrupted = False
        self.failure = None
        try:
            self._select_hosted()
            # the monitor and the workers start together: the monitor, far lighter, is ready long
            # before any worker publishes a stage's stats
            if layout.is_primary:
                children.start("monitor", monitor_entry, layout.monitor_spec())
            for w in layout.hosted:
                children.start(w, worker_entry, layout.worker_spec(w))
            if layout.is_primary:
                children.wait_ready(["monitor"], 60.0)
            # every worker of the run, those of other hosts included (their tokens come through the router)
            children.wait_ready(list(layout.groups), self.cfg.run.startup_timeout)
            if layout.runs_source:
                self._wait_for_tools()
                start_frame = self._resume_frame()
                children.start("source", source_entry, layout.source_spec(start_frame))
            interrupted = self._supervise()
        except RunError as exc:
            if not children.interrupts:
                self.failure = str(exc)  # the report says so before the error goes on
            else:
                interrupted = True  # Ctrl-C during start-up or a crash while stopping: an interrupted run
        finally:
            self._shutdown()
            stats_sub.undeclare()
            final_sub.undeclare()
            runlog.detach(logs)
            self.session.close()
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)
        if self.source_failure and not self.failure:
            self.failure = f"the source failed: {self.source_failure}"
        report = self._complete_report(interrupted)
        if self.failure:
            raise RunError(f"{self.failure} (report: {self.run_dir / 'report.json'})")
        return RunResult(self.run_dir, report, interrupted, dict(children.restarts),
                         children.last_signal if interrupted else None)

    def _wait_for_tools(self) -> None:
        """The tools the first frame waits for (``run.wait_for``: a viewer that must see frame 0),
        at most ``run.wait_for_s``; a tool that has not attached by then is not waited for."""
        missing = list(self.cfg.run.wait_for)
        deadline = time.monotonic() + self.cfg.run.wait_for_s
        while missing and time.monotonic() < deadline and not self.children.interrupts:
            alive = self.children.alive_tokens()
            missing = [n for n in missing if n not in alive]
            if missing:
                time.sleep(0.2)
        if missing:
            log.warning("starting without %s: not attached to the run after %.0f s", ", ".join(missing),
                        self.cfg.run.wait_for_s)

    # ------------------------------------------------------------------ what a share changes
    def _select_hosted(self) -> None:
        """Which workers this supervisor starts; all of them here (share.py narrows them)."""

    def _resume_frame(self) -> int:
        return self.layout.resume_cut or 0

    def _shutdown(self) -> None:
        self.children.shutdown()

    # ------------------------------------------------------------------ following the run
    def _source_died(self, proc: Any) -> bool:
        """Whether the source process ended with an error; its cause is then ``source_failure``
        (what it wrote in source_error.txt, else its exit code)."""
        if proc is None or proc.is_alive() or proc.exitcode in (0, None):
            return False
        err = self.run_dir / "source_error.txt"
        self.source_failure = (err.read_text().strip() if err.exists()
                               else f"the source process died with exit code {proc.exitcode}")
        return True

    def _supervise(self) -> bool:
        """Until the source is done and the pipeline drained; returns True when interrupted."""
        children = self.children
        src_done_at: float | None = None
        while True:
            time.sleep(0.2)
            if children.interrupts:
                return True
            children.restart_crashed()
            children.restart_monitor()
            src = self.collector.snapshot().get("source", {})
            source_proc = children.procs["source"]
            if not src.get("done") and self._source_died(source_proc):
                return False
            if src_done_at is None and (src.get("done") or not source_proc.is_alive()):
                src_done_at = time.monotonic()
            if src_done_at is None:
                continue
            waited = time.monotonic() - src_done_at
            stages = self.layout.stage_names()
            if self.lossless:
                # drained: every stage's newest stats (taken between two messages) show everything
                # its upstream published received and nothing waiting, and the final topic's
                # messages all arrived here; no quiet period is needed on top
                if self.collector.quiet(stages, for_s=0.0, fresh_s=1.5) and self._final_arrived():
                    return False
                # a message lost in transport would keep the strict check false for ever
                if waited > 20 and self.collector.quiet(stages, for_s=10.0, fresh_s=1.5, check_transport=False):
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
        children = self.children
        path = self.run_dir / "report.json"
        report: dict[str, Any] = {}
        try:
            if path.stat().st_mtime >= self.t_start - 1:  # not a report of an earlier run here
                report = json.loads(path.read_text())
        except (OSError, ValueError):
            pass
        if not report:
            report["monitor_report"] = "the monitor wrote no report; figures measured by the supervisor"
        report.update(build_report(self.collector.snapshot(), self.final, self.layout.workers(),
                                   self.layout.meta()))
        report["restarts"] = dict(children.restarts)
        report["restart_events"] = list(children.restart_events)
        # a worker stopped by force may not have saved its final state: `neoslam map export` reads this
        report["stopped_by_force"] = list(children.stopped_by_force)
        report["signal"] = children.last_signal if interrupted else None
        report["source_failure"] = self.source_failure
        report["interrupted"] = interrupted
        # a failed run says so, with its cause, and keeps no figure measured over nothing
        mark_status(report, self.failure, interrupted, self.source_failure)
        report["run_dir"] = str(self.run_dir)
        report["workers"] = self.layout.workers()
        report["host"] = host_usage(self.host_start, sample_host())  # run() sampled its start
        write_report(path, report)
        return report


def run_plan(cfg: RunConfig, plan: PipelinePlan, run_dir: str | Path | None = None,
             resume: str | Path | None = None, map_path: str | Path | None = None,
             source_factory: str | None = None) -> RunResult:
    """Run ``plan`` to the end (or until interrupted) and return the report. ``resume``: a run
    folder to continue from its last complete checkpoint; ``map_path``: an exported map to start
    from (a new session on an old map); ``source_factory``: what builds the run's source."""
    return Supervisor(cfg, plan, run_dir, resume, map_path, source_factory).run()
