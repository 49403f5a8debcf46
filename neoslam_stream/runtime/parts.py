"""One run over several hosts: each host's supervisor runs only some of the stage workers.

``neoslam run --stages A,B --run-id ID --connect tcp/HOST:7447`` on one machine and
``neoslam run --stages rest --run-id ID --connect tcp/HOST:7447`` on another make one run: the
stages of both exchange their topics through a zenoh router that both supervisors reach. Inside a
host nothing changes; between hosts only the supervisors' routers are linked (zenoh routes between
the peers of linked routers, not between peers that merely share a router). The host that runs the
pipeline's last stage (the primary) also runs the source and the monitor and ends the run, stopping
the other hosts' workers with the run's ``stop`` control messages; the other hosts end when their
workers have stopped, or when the primary's monitor has been gone for ``PRIMARY_GONE_S``.
``rest`` takes every worker no other host announced (liveliness tokens ``neoslam/<run>/part/...``).
Details: docs/runtime.md, "One run, stages on several hosts".
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from .bus import key_for, open_session
from .topology import CONTROL_TOKEN_ENV, PipelinePlan, RunError, RunResult, Supervisor, run_plan

log = logging.getLogger("neoslam.parts")

#: a ``rest`` host waits this long after the first announcement of another host for further ones
SETTLE_S = 2.0
#: a host without the source ends its share when the run's monitor has been gone this long
PRIMARY_GONE_S = 30.0


def parse_stages(text: str) -> list[str]:
    """``A,B`` -> ["A", "B"]; ``rest`` -> ["rest"] (the CLI's --stages)."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ValueError("--stages needs stage names (A,B,...) or 'rest'")
    if "rest" in names and len(names) > 1:
        raise ValueError("--stages rest takes no other names")
    return names


def check_selection(groups: dict[str, list[Any]], stages: list[str]) -> list[str]:
    """The workers of ``stages`` in the plan's order; a clear error for a name that is no worker."""
    if stages == ["rest"]:
        return []
    hosted_by = {s.name: w for w, specs in groups.items() for s in specs}
    unknown = [n for n in stages if n not in hosted_by]
    if unknown:
        raise RunError(f"--stages: unknown stage(s) {unknown}; this pipeline's stages: {list(groups)}")
    guests = [n for n in stages if hosted_by[n] != n]
    if guests:
        raise RunError(f"--stages: {guests} run in the process of {[hosted_by[n] for n in guests]}; "
                       f"name that stage instead")
    return [w for w in groups if w in stages]


class PartSupervisor(Supervisor):
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
        super().__init__(cfg, plan, run_dir, resume, map_path, source_factory)
        self.stages = list(cfg.run.stages)
        self.hosted = check_selection(self.groups, self.stages)
        self._part_token: Any = None

    # ------------------------------------------------------------------ which workers run here
    def _announced(self) -> dict[str, list[str]]:
        """Workers announced by the parts of this run on the bus (token key -> its workers)."""
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
            clash = {w for ws in self._announced().values() for w in ws} & set(self.hosted)
            if clash:
                raise RunError(f"stage(s) {sorted(clash)} already run on another host of run {self.run_id}")
        last = list(self.groups)[-1]
        self.is_primary = last in self.hosted
        self.order = ["supervisor", *(["monitor"] if self.is_primary else []), *self.hosted,
                      *(["source"] if self.is_primary else [])]
        self._part_token = self.session.liveliness().declare_token(
            key_for(self.run_id, "part/" + ",".join(self.hosted)))
        log.warning("run %s: this host runs %s%s", self.run_id, ", ".join(self.hosted),
                    " with the source and the monitor" if self.is_primary else "")

    def _links(self, name: str) -> tuple[list[str], list[str]]:
        """Only this host's earlier processes: other hosts are reached through the supervisor's
        router (``bus.connect`` links the routers, not every process)."""
        i = self.order.index(name)
        return [self.endpoints[name], *self.cfg.bus.listen], [self.endpoints[n] for n in self.order[:i]]

    # ------------------------------------------------------------------ a host without the source
    def _supervise(self) -> bool:
        if self.is_primary:
            return super()._supervise()
        # the primary's monitor lives as long as the run: gone for PRIMARY_GONE_S, the run is over
        seen_at: float | None = None
        checked = 0.0
        while True:
            time.sleep(0.2)
            if self.interrupts:
                return True
            now = time.monotonic()
            if now - checked > 5.0:
                checked = now
                if "monitor" in self._alive_tokens():
                    seen_at = now
                elif seen_at is not None and now - seen_at > PRIMARY_GONE_S:
                    log.warning("run %s: the host with the source is gone (no monitor for %.0f s); "
                                "stopping the stages here", self.run_id, now - seen_at)
                    return False
            done = []
            for w in self.hosted:
                p = self.procs.get(w)
                if p is not None and not p.is_alive() and p.exitcode == 0:
                    done.append(w)  # stopped by the primary's control message
            if len(done) == len(self.hosted):
                return False
            self._restart_crashed(stopped=done)

    def _complete_report(self, interrupted: bool) -> dict[str, Any]:
        if self._part_token is not None:
            try:
                self._part_token.undeclare()
            except Exception:  # the session may be closed already
                pass
        if self.is_primary:
            report = super()._complete_report(interrupted)
            report["hosted_here"] = list(self.hosted)
            path = self.run_dir / "report.json"
            tmp = path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(report, indent=2))
            os.replace(tmp, path)
            return report
        report = {"run": self.run_id, "part": list(self.hosted), "restarts": dict(self.restarts),
                  "restart_events": list(self.restart_events), "interrupted": interrupted,
                  "signal": self.last_signal if interrupted else None, "run_dir": str(self.run_dir)}
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
