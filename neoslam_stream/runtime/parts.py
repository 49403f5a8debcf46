"""One run over several hosts: each host's supervisor runs only some of the stage workers.

``neoslam run --stages A,B --run-id ID --connect tcp/HOST:7447`` on one machine and
``neoslam run --stages rest --run-id ID --connect tcp/HOST:7447`` on another make one run: the
stages of both exchange their topics through a zenoh router that both supervisors reach. Inside a
host nothing changes; between hosts only the supervisors' routers are linked (zenoh routes between
the peers of linked routers, not between peers that merely share a router). The host that runs the
pipeline's last stage (the primary) runs the monitor, ends the run and stops the other hosts'
processes with the run's ``stop`` control messages; the source runs on the host that names
``source`` in its ``--stages`` (a camera on the robot), else on the primary. ``rest`` takes every
worker no other host announced (liveliness tokens ``neoslam/<run>/part/...``). What the hosts
tell each other, and how a lossless run survives a lost link: parts_recovery.py.
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
from .parts_recovery import PartRecovery
from .report import write_report
from .topology import CONTROL_TOKEN_ENV, PipelinePlan, RunError, RunResult, Supervisor, run_plan

log = logging.getLogger("neoslam.parts")

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


def check_selection(groups: dict[str, list[Any]], stages: list[str]) -> list[str]:
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


class PartSupervisor(PartRecovery, Supervisor):
    """The supervisor of one host's share of a run split over several hosts (module docstring)."""

    def __init__(self, cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
                 resume: str | Path | None = None, map_path: str | Path | None = None,
                 source_factory: str | None = None) -> None:
        if cfg.run.topology != "pipeline":
            raise RunError("--stages needs the pipeline topology (one process per stage)")
        if not getattr(cfg.run, "run_id", None):
            raise RunError("--stages needs --run-id: every host of the run must use the same one")
        if not os.environ.get(CONTROL_TOKEN_ENV):
            # the source's host stops the other hosts' workers with control messages, which every
            # worker obeys only with the run's secret (bus.ControlGate): all hosts must share it
            raise RunError(f"--stages needs the run's control secret, the same on every host: set "
                           f"{CONTROL_TOKEN_ENV} (e.g. to the output of `openssl rand -hex 16`) in the "
                           f"environment of every host's `neoslam run`")
        # a part resumes its own stages only: the cut is chosen once they are known (_select_hosted)
        super().__init__(cfg, plan, run_dir, None, map_path, source_factory)
        self.stages = list(cfg.run.stages)
        self.hosted = check_selection(self.groups, self.stages)
        self.runs_source = "source" in self.stages
        self.part_resume = Path(resume) if resume else None
        self._part_token: Any = None
        self.init_recovery()

    def run(self) -> RunResult:
        try:
            return super().run()
        except RunError as exc:
            if self.is_primary:
                raise
            # this host's share has no report.json: its part.json says what happened here
            raise RunError(str(exc).replace(str(self.run_dir / "report.json"), str(self.run_dir / "part.json"))) \
                from None

    # ------------------------------------------------------------------ which workers run here
    def _announced(self) -> dict[str, list[str]]:
        """Processes announced by the parts of this run on the bus (token key -> its names)."""
        out = {}
        for reply in self.session.liveliness().get(key_for(self.run_id, "part/*"), timeout=1.0):
            try:
                key = str(reply.ok.key_expr)
            except Exception:
                continue
            out[key] = [w for w in key.rsplit("/", 1)[-1].split(",") if w]
        return out

    def _select_hosted(self) -> None:
        if self.stages == ["rest"]:
            deadline = time.monotonic() + self.cfg.run.startup_timeout
            announced = self._announced()
            while not announced:
                if time.monotonic() > deadline or self.interrupts:
                    raise RunError(f"--stages rest: no other host of run {self.run_id} announced its "
                                   f"stages within {self.cfg.run.startup_timeout:.0f} s")
                time.sleep(0.3)
                announced = self._announced()
            time.sleep(SETTLE_S)
            announced = self._announced()
            elsewhere = {w for ws in announced.values() for w in ws}
            self.hosted = [w for w in self.groups if w not in elsewhere]
            if not self.hosted:
                raise RunError(f"--stages rest: the other hosts run every stage already ({sorted(elsewhere)})")
        else:
            elsewhere = {w for ws in self._announced().values() for w in ws}
            clash = elsewhere & {*self.hosted, *(["source"] if self.runs_source else [])}
            if clash:
                raise RunError(f"stage(s) {sorted(clash)} already run on another host of run {self.run_id}")
        last = list(self.groups)[-1]
        self.is_primary = last in self.hosted
        # the source runs where a host named it, else with the primary
        self.runs_source = self.runs_source or (self.is_primary and "source" not in elsewhere)
        self.order = ["supervisor", *(["monitor"] if self.is_primary else []), *self.hosted,
                      *(["source"] if self.runs_source else [])]
        self.label = ",".join([*self.hosted, *(["source"] if self.runs_source else [])])
        self._part_token = self.session.liveliness().declare_token(key_for(self.run_id, "part/" + self.label))
        log.warning("run %s: this host runs %s%s%s", self.run_id, ", ".join(self.hosted),
                    " and the source" if self.runs_source else "", " with the monitor" if self.is_primary else "")
        self.start_recovery()

    def _links(self, name: str) -> tuple[list[str], list[str]]:
        """Only this host's earlier processes: other hosts are reached through the supervisor's
        router (``bus.connect`` links the routers, not every process)."""
        i = self.order.index(name)
        return [self.endpoints[name], *self.cfg.bus.listen], [self.endpoints[n] for n in self.order[:i]]

    def _resume_frame(self) -> int:
        """Before the first frame: the run's monitor is ready too, wherever it runs."""
        if not self.is_primary:
            self._wait_ready(["monitor"], self.cfg.run.startup_timeout)
        return self.resume_cut or 0

    def _complete_report(self, interrupted: bool) -> dict[str, Any]:
        self.stop_recovery()
        if self._part_token is not None:
            try:
                self._part_token.undeclare()
            except Exception:  # the session may be closed already
                pass
        if self.is_primary:
            report = super()._complete_report(interrupted)
            report["hosted_here"] = list(self.hosted)
            report.update(self.recovery_report(report))
            write_report(self.run_dir / "report.json", report)
            return report
        report = {"run": self.run_id, "part": list(self.hosted), "source_here": self.runs_source,
                  "restarts": dict(self.restarts), "restart_events": list(self.restart_events),
                  "interrupted": interrupted, "signal": self.last_signal if interrupted else None,
                  "failure": getattr(self, "failure", None), "run_dir": str(self.run_dir),
                  **self.recovery_part()}
        tmp = self.run_dir / "part.json.tmp"
        tmp.write_text(json.dumps(report, indent=2))
        os.replace(tmp, self.run_dir / "part.json")
        return report


def run_part(cfg: Any, plan: PipelinePlan, run_dir: str | Path | None = None,
             resume: str | Path | None = None, map_path: str | Path | None = None,
             source_factory: str | None = None) -> RunResult:
    """Run this host's share of ``plan`` (``cfg.run.stages``), or all of it when none is selected;
    ``source_factory`` builds the run's source (on the host that runs it)."""
    if not getattr(cfg.run, "stages", None):
        return run_plan(cfg, plan, run_dir, resume, map_path, source_factory)
    return PartSupervisor(cfg, plan, run_dir, resume, map_path, source_factory).run()


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
