"""The run's figures as they arrive: every stage's newest stats and the frames that reached the end.

:class:`StatsCollector` keeps the newest ``stats/<stage>`` message of each stage and adds up the
counters of a restarted stage's lives; :class:`FinalTracker` counts the frames that reached the
run's final topic with their end-to-end latency. The monitor and the supervisor both follow the
run with them (the supervisor's figures survive a killed monitor).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..tallies import FrameRanges, LogHistogram
from .messages import MessageError, decode

log = logging.getLogger("neoslam.monitor")


#: counters of a stage's stats that add up over its lives (a restarted worker starts them at 0)
CUMULATIVE = ("received", "processed", "errors", "internal_errors", "control_refused")
CUMULATIVE_MAPS = ("error_causes", "internal_error_causes", "published", "counters", "control_refused_causes")


def _add_maps(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[k] = out.get(k, 0) + v
        elif k not in out:
            out[k] = v
    return out


def _add_lives(earlier: dict[str, Any], now: dict[str, Any]) -> dict[str, Any]:
    """The stats of a stage's current life plus the totals of its ``earlier`` lives."""
    out = dict(now)
    for k in CUMULATIVE:
        if k in earlier or k in now:
            out[k] = int(earlier.get(k, 0) or 0) + int(now.get(k, 0) or 0)
    for k in CUMULATIVE_MAPS:
        if k in earlier or k in now:
            out[k] = _add_maps(earlier.get(k) or {}, now.get(k) or {})
    if "published_ranges" in earlier or "published_ranges" in now:  # a source started again: every frame it published
        out.update(_merge_source_lives(earlier, now))
    inputs = {t: dict(i) for t, i in (now.get("inputs") or {}).items()}
    for t, i in (earlier.get("inputs") or {}).items():
        cur = inputs.setdefault(t, {"received": 0, "evicted": 0, "depth": 0})
        cur["received"] = cur.get("received", 0) + i.get("received", 0)
        cur["evicted"] = cur.get("evicted", 0) + i.get("evicted", 0)
    if inputs or "inputs" in now:
        out["inputs"] = inputs
    return out


def union_ranges(*lists: list[list[int]]) -> list[list[int]]:
    """The union of lists of ``[first, last]`` frame ranges, sorted and merged."""
    out: list[list[int]] = []
    for a, b in sorted((int(r[0]), int(r[1])) for rs in lists for r in rs):
        if out and a <= out[-1][1] + 1:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return out


def _merge_source_lives(earlier: dict[str, Any], now: dict[str, Any]) -> dict[str, Any]:
    """The source's figures over its lives: the frames published (each once, however often it
    was published), the known losses added, the first publication of the first life."""
    ranges = union_ranges(earlier.get("published_ranges") or [], now.get("published_ranges") or [])
    out: dict[str, Any] = {"published_ranges": ranges, "frames_in": sum(b - a + 1 for a, b in ranges),
                           "frame_times": list(earlier.get("frame_times") or []) + list(now.get("frame_times") or []),
                           "doomed_frames": sorted(set(earlier.get("doomed_frames") or [])
                                                   | set(now.get("doomed_frames") or []))}
    for k in ("lost_at_source", "published_doomed"):
        out[k] = _add_maps(earlier.get(k) or {}, now.get(k) or {})
    firsts = [x for x in (earlier.get("first_publish"), now.get("first_publish")) if x is not None]
    out["first_publish"] = min(firsts) if firsts else None
    return out


