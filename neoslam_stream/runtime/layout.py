"""The processes of a run on this host: which run here, how they link, and what each is given.

Every child is a zenoh peer listening on its own loopback port and connecting to the processes
started before it (``order``: supervisor, monitor, workers, source), so frames go straight from
producer to consumer. A host's share of a run split over hosts (share.py) runs some of the
workers, links only to its own earlier processes and reaches the others through its supervisor's
router; its processes start in the run's current epoch and, when lossless, take their inputs in
strict order. The specs built here are plain data that cross a ``spawn``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from .checkpoint import cut_dir
from .config import RunConfig
from .monitor import MonitorSpec
from .plan import PipelinePlan, RunError, group_workers
from .ports import free_port
from .source_runner import SourceRunSpec, SourceSpec
from .worker import WorkerSpec


def queue_capacities(plan: PipelinePlan, configured: dict[str, int], monolithic: bool) -> dict[str, int]:
    """Input queue capacity per topic before a worker's own nodes raise it: the plan's, overridden
    by ``bus.capacity`` (``configured``). The monolithic process takes the source's topics at
    ``bus.default_capacity`` unless configured: the original design keeps the newest frames, not a
    batch."""
    caps = plan.capacity
    if monolithic:
        caps = {t: c for t, c in caps.items() if t not in plan.consumed_source_topics}
    return {**caps, **configured}


class RunLayout:
    """The processes of one run on this host (module docstring) and the spec each starts with.

    ``name``: the run's name (its folder's); ``resume``/``resume_cut``: the run folder and
    checkpoint cut the workers start from;
    ``map_path``: an exported map they start from instead; ``source_factory``: what builds the
    run's source. A share supervisor narrows ``hosted``, ``is_primary`` and ``runs_source`` once
    it knows what runs on the other hosts, and sets ``via_router``, ``strict_order`` and ``epoch``.
    """

    def __init__(self, cfg: RunConfig, plan: PipelinePlan, name: str, run_id: str, run_dir: Path,
                 control_token: str, source_factory: str | None = None, map_path: str = "",
                 resume: Path | None = None, resume_cut: int | None = None) -> None:
        self.cfg = cfg
        self.plan = plan
        self.name = name
        self.run_id = run_id
        self.run_dir = run_dir
        self.control_token = control_token
        self.source_factory = source_factory
        self.map_path = map_path
        self.resume = resume
        self.resume_cut = resume_cut
        self.lossless = cfg.run.mode == "lossless"
        self.groups = group_workers(plan, cfg.run.topology)
        #: the run's start (the zero of its trace) and ``run.trace``'s file, absolute ("": none)
        self.t_start = time.time()
        self.trace_path = str(Path(cfg.run.trace).resolve()) if cfg.run.trace else ""
        #: the workers started here (all but where other hosts run some), and whether this host
        #: runs the monitor (the primary: the host with the last stage) and the source
        self.hosted: list[str] = list(self.groups)
        self.is_primary = True
        self.runs_source = True
        #: a share of a split run: each process links to this host's earlier processes only
        self.via_router = False
        #: strict input order (a lossless split run) and the epoch of the processes started now
        self.strict_order = False
        self.epoch = 0
        host = cfg.bus.host
        order = ["supervisor", "monitor", *self.groups, "source"]
        self.endpoints = {n: f"tcp/{host}:{free_port(host)}" for n in order}
        self.order = order

    def stage_names(self, workers: list[str] | None = None) -> list[str]:
        """The stages of ``workers`` (default: every worker of the run)."""
        return [s.name for w in (self.groups if workers is None else workers) for s in self.groups[w]]

    def links(self, name: str) -> tuple[list[str], list[str]]:
        """Where process ``name`` listens and what it connects to: every process started before it
        and ``bus.connect``; in a share, only this host's earlier processes (other hosts are
        reached through the supervisor's router, which alone connects to ``bus.connect``)."""
        i = self.order.index(name)
        listen = [self.endpoints[name], *self.cfg.bus.listen]
        connect = [self.endpoints[n] for n in self.order[:i]]
        if not self.via_router:
            connect += list(self.cfg.bus.connect)
        return listen, connect

    def worker_spec(self, wname: str) -> WorkerSpec:
        cfg = self.cfg
        specs = self.groups[wname]
        listen, connect = self.links(wname)
        connect += [e for s in specs for e in s.connect if e not in connect]
        caps = queue_capacities(self.plan, cfg.bus.capacity, wname == "monolithic")
        for s in specs:  # what a node needs at least (the recorder must not lose rows)
            for t, c in s.capacity.items():
                caps[t] = max(c, caps.get(t, cfg.bus.default_capacity))
        resume_states = {}
        if self.resume_cut is not None and self.resume is not None:
            for s in specs:
                resume_states[s.name] = str(cut_dir(self.resume / "checkpoint", self.resume_cut) /
                                            f"{s.name}.state")
        return WorkerSpec(
            name=wname, stages=specs, run=self.run_id, run_dir=str(self.run_dir), lossless=self.lossless,
            listen=listen, connect=connect, shm=cfg.bus.shm, capacities=caps,
            default_capacity=cfg.bus.default_capacity,
            threads=max(s.threads for s in specs) if wname != "monolithic" else max(
                1, max(s.threads for s in specs)),
            max_batch=cfg.run.max_batch, log_level=cfg.run.log_level,
            batch_wait_ms={s.name: cfg.run.batch_wait_ms[s.name] for s in specs
                           if s.name in cfg.run.batch_wait_ms},
            resume_states=resume_states, expected_peers=self.order.index(wname), map_path=self.map_path,
            checkpoint_every=cfg.run.checkpoint_every,
            checkpoint_dir=str(self.run_dir / "checkpoint") if cfg.run.checkpoint_every else "",
            control_token=self.control_token, topics=list(self.plan.topics),
            strict_order=self.strict_order, epoch=self.epoch)

    def worker_spec_at(self, wname: str, cut: int) -> WorkerSpec:
        """Worker ``wname`` restarted from this run's own checkpoint ``cut`` (afresh at 0, and for
        a stage that saved no state there)."""
        spec = self.worker_spec(wname)
        spec.resume_states = {}
        for s in spec.stages:
            path = cut_dir(self.run_dir / "checkpoint", cut) / f"{s.name}.state"
            if cut > 0 and path.exists():
                spec.resume_states[s.name] = str(path)
        return spec

    def source_spec(self, start_frame: int = 0) -> SourceRunSpec:
        src = self.cfg.source
        listen, connect = self.links("source")
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
            expected_peers=len(self.order) - 1, wait_topics=list(self.plan.consumed_source_topics),
            control_token=self.control_token, topics=list(self.plan.topics), epoch=self.epoch,
            camera_log_s=src.camera_log_s, camera_log_frames=src.camera_log_frames)

    def meta(self) -> dict[str, Any]:
        """What the report says about the run's set-up."""
        run = self.cfg.run
        return {"topology": run.topology, "mode": run.mode, "pipeline": run.pipeline, "run": self.name,
                "rate": self.cfg.source.rate, "final_topic": self.plan.final_topic}

    def workers(self) -> dict[str, list[str]]:
        """Every worker of the run with the stages it hosts."""
        return {w: [s.name for s in specs] for w, specs in self.groups.items()}

    def monitor_spec(self) -> MonitorSpec:
        listen, connect = self.links("monitor")
        return MonitorSpec(run=self.run_id, run_dir=str(self.run_dir), final_topic=self.plan.final_topic,
                           entry_stages=self.plan.entry_stages, workers=self.workers(), meta=self.meta(),
                           listen=listen, connect=connect, shm=self.cfg.bus.shm, live=self.cfg.run.live,
                           control_token=self.control_token, topics=list(self.plan.topics),
                           trace=self.trace_path, started=self.t_start)

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
