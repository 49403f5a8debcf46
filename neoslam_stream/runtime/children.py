"""The run's child processes: started, awaited, commanded, restarted and stopped in order.

Part of the supervisor (mixed into :class:`~neoslam_stream.runtime.topology.Supervisor`): each
child is a ``spawn`` process that dies with the supervisor; readiness is a liveliness token on the
bus; commands go over the run's control topic with its secret. A crashed worker is restarted from
its stages' newest checkpointed state, a dead monitor started again, both bounded and reported.
The stop is ordered: the source, then the workers (they flush), the watchers, the monitor.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Collection
from typing import Any

from .bus import key_for
from .checkpoint import latest_stage_state
from .messages import Message, encode
from .plan import RunError
from .procs import monitor_entry, worker_entry
from .worker import EXIT_STATE_REFUSED

log = logging.getLogger("neoslam.topology")


class ChildProcesses:
    """The process part of the supervisor (it reads the supervisor's config, groups, specs,
    session and collector)."""

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
                    if p.exitcode == EXIT_STATE_REFUSED:
                        raise RunError(f"process {n!r} refused the saved state it was given (the error line "
                                       "above says why): run with the config the state was made with, "
                                       "or start afresh")
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
            # the source and the stages stop together: a lossless run comes here drained (the
            # source has nothing left in flight), and a live run ends at once (what is still in
            # flight when the camera stops is lost; its other hosts' workers were stopped already)
            own_source = ["source"] if "source" in self.procs else []
            if self.lossless:
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

    def _wait_remote_stopped(self, names: list[str], deadline: float) -> None:
        """Wait until the workers ``names`` of other hosts have withdrawn their liveliness tokens."""
        while names and time.monotonic() < deadline:
            if not set(names) & self._alive_tokens():
                return
            time.sleep(0.2)
