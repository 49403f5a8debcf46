"""One run over several hosts: each host's supervisor runs its share of the stage workers.

``neoslam run --stages A,B --run-id ID --connect tcp/HOST:7447`` on one machine and
``neoslam run --stages rest --run-id ID --connect tcp/HOST:7447`` on another make one run: the
stages of both exchange their topics through a zenoh router that both supervisors reach. Inside a
host nothing changes; between hosts only the supervisors' routers are linked (zenoh routes between
the peers of linked routers, not between peers that merely share a router). The host that runs the
pipeline's last stage (the primary) runs the monitor, ends the run and stops the other hosts'
processes with the run's ``stop`` control messages; the source runs on the host that names
``source`` in its ``--stages`` (a camera on the robot), else on the primary. ``rest`` takes every
worker no other host announced (liveliness tokens ``neoslam/<run>/part/...``). A host's share is
the workers it runs (and the source, the monitor where it runs them); what the hosts tell each
other, and how a lossless run survives a lost link: share_recovery.py.
Details: docs/hosts.md, "One run, stages on several hosts".
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from .bus import key_for, open_session
from .checkpoint import StateFormatError, latest_complete_cut
from .config import RunConfig
from .node import NodeSpec
from .report import write_report
from .share_recovery import STATE_FILE, ShareRecovery
from .topology import CONTROL_TOKEN_ENV, PipelinePlan, RunError, RunResult, Supervisor, check_cut, run_plan

log = logging.getLogger("neoslam.share")

#: a ``rest`` host waits this long after the first announcement of another host for further ones
SETTLE_S = 2.0


def parse_stages(text: str) -> list[str]:
    """``A,B`` -> ["A", "B"]; ``A,B,source``: the source here too; ``rest`` -> ["rest"] (the
    CLI's --stages)."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ValueError("--stages needs stage names (A,B,...), 'source' or 'rest'")
    if "rest" in names and len(names) > 1:
        raise ValueError("--stages rest takes no other names")
    return names


def check_selection(groups: dict[str, list[NodeSpec]], stages: list[str]) -> list[str]:
    """The workers of ``stages`` in the plan's order (``source`` is no worker); a clear error for
    a name that is no worker."""
    if stages == ["rest"]:
        return []
    stages = [n for n in stages if n != "source"]
    hosted_by = {s.name: w for w, specs in groups.items() for s in specs}
    unknown = [n for n in stages if n not in hosted_by]
    if unknown:
        raise RunError(f"--stages: unknown stage(s) {unknown}; this pipeline's stages: {list(groups)}")
    guests = [n for n in stages if hosted_by[n] != n]
    if guests:
        raise RunError(f"--stages: {guests} run in the process of {[hosted_by[n] for n in guests]}; "
                       f"name that stage instead")
    return [w for w in groups if w in stages]


class ShareSupervisor(Supervisor):
    """The supervisor of one host's share of a run split over several hosts (module docstring):
    a supervisor whose layout holds only this host's processes, linked to the others through its
    router, and which owns the :class:`ShareRecovery` that watches the other hosts."""

    def __init__(self, cfg: RunConfig, plan: PipelinePlan, run_dir: str | Path | None = None,
                 resume: str | Path | None = None, map_path: str | Path | None = None,
                 source_factory: str | None = None) -> None:
        if cfg.run.topology != "pipeline":
            raise RunError("--stages needs the pipeline topology (one process per stage)")
        if not cfg.run.run_id:
            raise RunError("--stages needs --run-id: every host of the run must use the same one")
        if not os.environ.get(CONTROL_TOKEN_ENV):
            # the source's host stops the other hosts' workers with control messages, which every
            # worker obeys only with the run's secret (bus.ControlGate): all hosts must share it
            raise RunError(f"--stages needs the run's control secret, the same on every host: set "
                           f"{CONTROL_TOKEN_ENV} (e.g. to the output of `openssl rand -hex 16`) in the "
                           f"environment of every host's `neoslam run`")
        # a share resumes its own stages only: the cut is chosen once they are known (_select_hosted)
        super().__init__(cfg, plan, run_dir, None, map_path, source_factory)
        self.stages = list(cfg.run.stages or [])
        layout = self.layout
        layout.hosted = check_selection(layout.groups, self.stages)
        layout.runs_source = "source" in self.stages
        layout.via_router = True
        layout.strict_order = self.lossless
        #: the run folder this host's share resumes from (``--resume``)
        self.resume_dir = Path(resume) if resume else None
        if self.resume_dir is not None and self.lossless:
            # a resumed host takes only messages of its own epoch until the others rolled back to it
            layout.epoch = int(time.time() * 1000)
        self._share_token: Any = None
        self.recovery = ShareRecovery(layout, self.children, self.collector, self.final, self.t_start)

    def run(self) -> RunResult:
        try:
            return super().run()
        except RunError as exc:
            if self.layout.is_primary:
                raise
            # this host's share has no report.json: its part.json says what happened here
            raise RunError(str(exc).replace(str(self.run_dir / "report.json"), str(self.run_dir / "part.json"))) \
                from None

    # ------------------------------------------------------------------ which workers run here
    def _announced(self) -> dict[str, list[str]]:
        """Processes announced by the hosts of this run on the bus (token key -> its names)."""
        out = {}
        for reply in self.session.liveliness().get(key_for(self.run_id, "part/*"), timeout=1.0):
            try:
                key = str(reply.ok.key_expr)
            except Exception:
                continue
            out[key] = [w for w in key.rsplit("/", 1)[-1].split(",") if w]
        return out

    def _select_hosted(self) -> None:
        layout, children = self.layout, self.children
        if self.stages == ["rest"]:
            deadline = time.monotonic() + self.cfg.run.startup_timeout
            announced = self._announced()
            while not announced:
                if time.monotonic() > deadline or children.interrupts:
                    raise RunError(f"--stages rest: no other host of run {self.run_id} announced its "
                                   f"stages within {self.cfg.run.startup_timeout:.0f} s")
                time.sleep(0.3)
                announced = self._announced()
            time.sleep(SETTLE_S)
            announced = self._announced()
            elsewhere = {w for ws in announced.values() for w in ws}
            layout.hosted = [w for w in layout.groups if w not in elsewhere]
            if not layout.hosted:
                raise RunError(f"--stages rest: the other hosts run every stage already ({sorted(elsewhere)})")
        else:
            elsewhere = {w for ws in self._announced().values() for w in ws}
            clash = elsewhere & {*layout.hosted, *(["source"] if layout.runs_source else [])}
            if clash:
                raise RunError(f"stage(s) {sorted(clash)} already run on another host of run {self.run_id}")
        last = list(layout.groups)[-1]
        layout.is_primary = last in layout.hosted
        # the source runs where a host named it, else with the primary
        layout.runs_source = layout.runs_source or (layout.is_primary and "source" not in elsewhere)
        source = ["source"] if layout.runs_source else []
        layout.order = ["supervisor", *(["monitor"] if layout.is_primary else []), *layout.hosted, *source]
        label = ",".join([*layout.hosted, *source])
        self._share_token = self.session.liveliness().declare_token(key_for(self.run_id, "part/" + label))
        log.warning("run %s: this host runs %s%s%s", self.run_id, ", ".join(layout.hosted),
                    " and the source" if layout.runs_source else "", " with the monitor" if layout.is_primary else "")
        self._resume_share()
        self.recovery.start(self.session, label)

    def _resume_share(self) -> None:
        """``--resume``: this host's stages from the newest cut they all completed, and on the
        primary the figures of the run's earlier life."""
        if self.resume_dir is None:
            return
        layout = self.layout
        names = self.recovery.own_stages()
        layout.resume = self.resume_dir
        layout.resume_cut = latest_complete_cut(self.resume_dir / "checkpoint", names)
        if layout.resume_cut is None:
            log.warning("run %s: no complete checkpoint of %s in %s: these stages start afresh",
                        self.run_id, names, self.resume_dir)
        else:
            check_cut(self.resume_dir / "checkpoint", layout.resume_cut, names)
        if layout.is_primary:
            try:
                self.recovery.restore(self.resume_dir / STATE_FILE)
            except StateFormatError as exc:
                raise RunError(f"cannot resume: {exc}") from None

    def _resume_frame(self) -> int:
        """Before the first frame: the run's monitor is ready too, wherever it runs."""
        if not self.layout.is_primary:
            self.children.wait_ready(["monitor"], self.cfg.run.startup_timeout)
        return self.layout.resume_cut or 0

    # ------------------------------------------------------------------ the loops
    def _supervise(self) -> bool:
        return self._supervise_primary() if self.layout.is_primary else self._supervise_secondary()

    def _supervise_primary(self) -> bool:
        layout, children, recovery = self.layout, self.children, self.recovery
        src_done_at: float | None = None
        if self.resume_dir is not None and self.lossless:
            recovery.rollback("this host was resumed", fresh=True)
        stalled_since: float | None = None
        last_out = -1
        while True:
            time.sleep(0.2)
            if children.interrupts:
                return True
            recovery.persist()
            children.restart_crashed()
            children.restart_monitor()
            recovery.check_gone()
            if self.lossless:
                cause = recovery.rollback_cause(stalled_since)
                if cause:
                    recovery.rollback(cause)
                    src_done_at = stalled_since = None
                    continue
            src = self.collector.snapshot().get("source", {})
            proc = children.procs.get("source") if layout.runs_source else None
            if not src.get("done") and self._source_died(proc):
                return False
            done = bool(src.get("done")) and src.get("epoch", 0) == layout.epoch
            n_out = len(self.final.frames)
            if n_out != last_out:
                last_out, stalled_since = n_out, None
            elif stalled_since is None:
                stalled_since = time.monotonic()
            if src_done_at is None and done:
                src_done_at = time.monotonic()
            if src_done_at is None:
                continue
            waited = time.monotonic() - src_done_at
            if not self.lossless:
                if waited >= self.cfg.run.drain_s:
                    return False
                continue
            stages = layout.stage_names()
            if self.collector.quiet(stages, for_s=1.0, fresh_s=1.5) or (
                    self.collector.quiet(stages, for_s=1.0, fresh_s=1.5, check_transport=False)
                    and self._all_out(src)):
                return False
            if waited > 20 and self.collector.quiet(stages, for_s=10.0, fresh_s=1.5, check_transport=False):
                log.warning("pipeline idle but not every published message arrived; ending the run")
                return False

    def _all_out(self, src: dict[str, Any]) -> bool:
        doomed = set(src.get("doomed_frames") or [])
        with self.final.lock:
            return all(f in self.final.frames or f in doomed
                       for a, b in src.get("published_ranges") or [] for f in range(a, b + 1))

    def _supervise_secondary(self) -> bool:
        layout, children, recovery = self.layout, self.children, self.recovery
        while True:
            time.sleep(0.2)
            if children.interrupts:
                return True
            recovery.obey_commands()
            recovery.check_gone()
            if recovery.paused is not None:
                if recovery.replay_from is not None:
                    recovery.replay()
                else:
                    recovery.paused = None
                continue
            done = [w for w in layout.hosted if (p := children.procs.get(w)) is not None and not p.is_alive()
                    and p.exitcode == 0]  # stopped by the primary's control message
            src = children.procs.get("source")
            if self._source_died(src):
                return False
            source_done = src is None or (not src.is_alive() and src.exitcode == 0)
            if len(done) == len(layout.hosted) and source_done:
                return False
            children.restart_crashed(stopped=done)

    def _shutdown(self) -> None:
        """The primary stops a source that runs on another host first, as it stops its own; a
        real-time run then ends the other hosts' workers at once too."""
        children = self.children
        if self.layout.is_primary and self.recovery.link is not None:
            remote = self.recovery.remote()
            if "source" in remote:
                children.control("stop", "source")
                children.wait_remote_stopped(["source"], time.monotonic() + 10)
            if not self.lossless:
                for w in remote:
                    if w != "source":
                        children.control("stop", w)
                children.wait_remote_stopped([w for w in remote if w != "source"], time.monotonic() + 30)
        children.shutdown()

    # ------------------------------------------------------------------ report
    def _complete_report(self, interrupted: bool) -> dict[str, Any]:
        layout, children = self.layout, self.children
        self.recovery.stop()
        if self._share_token is not None:
            try:
                self._share_token.undeclare()
            except Exception:  # the session may be closed already
                pass
        if layout.is_primary:
            report = super()._complete_report(interrupted)
            report["hosted_here"] = list(layout.hosted)
            report.update(self.recovery.report(report))
            write_report(self.run_dir / "report.json", report)
            return report
        # part.json (its name and its "part" key are what the CLI and the viewer read)
        report = {"run": self.run_id, "part": list(layout.hosted), "source_here": layout.runs_source,
                  "restarts": dict(children.restarts), "restart_events": list(children.restart_events),
                  "interrupted": interrupted, "signal": children.last_signal if interrupted else None,
                  "failure": self.failure, "run_dir": str(self.run_dir), **self.recovery.summary()}
        tmp = self.run_dir / "part.json.tmp"
        tmp.write_text(json.dumps(report, indent=2))
        os.replace(tmp, self.run_dir / "part.json")
        return report


def run_share(cfg: RunConfig, plan: PipelinePlan, run_dir: str | Path | None = None,
              resume: str | Path | None = None, map_path: str | Path | None = None,
              source_factory: str | None = None) -> RunResult:
    """Run this host's share of ``plan`` (``cfg.run.stages``), or all of it when none is selected;
    ``source_factory`` builds the run's source (on the host that runs it)."""
    if not cfg.run.stages:
        return run_plan(cfg, plan, run_dir, resume, map_path, source_factory)
    return ShareSupervisor(cfg, plan, run_dir, resume, map_path, source_factory).run()


def serve_router(listen: list[str], connect: list[str] | None = None, duration: float | None = None) -> None:
    """``neoslam router``: a zenoh router (scouting off) that the supervisors of a split run link
    to; runs until Ctrl-C or ``duration`` seconds. ``bus.zenoh_config`` settings (TLS, access
    control) come through the NEOSLAM_ZENOH_CONFIG variable, as for the runs."""
    session = open_session(listen=listen, connect=list(connect or []), mode="router")
    t_end = None if duration is None else time.monotonic() + duration
    try:
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
