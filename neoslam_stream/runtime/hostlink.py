"""What the supervisors of a run split over hosts tell each other, and what they learn from it.

Each supervisor puts a heartbeat on ``neoslam/<run>/host/<label>`` four times a second (its
label: the processes it runs, e.g. ``A,B,source``; its life: drawn when it starts, so a restarted
host is told from one that was merely out of reach). From the heartbeats of the others it knows
when a link was out and for how long (:attr:`HostLink.outages`), when a host came back as a new
life, and how long a host has been silent. Commands between supervisors (the rollback of a
lossless run) go on ``neoslam/<run>/parts/control``, with the run's control secret.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections import deque
from typing import Any

from .bus import ControlGate, key_for
from .messages import Message, MessageError, decode, encode

log = logging.getLogger("neoslam.share")

#: seconds between two heartbeats, and the silence that counts as an outage of the link
HEARTBEAT_S = 0.25
OUTAGE_S = 1.0


class HostLink:
    """Heartbeats and commands of one supervisor of a split run (module docstring)."""

    def __init__(self, session: Any, run_id: str, label: str, token: str, t_start: float) -> None:
        self.session = session
        self.run_id = run_id
        self.label = label
        self.life = secrets.token_hex(4)
        self.t_start = t_start
        self.gate = ControlGate(token, f"supervisor {label}")
        self.token = token
        self.lock = threading.Lock()
        #: label -> the newest heartbeat of that host, with ``_arrived`` (monotonic) and ``_wall``
        self.peers: dict[str, dict[str, Any]] = {}
        #: links out of reach, as seen here: host, start (s since this supervisor started), length
        self.outages: list[dict[str, Any]] = []
        #: hosts that came back as a new life (their supervisor was started again)
        self.restarted: list[dict[str, Any]] = []
        self.commands: deque[dict[str, Any]] = deque()
        self._next_beat = 0.0
        self._subs = [
            session.declare_subscriber(key_for(run_id, "host/*"), self._on_heartbeat),
            session.declare_subscriber(key_for(run_id, "parts/control"), self._on_command)]

    # ------------------------------------------------------------------ heartbeats
    def beat(self, info: dict[str, Any]) -> None:
        """Put a heartbeat (at most every HEARTBEAT_S) with ``info`` (this host's state)."""
        now = time.monotonic()
        if now < self._next_beat:
            return
        self._next_beat = now + HEARTBEAT_S
        data = {"stage": f"host:{self.label}", "label": self.label, "life": self.life, "time": time.time(),
                "outages": self.outages[-50:], **info}
        try:
            self.session.put(key_for(self.run_id, f"host/{self.label}"),
                             encode(Message("stats", 0, time.time(), data), validate=False))
        except Exception as exc:  # a closed session while stopping: nothing to tell any more
            log.debug("heartbeat not sent: %s", exc)

    def _on_heartbeat(self, sample: Any) -> None:
        try:
            data = decode(sample.payload.to_bytes(), expected_type="stats").data
        except MessageError:
            return
        label = data.get("label")
        if not isinstance(label, str) or label == self.label:
            return
        now, wall = time.monotonic(), time.time()
        with self.lock:
            prev = self.peers.get(label)
            if prev is not None:
                silent = now - prev["_arrived"]
                if silent > OUTAGE_S:
                    self.outages.append({"host": label, "start_s": round(prev["_wall"] - self.t_start, 3),
                                         "length_s": round(silent, 3), "start_wall": prev["_wall"],
                                         "end_wall": wall})
                    log.warning("run %s: no word from host %s for %.1f s (link out); it is back",
                                self.run_id, label, silent)
                if data.get("life") != prev.get("life"):
                    self.restarted.append({"host": label, "at_s": round(wall - self.t_start, 3),
                                           "life": data.get("life")})
                    if silent > OUTAGE_S:  # not the link: the host itself was down
                        self.outages[-1]["host_restarted"] = True
                    log.warning("run %s: host %s was started again", self.run_id, label)
            self.peers[label] = {**data, "_arrived": now, "_wall": wall}

    def silent(self) -> dict[str, float]:
        """Seconds since each known host was last heard."""
        now = time.monotonic()
        with self.lock:
            return {label: now - p["_arrived"] for label, p in self.peers.items()}

    def peer(self, label: str) -> dict[str, Any] | None:
        with self.lock:
            p = self.peers.get(label)
            return dict(p) if p is not None else None

    def all_outages(self) -> list[dict[str, Any]]:
        """Every outage this host saw, and those the other hosts reported, each once."""
        with self.lock:
            seen = [{**o, "seen_by": self.label} for o in self.outages]
            for label, p in self.peers.items():
                seen += [{**o, "seen_by": label} for o in p.get("outages") or []]
        return seen

    # ------------------------------------------------------------------ commands
    def command(self, command: str, **data: Any) -> None:
        msg = Message("control", 0, time.time(), {"command": command, "token": self.token, "from": self.label,
                                                  **data})
        self.session.put(key_for(self.run_id, "parts/control"), encode(msg))

    def _on_command(self, sample: Any) -> None:
        data = self.gate.check(sample.payload.to_bytes())
        if data is None or data.get("from") == self.label:
            return
        with self.lock:
            self.commands.append(data)

    def take_commands(self) -> list[dict[str, Any]]:
        with self.lock:
            out = list(self.commands)
            self.commands.clear()
        return out

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:
                pass
