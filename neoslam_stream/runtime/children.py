"""The run's child processes on this host: started, awaited, commanded, restarted and stopped.

Each child is a ``spawn`` process that dies with the supervisor; readiness is a liveliness token on
the bus; commands go over the run's control topic with its secret. A crashed worker is restarted
from its stages' newest checkpointed state, a dead monitor started again, both bounded and
reported. The stop is ordered: the source, then the workers (they flush), the watchers, the
monitor. The first Ctrl-C asks the supervisor for that stop; a second kills every child at once.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import time
from collections.abc import Collection
from typing import Any

from .bus import key_for
from .checkpoint import latest_stage_state
from .collector import StatsCollector
from .layout import RunLayout
from .messages import Message, encode
from .plan import RunError
from .procs import monitor_entry, worker_entry
from .worker import EXIT_STATE_REFUSED

log = logging.getLogger("neoslam.topology")


class Children:
    """This host's processes of a run (module docstring). The supervisor owns one and gives it the
    layout (which processes run here, their specs), the collector (the source's frame count at a
    restart) and the run's start time; ``session`` is the supervisor's, set once it is open.
    ``restarts`` and ``restart_events`` are what the report says about restarts, ``stopped_by_force``
    the processes that did not stop in time at the end (their final state may be missing)."""

    def __init__(self, layout: RunLayout, collector: StatsCollector, t_start: float) -> None:
        self.layout = layout
        self.collector = collector
        self.t_start = t_start
        self.ctx = mp.get_context("spawn")
        self.session: Any = None
        self.procs: dict[str, Any] = {}
        self.restarts: dict[str, int] = {}
        self.restart_events: list[dict[str, Any]] = []
        self.stopped_by_force: list[str] = []
        #: SIGINT/SIGTERM received, and the last one (the run's exit status names it)
        self.interrupts = 0
        self.last_signal: int | None = None
        self._monitor_given_up = False

    def start(self, name: str, target: Any, spec: Any) -> None:
        # the supervisor's pid: the child stops when this process dies (procs.follow_parent)
        p = self.ctx.Process(target=target, args=(spec, os.getpid(), self.layout.scheduling(name)),
                             name=f"neoslam-{name}", daemon=False)
        p.start()
        self.procs[name] = p

    def alive_tokens(self) -> set[str]:
        """The processes of the run (on every host) that announced readiness."""
        names = set()
        for reply in self.session.liveliness().get(key_for(self.layout.run_id, "alive/*"), timeout=1.0):
            try:
                names.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
            except Exception:
                continue
        return names

    def wait_ready(self, names: list[str], timeout: float) -> None:
        """Until every process of ``names`` announced readiness; a worker of this host that died
        meanwhile is restarted (bounded), one that refused its saved state ends the run."""
        max_restarts = self.layout.cfg.run.max_restarts
        deadline = time.monotonic() + timeout
        while True:
            alive = self.alive_tokens()
            if all(n in alive for n in names):
                return
            for n in names:
                p = self.procs.get(n)
                if p is not None and not p.is_alive() and not self.interrupts:  # Ctrl-C: no restart
                    if p.exitcode == EXIT_STATE_REFUSED:
                        raise RunError(f"process {n!r} refused the saved state it was given (the error line "
                                       "above says why): run with the config the state was made with, "
                                       "or start afresh")
                    if n in self.layout.groups and self.restarts.get(n, 0) < max_restarts:
                        self.restart(n, p.exitcode)
                        continue
                    raise RunError(f"process {n!r} exited with code {p.exitcode} during start-up "
                                   f"(see its log above)")
            if time.monotonic() > deadline or self.interrupts:
                missing = [n for n in names if n not in alive]
                raise RunError(f"processes not ready after {timeout:.0f} s: {missing}")
            time.sleep(0.2)

    def control(self, command: str, target: str | None = None, **extra: Any) -> None:
        """A command on the run's control topic, with the run's secret (``target``: one process)."""
        data = {"command": command, "token": self.layout.control_token, **extra}
        if target is not None:
            data["target"] = target
        self.session.put(key_for(self.layout.run_id, "control"), encode(Message("control", 0, time.time(), data)))

    def on_signal(self, signum: int, _frame: Any) -> None:
        self.interrupts += 1
        self.last_signal = signum
        if self.interrupts >= 2:
            log.warning("second interrupt: killing every process of the run")
            for p in self.procs.values():
                if p.is_alive():
                    p.kill()

    def restart_crashed(self, stopped: Collection[str] = ()) -> None:
        """Restart the hosted workers that died (bounded); ``stopped``: workers that ended on
        purpose (a split run's primary stopped them), not to be restarted."""
        run = self.layout.cfg.run
        for w in self.layout.hosted:
            p = self.procs.get(w)
            if w in stopped or p is None or p.is_alive():
                continue
            n = self.restarts.get(w, 0)
            if n >= run.max_restarts:
                raise RunError(f"worker {w!r} died (exit code {p.exitcode}) and was already restarted "
                               f"{n} times; giving up")
            self.restart(w, p.exitcode)
            self.wait_ready([w], run.startup_timeout)

    def restart_monitor(self) -> None:
        """A dead monitor is started again (bounded, reported like a worker's restart). Its figures
        are not lost: the supervisor follows the stats and the final topic itself."""
        p = self.procs.get("monitor")
        if p is None or p.is_alive():
            return
        n = self.restarts.get("monitor", 0)
        max_restarts = self.layout.cfg.run.max_restarts
        if n >= max_restarts:
            if not self._monitor_given_up:
                self._monitor_given_up = True
                log.error("the monitor died (exit code %s) and was already restarted %d times; the run "
                          "goes on without it (the supervisor still writes the report)", p.exitcode, n)
            return
        log.warning("the monitor died with exit code %s; restarting (%d/%d)", p.exitcode, n + 1, max_restarts)
        self.restarts["monitor"] = n + 1
        self.restart_events.append({"worker": "monitor", "time_s": round(time.time() - self.t_start, 3),
                                    "exit_code": p.exitcode, "resumed_from_cut": None,
                                    "frames_in_at_restart": self.collector.snapshot().get("source", {})
                                    .get("frames_in")})
        self.start("monitor", monitor_entry, self.layout.monitor_spec())

    def restart(self, w: str, exitcode: int | None) -> None:
        """Start worker ``w`` again, with each stage's newest checkpointed state when there is one."""
        n = self.restarts.get(w, 0)
        log.warning("worker %s died with exit code %s; restarting (%d/%d)", w, exitcode, n + 1,
                    self.layout.cfg.run.max_restarts)
        self.restarts[w] = n + 1
        spec = self.layout.worker_spec(w)
        cuts = []
        for s in spec.stages:
            path = latest_stage_state(self.layout.run_dir / "checkpoint", s.name)
            if path is not None:
                spec.resume_states[s.name] = str(path)
                cuts.append(int(path.parent.name))
        src = self.collector.snapshot().get("source", {})
        # what the report says about the crash: when, how, which state came back, and the source's
        # frame count then (the frames lost in between are those the stage never saw)
        self.restart_events.append({
            "worker": w, "time_s": round(time.time() - self.t_start, 3), "exit_code": exitcode,
            "resumed_from_cut": min(cuts) if cuts else None, "frames_in_at_restart": src.get("frames_in")})
        self.start(w, worker_entry, spec)

    def kill(self, names: list[str]) -> None:
        """Kill the processes ``names`` at once (a rollback replaces them)."""
        for n in names:
            p = self.procs.get(n)
            if p is not None and p.is_alive():
                p.kill()
                p.join(10)

    def shutdown(self) -> None:
        """Stop the source, then the workers (they flush), then the monitor; nothing left behind."""
        layout = self.layout

        def stop(names: list[str], timeout: float) -> None:
            for n in names:
                self.control("stop", n)
            deadline = time.monotonic() + timeout
            for n in names:
                p = self.procs.get(n)
                if p is None:
                    continue
                p.join(max(0.1, deadline - time.monotonic()))
                if p.is_alive():
                    log.warning("%s did not stop in time; terminating", n)
                    self.stopped_by_force.append(n)
                    p.terminate()
                    p.join(5)
                if p.is_alive():
                    p.kill()
                    p.join(2)
            self.wait_remote_stopped([n for n in names if n in layout.groups and n not in layout.hosted],
                                     deadline)

        try:
            # the primary of a run split over hosts stops the other hosts' workers too, in order
            workers = [w for w in layout.groups
                       if w in self.procs or (layout.is_primary and w not in layout.hosted)]
            # processes that host a watcher (the recorder) go last: what the others publish up to
            # their end (a stage's last frame, the pose cells' final actions) is still recorded
            watchers = [w for w in workers if any(s.observer for s in layout.groups[w])]
            others = [w for w in workers if w not in watchers]
            # the source and the stages stop together: a lossless run comes here drained (the
            # source has nothing left in flight), and a live run ends at once (what is still in
            # flight when the camera stops is lost; its other hosts' workers were stopped already)
            own_source = ["source"] if "source" in self.procs else []
            if layout.lossless:
                stop(own_source + others, 60)
            else:
                stop(own_source + [n for n in others if n in self.procs], 60)
            stop(watchers, 60)
            if "monitor" in self.procs:
                stop(["monitor"], 30)
        finally:
            for p in self.procs.values():
                if p.is_alive():
                    p.kill()
                    p.join(2)

    def wait_remote_stopped(self, names: list[str], deadline: float) -> None:
        """Wait until the workers ``names`` of other hosts have withdrawn their liveliness tokens."""
        while names and time.monotonic() < deadline:
            if not set(names) & self.alive_tokens():
                return
            time.sleep(0.2)
