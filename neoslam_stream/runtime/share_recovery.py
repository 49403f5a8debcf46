"""How the hosts of a split run watch each other and get over a link that failed.

Every supervisor beats a heartbeat (hostlink.py) from a thread of its own; a host silent for
``run.host_timeout`` is gone, and the other side ends its share with one line naming what is
missing. **Lossless** runs never process a frame out of order: every worker takes its inputs
strictly as their producer sent them (bus.InputQueue ``strict``), so samples a link lost leave a
hole, not a wrong map. The primary then rolls the whole run back: every host restarts its workers
from the newest checkpoint cut all hosts hold (0 without checkpoints), in a new epoch (nothing an
old process still sends is taken), and the source replays from that frame; the recorder skips the
rows it already wrote. Triggers: a hole, the primary resumed (``--resume``), another host started
again, a pipeline stalled after an outage with messages missing. **Real-time** runs roll nothing
back: lost frames are counted by cause (loss.py), outages named.

The primary also keeps what a resumed primary needs (the figures of the run so far) in
``parts_state.json``, which begins with its format and version: one of another version, or
without one, is refused.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from .checkpoint import StateFormatError, latest_complete_cut
from .children import Children
from .collector import FinalTracker, StatsCollector, union_ranges
from .files import write_atomic
from .hostlink import HostLink
from .layout import RunLayout
from .loss import loss_by_cause, useful_stages
from .plan import RunError
from .procs import source_entry, worker_entry

log = logging.getLogger("neoslam.share")

#: a lossless pipeline that did not move this long after an outage lost its tail: roll back
STALL_S = 2.0
#: the primary saves what a resumed primary needs (frames done, figures of earlier lives) this often
PERSIST_S = 1.0
STATE_FILE = "parts_state.json"
#: what STATE_FILE holds, and the one version of it this build reads
STATE_FORMAT = "neoslam-share-state"
STATE_VERSION = 1


class ShareRecovery:
    """Heartbeats, host loss, rollbacks and the extra figures of one host's share of a split run
    (module docstring). The share supervisor owns one and gives it the run's layout (this host's
    processes, their specs, the epoch they start in), its child processes and the figures it
    follows (``collector``, ``final``); ``start`` links it to the other hosts."""

    def __init__(self, layout: RunLayout, children: Children, collector: StatsCollector, final: FinalTracker,
                 t_start: float) -> None:
        self.layout = layout
        self.children = children
        self.collector = collector
        self.final = final
        self.t_start = t_start
        self.rollbacks: list[dict[str, Any]] = []
        self.paused: int | None = None  # a secondary host rolling back (its epoch)
        self.ready_epoch = 0  # the epoch this host's workers are ready in (heartbeat "ready")
        self.replay_from: int | None = None
        self.link: HostLink | None = None
        self.label = ""
        self._beating = threading.Event()
        self._persisted_at = 0.0
        self._cut_cache: tuple[float, int | None] = (0.0, None)
        self._outages_handled = 0
        self._restarts_handled = 0
        #: outages a resumed primary's earlier life saw (from STATE_FILE)
        self._earlier_outages: list[dict[str, Any]] = []

    # ------------------------------------------------------------------ set-up
    def start(self, session: Any, label: str) -> None:
        """Link to the other hosts as ``label`` (this host's processes) and beat."""
        self.label = label
        layout = self.layout
        self.link = HostLink(session, layout.run_id, label, layout.control_token, self.t_start)
        threading.Thread(target=self._beat_loop, name="heartbeat", daemon=True).start()

    def stop(self) -> None:
        """No more heartbeats (the run's processes are stopped: this host's share is over)."""
        self._beating.set()

    def own_stages(self) -> list[str]:
        return self.layout.stage_names(self.layout.hosted)

    def _beat_loop(self) -> None:
        layout = self.layout
        while not self._beating.wait(0.05):
            try:
                self.link.beat({"stages": list(layout.hosted), "source": layout.runs_source,
                                "primary": layout.is_primary, "epoch": layout.epoch, "ready": self.ready_epoch,
                                "cut": self.newest_cut()})
            except Exception as exc:  # the session closed under us at the end
                log.debug("heartbeat: %s", exc)

    def newest_cut(self) -> int | None:
        """The newest checkpoint cut all of this host's stages completed (read at most once a second)."""
        at, cut = self._cut_cache
        if time.monotonic() - at > 1.0:
            cut = latest_complete_cut(self.layout.run_dir / "checkpoint", self.own_stages())
            self._cut_cache = (time.monotonic(), cut)
        return cut

    def check_gone(self) -> None:
        """One line and the end of this host's share when another host has been silent too long."""
        for label, silent in self.link.silent().items():
            if silent < self.layout.cfg.run.host_timeout:
                continue
            peer = self.link.peer(label) or {}
            what = list(peer.get("stages") or []) + (["the source"] if peer.get("source") else []) + \
                (["the monitor"] if peer.get("primary") else [])
            raise RunError(f"run {self.layout.run_id}: host {label!r} silent for {silent:.0f} s (link down or "
                           f"host dead); ending this host's share: missing {', '.join(what) or label}")

    # ------------------------------------------------------------------ rollback (lossless)
    def remote(self) -> list[str]:
        """The processes of the run that other hosts run."""
        layout = self.layout
        return [w for w in layout.groups if w not in layout.hosted] + ([] if layout.runs_source else ["source"])

    def rollback_cause(self, stalled_since: float | None) -> str | None:
        """Why the run must roll back now, or None."""
        for name, st in self.collector.snapshot().items():
            if st.get("holes") and st.get("epoch", 0) == self.layout.epoch:
                topic, (last, prev, frame) = next(iter(st["holes"].items()))
                return f"{name} missed {topic} after frame {last} (next came frame {frame})"
        if len(self.link.restarted) > self._restarts_handled:
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
        if any(st.get("epoch", 0) != self.layout.epoch for st in raw.values() if "epoch" in st):
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

    def restart_at(self, cut: int) -> None:
        """This host's workers from ``cut`` (afresh at 0), in the run's current epoch."""
        layout = self.layout
        for w in layout.hosted:
            self.children.start(w, worker_entry, layout.worker_spec_at(w, cut))
        self.children.wait_ready(list(layout.hosted), layout.cfg.run.startup_timeout)
        self.ready_epoch = layout.epoch

    def _peers(self) -> list[dict[str, Any]]:
        return [p for p in (self.link.peer(lb) for lb in self.link.silent()) if p]

    def _peers_ready(self, epoch: int) -> bool:
        peers = self._peers()
        return bool(peers) and all(p.get("ready") == epoch for p in peers)

    def rollback(self, cause: str, fresh: bool = False) -> None:
        """Roll the whole run back to the newest cut every host holds (module docstring); every
        host restarts its workers at once (the new epoch keeps what old processes still send
        out), the source replays once all are ready. ``fresh``: this host's workers were just
        started from the cut (a resumed host)."""
        layout, children = self.layout, self.children
        t0 = time.time()
        log.warning("run %s: rolling back (%s)", layout.run_id, cause)
        if fresh:
            cut = layout.resume_cut or 0
        else:
            cuts = [self.newest_cut()] + [p.get("cut") for p in self._peers()]
            cut = 0 if any(c is None for c in cuts) else int(min(cuts))
            layout.epoch = int(time.time() * 1000)
        epoch = layout.epoch
        self.link.command("rollback", epoch=epoch, cut=cut)
        sent = time.monotonic()
        if not fresh:
            children.kill([*layout.hosted, *(["source"] if layout.runs_source else [])])
            self.restart_at(cut)
        self.ready_epoch = epoch
        while not self._peers_ready(epoch):  # the other hosts restart theirs from the same cut
            if time.monotonic() - sent > 2.0:
                self.link.command("rollback", epoch=epoch, cut=cut)
                sent = time.monotonic()
            self.check_gone()
            time.sleep(0.1)
        if layout.runs_source:
            children.kill(["source"])
            children.wait_ready(list(layout.groups), layout.cfg.run.startup_timeout)
            children.start("source", source_entry, layout.source_spec(cut))
        self._outages_handled = len(self.link.all_outages())
        self.rollbacks.append({"time_s": round(t0 - self.t_start, 3), "cause": cause, "cut": cut,
                               "took_s": round(time.time() - t0, 3)})
        log.warning("run %s: rolled back to frame %d in %.1f s", layout.run_id, cut, time.time() - t0)

    def obey_commands(self) -> None:
        """A secondary host: the primary's rollbacks since the last call (``obey``)."""
        for cmd in self.link.take_commands():
            self.obey(cmd)

    def obey(self, cmd: dict[str, Any]) -> None:
        """A secondary host: the primary's rollback; its source replays once the primary is ready."""
        layout = self.layout
        epoch = int(cmd.get("epoch") or 0)
        if cmd.get("command") != "rollback" or epoch <= layout.epoch:
            return
        t0 = time.time()
        self.paused = epoch
        self.children.kill([*layout.hosted, "source"])
        layout.epoch, cut = epoch, int(cmd.get("cut") or 0)
        self.restart_at(cut)
        self.replay_from = cut if layout.runs_source else None
        self.rollbacks.append({"time_s": round(t0 - self.t_start, 3), "cut": cut,
                               "took_s": round(time.time() - t0, 3)})

    def replay(self) -> None:
        """A secondary host with the source: start it again once every host is ready."""
        layout = self.layout
        primary = next((p for p in self._peers() if p.get("primary")), None)
        if primary is None or primary.get("ready") != layout.epoch:
            return
        if set(layout.groups) - self.children.alive_tokens():
            return
        self.children.start("source", source_entry, layout.source_spec(self.replay_from))
        self.replay_from = None
        self.paused = None

    # ------------------------------------------------------------------ what a resumed primary needs
    def persist(self) -> None:
        """Save the run's figures so far to STATE_FILE (at most every PERSIST_S)."""
        if time.monotonic() - self._persisted_at < PERSIST_S:
            return
        self._persisted_at = time.monotonic()
        c = self.collector
        with c.lock:
            state = {"raw": c.raw, "earlier": c.earlier, "lives": c.lives, "spans": c.spans}
            state = json.loads(json.dumps(state, default=str))
        with self.final.lock:
            final = self.final.frames.ranges()
        state.update({"final": final, "outages": self.link.all_outages(), "rollbacks": self.rollbacks,
                      "restart_events": self.children.restart_events})
        state = {"format": STATE_FORMAT, "version": STATE_VERSION, **state}
        try:
            write_atomic(self.layout.run_dir / STATE_FILE, json.dumps(state).encode())
        except OSError as exc:
            log.debug("%s not written: %s", STATE_FILE, exc)

    def restore(self, path: Path) -> None:
        """A resumed primary takes the figures its earlier life saved in ``path`` (none when it
        saved none); a file of another format version, or of none, is refused with
        :class:`~neoslam_stream.runtime.checkpoint.StateFormatError`."""
        try:
            state = json.loads(path.read_text())
        except (OSError, ValueError):
            return
        found = state.get("version") if isinstance(state, dict) and state.get("format") == STATE_FORMAT else None
        if found != STATE_VERSION:
            raise StateFormatError(path, found, STATE_VERSION)
        c = self.collector
        with c.lock:
            c.raw, c.earlier = state["raw"], state["earlier"]
            c.lives, c.spans = state["lives"], state["spans"]
        with self.final.lock:
            for a, b in state["final"]:
                self.final.frames.add_range(a, b)
        self.rollbacks = list(state["rollbacks"])
        self.children.restart_events = list(state["restart_events"])
        self._earlier_outages = list(state["outages"])

    # ------------------------------------------------------------------ report
    def outages(self) -> list[dict[str, Any]]:
        seen, out = set(), []
        for o in [*self._earlier_outages, *(self.link.all_outages() if self.link else [])]:
            key = (o.get("seen_by"), o.get("host"), o.get("start_wall"))
            if key not in seen:
                seen.add(key)
                out.append(o)
        return sorted(out, key=lambda o: o.get("start_wall") or 0)

    def report(self, report: dict[str, Any]) -> dict[str, Any]:
        """report.json's split-run figures: hosts, outages, rollbacks, the loss by cause."""
        layout = self.layout
        stats = self.collector.snapshot()
        src = stats.get("source", {})
        outages = self.outages()
        with self.final.lock:
            final = self.final.frames.copy()
        spans = {k: list(v) for k, v in self.collector.spans.items()}
        loss = loss_by_cause(src, final, stats, spans, outages, int(report.get("frames_strided") or 0),
                             useful_stages(stats, layout.plan.final_topic))
        # no link yet when the share failed before it knew its processes (e.g. --resume refused)
        link = self.link
        hosts = {lb: {"stages": p.get("stages"), "source": p.get("source"), "primary": p.get("primary"),
                      "silent_s": round(s, 3)}
                 for lb, s in (link.silent().items() if link else ()) if (p := link.peer(lb))}
        hosts[self.label] = {"stages": list(layout.hosted), "source": layout.runs_source, "primary": True}
        for o in outages:
            log.warning("run %s: link to %s out at %.1f s for %.1f s (seen by %s)", layout.run_id, o["host"],
                        o["start_s"], o["length_s"], o["seen_by"])
        if report.get("frames_lost"):
            log.warning("run %s: frames lost by cause: %s", layout.run_id,
                        ", ".join(f"{k} {v}" for k, v in loss["by_cause"].items() if v))
        return {"hosts": hosts, "outages": outages, "rollbacks": list(self.rollbacks), "epoch": layout.epoch,
                "loss_by_cause": loss["by_cause"], "loss_frames": loss["frames"],
                "published_ranges": union_ranges(src.get("published_ranges") or [])}

    def summary(self) -> dict[str, Any]:
        """part.json's split-run figures of a secondary host."""
        return {"label": self.label, "outages": self.link.all_outages() if self.link else [],
                "rollbacks": list(self.rollbacks), "epoch": self.layout.epoch}