class StatsCollector:
    """Keeps the newest ``stats/<stage>`` message of every stage and a short history of each.

    A stage whose stats come from a new pid was restarted: its counters start again at 0, so the
    last stats of its earlier lives are kept and added (``received``, ``processed``, errors,
    drops...; ``incarnations`` says how many lives). Without this, a restart made the report
    compare the new life's ``received`` with everything its upstream ever published.
    """

    def __init__(self) -> None:
        self.latest: dict[str, dict[str, Any]] = {}
        #: per stage: the newest stats of its current life as sent, and the sum of earlier lives
        self.raw: dict[str, dict[str, Any]] = {}
        self.earlier: dict[str, dict[str, Any]] = {}
        self.lives: dict[str, int] = {}
        self.prev: dict[str, dict[str, Any]] = {}
        self.first_seen: dict[str, float] = {}
        self.changed_at: dict[str, float] = {}
        #: per stage: (first, last) frame each earlier life processed (the gaps between lives are
        #: the frames a restart cost)
        self.spans: dict[str, list[list[int]]] = {}
        self.lock = threading.Lock()

    def on_sample(self, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), expected_type="stats")
        except MessageError as exc:
            log.warning("ignoring malformed stats message: %s", exc)
            return
        self.add(msg.data)

    def add(self, data: dict[str, Any]) -> None:
        name = data.get("stage")
        if not isinstance(name, str):
            return
        now = time.monotonic()
        with self.lock:
            raw_old = self.raw.get(name)
            if raw_old is None:
                self.lives[name] = 1
            elif data.get("pid") is not None and raw_old.get("pid") not in (None, data.get("pid")):
                self.earlier[name] = _add_lives(self.earlier.get(name, {}), raw_old)
                self.spans.setdefault(name, []).append([int(raw_old.get("first_frame", -1)),
                                                        int(raw_old.get("last_frame", -1))])
                self.lives[name] = self.lives.get(name, 1) + 1
            self.raw[name] = dict(data)
            if name in self.earlier:
                data = _add_lives(self.earlier[name], data)
            data = dict(data)
            data["incarnations"] = self.lives[name]
            old = self.latest.get(name)
            if old is not None:
                self.prev[name] = old
                if (old.get("processed"), old.get("received"), old.get("frames_in")) != (
                        data.get("processed"), data.get("received"), data.get("frames_in")):
                    self.changed_at[name] = now
            else:
                self.first_seen[name] = now
                self.changed_at[name] = now
            data = dict(data)
            data["_seen"] = now
            self.latest[name] = data

    def snapshot(self) -> dict[str, dict[str, Any]]:
        with self.lock:
            return {k: dict(v) for k, v in self.latest.items()}

    def quiet(self, stages: list[str], for_s: float, fresh_s: float, check_transport: bool = True) -> bool:
        """True when every stage reported recently, has nothing queued, and nothing moved for ``for_s``."""
        now = time.monotonic()
        with self.lock:
            for name in stages:
                st = self.latest.get(name)
                if st is None or now - st["_seen"] > fresh_s:
                    return False
                if any(i.get("depth", 0) for i in st.get("inputs", {}).values()):
                    return False
                if now - self.changed_at.get(name, now) < for_s:
                    return False
            if not check_transport:
                return True
            # everything a stage published must have arrived at its consumers (lossless transport)
            published: dict[str, int] = {}
            for st in self.latest.values():
                for topic, n in (st.get("published") or {}).items():
                    published[topic] = published.get(topic, 0) + n
            src = self.latest.get("source")
            if src is not None:
                published["image"] = published.get("image", 0) + src.get("frames_in", 0)
                published["odom"] = published.get("odom", 0) + src.get("odom", 0)
            for name in stages:
                for topic, inp in self.latest[name].get("inputs", {}).items():
                    if inp.get("received", 0) < published.get(topic, 0):
                        return False
        return True


@dataclass
class FinalTracker:
    """Frames that reached the final topic, with their end-to-end latency (in memory that does not
    grow with the run: tallies.py)."""

    entry_stages: set[str] = field(default_factory=set)
    frames: FrameRanges = field(default_factory=FrameRanges)
    latencies: LogHistogram = field(default_factory=LogHistogram)
    messages: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
    #: a refused message was logged (once: a stream of them must not flood the log)
    refusal_logged: bool = False
    #: called with each new frame and its trace, in arrival order (the monitor's ``--trace`` writer)
    on_frame: Callable[[int, list], None] | None = None

    def on_sample(self, sample: Any) -> None:
        now = time.time()
        try:
            msg = decode(sample.payload.to_bytes())
        except MessageError as exc:  # not counted as arrived; an unregistered type says so here
            if not self.refusal_logged:
                self.refusal_logged = True
                log.warning("a message of the final topic was refused: %s", exc)
            return
        self.add(msg.frame, msg.trace, now)

    def add(self, frame: int, trace: list, now: float) -> None:
        with self.lock:
            self.messages += 1
            if self.entry_stages and not any(t[0] in self.entry_stages for t in trace):
                return
            if frame in self.frames:
                return
            self.frames.add(frame)
            if trace:
                self.latencies.add(now - trace[0][1])
            if self.on_frame is not None:
                self.on_frame(frame, trace)

