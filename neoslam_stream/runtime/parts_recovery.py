"""How the hosts of a split run watch each other and get over a link that failed.

Mixed into parts.PartSupervisor. Every supervisor beats a heartbeat (hostlink.py) from a thread of
its own; a host silent for ``run.host_timeout`` is gone, and the other side ends its share with one
line naming what is missing. **Lossless** runs never process a frame out of order: every worker
takes its inputs strictly as their producer sent them (bus.InputQueue ``strict``), so samples a
link lost leave a hole, not a wrong map. The primary then rolls the whole run back: every host
restarts its workers from the newest checkpoint cut all hosts hold (0 without checkpoints), in a
new epoch (nothing an old process still sends is taken), and the source replays from that frame;
the recorder skips the rows it already wrote. Triggers: a hole, the primary resumed (``--resume``),
another host started again, a pipeline stalled after an outage with messages missing.
**Real-time** runs roll nothing back: lost frames are counted by cause (loss.py), outages named.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from .checkpoint import cut_dir, latest_complete_cut
from .collector import union_ranges
from .files import write_atomic
from .hostlink import HostLink
from .loss import loss_by_cause, to_ranges, useful_stages
from .plan import RunError
from .procs import source_entry, worker_entry

log = logging.getLogger("neoslam.parts")

#: a lossless pipeline that did not move this long after an outage lost its tail: roll back
STALL_S = 2.0
#: the primary saves what a resumed primary needs (frames done, figures of earlier lives) this often
PERSIST_S = 1.0
STATE_FILE = "parts_state.json"


class PartRecovery:
    """Heartbeats, host loss, rollbacks and the extra figures of a split run (module docstring)."""

    # ------------------------------------------------------------------ set-up
    def init_recovery(self) -> None:
        self.epoch = 0
        self.rollbacks: list[dict[str, Any]] = []
        self.paused: int | None = None  # a secondary host rolling back (its epoch)
        self.ready_epoch = 0  # the epoch this host's workers are ready in (heartbeat "ready")
        self._replay_from: int | None = None
        self.link: HostLink | None = None
        self.label = ""
        self._beating = threading.Event()
        self._persisted_at = 0.0
        self._cut_cache: tuple[float, int | None] = (0.0, None)
        self._outages_handled = 0
        if self.part_resume is not None and self.lossless:
            # a resumed host takes only messages of its own epoch until the others rolled back to it
            self.epoch = int(time.time() * 1000)

    def start_recovery(self) -> None:
        """Once this host's share is known: resume its stages, restore the figures, beat."""
        if self.part_resume is not None:
            names = self._own_stages()
            self.resume = self.part_resume
            self.resume_cut = latest_complete_cut(self.part_resume / "checkpoint", names)
            if self.resume_cut is None:
                log.warning("run %s: no complete checkpoint of %s in %s: these stages start afresh",
                            self.run_id, names, self.part_resume)
            if self.is_primary:
                self._restore(self.part_resume / STATE_FILE)
        self.link = HostLink(self.session, self.run_id, self.label, self.control_token, self.t_start)
        threading.Thread(target=self._beat_loop, name="heartbeat", daemon=True).start()

    def _own_stages(self) -> list[str]:
        return [s.name for w in self.hosted for s in self.groups[w]]

    def _beat_loop(self) -> None:
        while not self._beating.wait(0.05):
            try:
                self.link.beat({"stages": list(self.hosted), "source": self.runs_source,
                                "primary": self.is_primary, "epoch": self.epoch, "ready": self.ready_epoch,
                                "cut": self._newest_cut()})
            except Exception as exc:  # the session closed under us at the end
                log.debug("heartbeat: %s", exc)

    def _newest_cut(self) -> int | None:
        """The newest checkpoint cut all of this host's stages completed (read at most once a second)."""
        at, cut = self._cut_cache
        if time.monotonic() - at > 1.0:
            cut = latest_complete_cut(self.run_dir / "checkpoint", self._own_stages())
            self._cut_cache = (time.monotonic(), cut)
        return cut

    def worker_spec(self, wname: str) -> Any:
        spec = super().worker_spec(wname)
        spec.strict_order = self.lossless
        spec.epoch = self.epoch
        return spec

    def source_spec(self, start_frame: int = 0) -> Any:
        spec = super().source_spec(start_frame)
        spec.epoch = self.epoch
        return spec

    # ------------------------------------------------------------------ the loops
    def _supervise(self) -> bool:
        return self._supervise_primary() if self.is_primary else self._supervise_secondary()

    def stop_recovery(self) -> None:
        """No more heartbeats (the run's processes are stopped: this host's share is over)."""
        self._beating.set()

    def _gone(self) -> None:
        """One line and the end of this host's share when another host has been silent too long."""
        for label, silent in self.link.silent().items():
            if silent < self.cfg.run.host_timeout:
                continue
            peer = self.link.peer(label) or {}
            what = list(peer.get("stages") or []) + (["the source"] if peer.get("source") else []) + \
                (["the monitor"] if peer.get("primary") else [])
            raise RunError(f"run {self.run_id}: host {label!r} silent for {silent:.0f} s (link down or host "
                           f"dead); ending this host's share: missing {', '.join(what) or label}")

    def _supervise_primary(self) -> bool:
        src_done_at: float | None = None
        if self.part_resume is not None and self.lossless:
            self._rollback("this host was resumed", fresh=True)
        stalled_since: float | None = None
        last_out = -1
        while True:
            time.sleep(0.2)
            if self.interrupts:
                return True
            self._persist()
            self._restart_crashed()
            self._restart_monitor()
            self._gone()
            if self.lossless:
                cause = self._rollback_cause(stalled_since)
                if cause:
                    self._rollback(cause)
                    src_done_at = stalled_since = None
                    continue
            src = self.collector.snapshot().get("source", {})
            proc = self.procs.get("source") if self.runs_source else None
            if proc is not None and not proc.is_alive() and proc.exitcode not in (0, None) and not src.get("done"):
                err = self.run_dir / "source_error.txt"
                self.source_failure = (err.read_text().strip() if err.exists()
                                       else f"the source process died with exit code {proc.exitcode}")
                return False
            done = bool(src.get("done")) and src.get("epoch", 0) == self.epoch
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
            stages = self._stage_names()
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
        while True:
            time.sleep(0.2)
            if self.interrupts:
                return True
            for cmd in self.link.take_commands():
                self._obey(cmd)
            self._gone()
            if self.paused is not None:
                if self._replay_from is not None:
                    self._replay()
                else:
                    self.paused = None
                continue
            done = [w for w in self.hosted if (p := self.procs.get(w)) is not None and not p.is_alive()
                    and p.exitcode == 0]  # stopped by the primary's control message
            src = self.procs.get("source")
            if src is not None and not src.is_alive() and src.exitcode not in (0, None):
                err = self.run_dir / "source_error.txt"
                self.source_failure = (err.read_text().strip() if err.exists()
                                       else f"the source process died with exit code {src.exitcode}")
                return False
            source_done = src is None or (not src.is_alive() and src.exitcode == 0)
            if len(done) == len(self.hosted) and source_done:
                return False
            self._restart_crashed(stopped=done)

    def _shutdown(self) -> None:
        """The primary stops a source that runs on another host first, as it stops its own; a
        real-time run then ends the other hosts' workers at once too."""
        if self.is_primary and self.link is not None:
            remote = self._remote()
            if "source" in remote:
                self._control("stop", "source")
                self._wait_remote_stopped(["source"], time.monotonic() + 10)
            if not self.lossless:
                for w in remote:
                    if w != "source":
                        self._control("stop", w)
                self._wait_remote_stopped([w for w in remote if w != "source"], time.monotonic() + 30)
        super()._shutdown()

    # ------------------------------------------------------------------ rollback (lossless)
    def _remote(self) -> list[str]:
        """The processes of the run that other hosts run."""
        return [w for w in self.groups if w not in self.hosted] + ([] if self.runs_source else ["source"])

    def _rollback_cause(self, stalled_since: float | None) -> str | None:
        for name, st in self.collector.snapshot().items():
            if st.get("holes") and st.get("epoch", 0) == self.epoch:
                topic, (last, prev, frame) = next(iter(st["holes"].items()))
                return f"{name} missed {topic} after frame {last} (next came frame {frame})"
        if len(self.link.restarted) > getattr(self, "_restarts_handled", 0):
            self._restarts_handled = len(self.link.restarted)
            return f"host {self.link.restarted[-1]['host']} was started again"
        outages = self.link.all_outages()
        if stalled_since is not None and len(outages) > self._outages_handled:
            # counted from the end of the outage: what a link held back may still be coming
            ended = max(o["end_wall"] for o in outages)
            since = max(stalled_since, time.monotonic() - (time.time() - ended))
            lost = self._not_received()
            if time.monotonic() - since > STALL_S and lost:
                return f"no progress for {STALL_S:.0f} s after an outage, {lost} never arrived"
        return None

    def _not_received(self) -> str | None:
        """A topic whose messages of this epoch were put and never taken (the current lives'
        counts, all of this epoch), as ``topic (n of m)``; None when everything arrived."""
        with self.collector.lock:
            raw = {k: dict(v) for k, v in self.collector.raw.items()}
        if any(st.get("epoch", 0) != self.epoch for st in raw.values() if "epoch" in st):
            return None
        published: dict[str, int] = {}
        for st in raw.values():
            for topic, n in (st.get("published") or {}).items():
                published[topic] = published.get(topic, 0) + int(n)
        src = raw.get("source", {})
        published["image"] = published.get("image", 0) + int(src.get("frames_in", 0))
        published["odom"] = published.get("odom", 0) + int(src.get("odom", 0))
        for st in raw.values():
            for topic, inp in (st.get("inputs") or {}).items():
                if int(inp.get("received", 0)) < published.get(topic, 0):
                    return f"{topic} ({inp.get('received', 0)} of {published[topic]})"
        return None

    def _kill(self, names: list[str]) -> None:
        for n in names:
            p = self.procs.get(n)
            if p is not None and p.is_alive():
                p.kill()
                p.join(10)

    def _spec_at(self, wname: str, cut: int) -> Any:
        spec = self.worker_spec(wname)
        spec.resume_states = {}
        for s in spec.stages:
            path = cut_dir(self.run_dir / "checkpoint", cut) / f"{s.name}.state"
            if cut > 0 and path.exists():
                spec.resume_states[s.name] = str(path)
        return spec

    def _restart_at(self, cut: int) -> None:
        """This host's workers from ``cut`` (afresh at 0), in the run's current epoch."""
        for w in self.hosted:
            self._start(w, worker_entry, self._spec_at(w, cut))
        self._wait_ready(list(self.hosted), self.cfg.run.startup_timeout)
        self.ready_epoch = self.epoch

    def _peers_ready(self, epoch: int) -> bool:
        peers = [p for p in (self.link.peer(lb) for lb in self.link.silent()) if p]
        return bool(peers) and all(p.get("ready") == epoch for p in peers)

    def _rollback(self, cause: str, fresh: bool = False) -> None:
        """Roll the whole run back to the newest cut every host holds (module docstring); every
        host restarts its workers at once (the new epoch keeps what old processes still send
        out), the source replays once all are ready. ``fresh``: this host's workers were just
        started from the cut (a resumed host)."""
        t0 = time.time()
        log.warning("run %s: rolling back (%s)", self.run_id, cause)
        if fresh:
            cut = self.resume_cut or 0
        else:
            cuts = [self._newest_cut()] + [p.get("cut") for p in (self.link.peer(lb) for lb in self.link.silent()) if p]
            cut = 0 if any(c is None for c in cuts) else int(min(cuts))
            self.epoch = int(time.time() * 1000)
        epoch = self.epoch
        self.link.command("rollback", epoch=epoch, cut=cut)
        sent = time.monotonic()
        if not fresh:
            self._kill([*self.hosted, *(["source"] if self.runs_source else [])])
            self._restart_at(cut)
        self.ready_epoch = epoch
        while not self._peers_ready(epoch):  # the other hosts restart theirs from the same cut
            if time.monotonic() - sent > 2.0:
                self.link.command("rollback", epoch=epoch, cut=cut)
                sent = time.monotonic()
            self._gone()
            time.sleep(0.1)
        if self.runs_source:
            self._kill(["source"])
            self._wait_ready(list(self.groups), self.cfg.run.startup_timeout)
            self._start("source", source_entry, self.source_spec(cut))
        self._outages_handled = len(self.link.all_outages())
        self.rollbacks.append({"time_s": round(t0 - self.t_start, 3), "cause": cause, "cut": cut,
                               "took_s": round(time.time() - t0, 3)})
        log.warning("run %s: rolled back to frame %d in %.1f s", self.run_id, cut, time.time() - t0)

    def _obey(self, cmd: dict[str, Any]) -> None:
        """A secondary host: the primary's rollback; its source replays once the primary is ready."""
        epoch = int(cmd.get("epoch") or 0)
        if cmd.get("command") != "rollback" or epoch <= self.epoch:
            return
        t0 = time.time()
        self.paused = epoch
        self._kill([*self.hosted, "source"])
        self.epoch, cut = epoch, int(cmd.get("cut") or 0)
        self._restart_at(cut)
        self._replay_from = cut if self.runs_source else None
        self.rollbacks.append({"time_s": round(t0 - self.t_start, 3), "cut": cut,
                               "took_s": round(time.time() - t0, 3)})

    def _replay(self) -> None:
        """A secondary host with the source: start it again once every host is ready."""
        primary = next((p for p in (self.link.peer(lb) for lb in self.link.silent()) if p and p.get("primary")), None)
        if primary is None or primary.get("ready") != self.epoch:
            return
        if set(self.groups) - self._alive_tokens():
            return
        self._start("source", source_entry, self.source_spec(self._replay_from))
        self._replay_from = None
        self.paused = None

    # ------------------------------------------------------------------ what a resumed primary needs
    def _persist(self) -> None:
        if time.monotonic() - self._persisted_at < PERSIST_S:
            return
        self._persisted_at = time.monotonic()
        c = self.collector
        with c.lock:
            state = {"raw": c.raw, "earlier": c.earlier, "lives": c.lives, "spans": c.spans}
            state = json.loads(json.dumps(state, default=str))
        with self.final.lock:
            final = to_ranges(self.final.frames)
        state.update({"final": final, "outages": self.link.all_outages(), "rollbacks": self.rollbacks,
                      "restart_events": self.restart_events})
        try:
            write_atomic(self.run_dir / STATE_FILE, json.dumps(state).encode())
        except OSError as exc:
            log.debug("%s not written: %s", STATE_FILE, exc)

    def _restore(self, path: Path) -> None:
        try:
            state = json.loads(path.read_text())
        except (OSError, ValueError):
            return
        c = self.collector
        with c.lock:
            c.raw, c.earlier = state.get("raw", {}), state.get("earlier", {})
            c.lives, c.spans = state.get("lives", {}), state.get("spans", {})
        with self.final.lock:
            for a, b in state.get("final", []):
                self.final.frames.update(range(a, b + 1))
        self.rollbacks = list(state.get("rollbacks", []))
        self.restart_events = list(state.get("restart_events", []))
        self._earlier_outages = list(state.get("outages", []))

    # ------------------------------------------------------------------ report
    def _outages(self) -> list[dict[str, Any]]:
        seen, out = set(), []
        for o in [*getattr(self, "_earlier_outages", []), *self.link.all_outages()]:
            key = (o.get("seen_by"), o.get("host"), o.get("start_wall"))
            if key not in seen:
                seen.add(key)
                out.append(o)
        return sorted(out, key=lambda o: o.get("start_wall") or 0)

    def recovery_report(self, report: dict[str, Any]) -> dict[str, Any]:
        """report.json's split-run figures: hosts, outages, rollbacks, the loss by cause."""
        stats = self.collector.snapshot()
        src = stats.get("source", {})
        outages = self._outages()
        with self.final.lock:
            final = set(self.final.frames)
        spans = {k: list(v) for k, v in self.collector.spans.items()}
        loss = loss_by_cause(src, final, stats, spans, outages, int(report.get("frames_strided") or 0),
                             useful_stages(stats, self.plan.final_topic))
        hosts = {lb: {"stages": p.get("stages"), "source": p.get("source"), "primary": p.get("primary"),
                      "silent_s": round(s, 3)}
                 for lb, s in self.link.silent().items() if (p := self.link.peer(lb))}
        hosts[self.label] = {"stages": list(self.hosted), "source": self.runs_source, "primary": True}
        for o in outages:
            log.warning("run %s: link to %s out at %.1f s for %.1f s (seen by %s)", self.run_id, o["host"],
                        o["start_s"], o["length_s"], o["seen_by"])
        if report.get("frames_lost"):
            log.warning("run %s: frames lost by cause: %s", self.run_id,
                        ", ".join(f"{k} {v}" for k, v in loss["by_cause"].items() if v))
        return {"hosts": hosts, "outages": outages, "rollbacks": list(self.rollbacks), "epoch": self.epoch,
                "loss_by_cause": loss["by_cause"], "loss_frames": loss["frames"],
                "published_ranges": union_ranges(src.get("published_ranges") or [])}

    def recovery_part(self) -> dict[str, Any]:
        return {"label": self.label, "outages": self.link.all_outages() if self.link else [],
                "rollbacks": list(self.rollbacks), "epoch": self.epoch}
