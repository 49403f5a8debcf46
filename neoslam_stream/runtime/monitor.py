"""The monitor process: follows a run's stats and writes its figures.

During a run it shows a live ``rich`` table, appends a row per stage to ``timeline.csv`` every
second and a line to ``stats.jsonl`` every few seconds, and at the end writes ``report.json``
(report.py) once every stage sent its final stats; with ``--trace FILE`` it streams every frame's
path through the stages to FILE (trace.py). ``neoslam monitor`` attaches the same table to a
running pipeline. What it collects: collector.py; the figures: report.py.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import runlog
from .bus import key_for, open_session
from .collector import FinalTracker, StatsCollector
from .messages import LOG, Topic, register_topics
from .report import _json_default, build_report, write_report
from .trace import TraceWriter

#: the live table's columns after the stage's name, and what they say (its caption)
LIVE_COLUMNS = ("recv", "done", "Hz", "p50\nms", "p95\nms", "wait\nms", "drop", "err", "cpu\n%", "MB")
LIVE_CAPTION = ("recv/done: messages received/processed; Hz: done per second; p50/p95: service time tau; "
                "wait: queueing p50; drop: evicted from the stage's queue; err: refused; MB: memory (PSS)")


def figure(value: float) -> str:
    """A measured figure in at most four characters where it can: three significant digits below
    1000 (0.42, 12.3, 123), whole numbers above."""
    v = float(value)
    if not math.isfinite(v):
        return str(v)
    a = abs(v)
    return f"{v:.0f}" if a >= 99.95 or a == 0 else f"{v:.1f}" if a >= 9.995 else f"{v:.2f}"


def stats_table(stats: dict[str, dict[str, Any]], title: str = "neoslam") -> Any:
    """A rich Table of the current stats (used by the live view and `neoslam monitor`). Compact, so
    that 80 columns show every stage's whole name and every value: no vertical rules, short
    headers, figures in at most four characters, what the columns mean in the caption."""
    from rich import box
    from rich.table import Table

    names = [n for n in stats if n != "source"]
    table = Table(title=title, caption=LIVE_CAPTION, expand=False, box=box.SIMPLE_HEAD, pad_edge=False,
                  padding=0, caption_justify="left")
    table.add_column("stage", no_wrap=True, min_width=max([6, *map(len, names)]))
    for col in LIVE_COLUMNS:
        table.add_column(col, justify="right", no_wrap=True)
    now = time.time()
    src = stats.get("source")
    if src is not None:
        table.add_row("source", "", str(src.get("frames_in", 0)), _source_rate(src), "", "", "",
                      str(sum((src.get("lost_at_source") or {}).values())), str(src.get("errors", 0)), "", "")
        camera = (src.get("info") or {}).get("camera")
        if isinstance(camera, dict):
            table.add_row(*camera_row(camera))
    for name, st in sorted(stats.items()):
        if name == "source":
            continue
        active = max(1e-9, now - st.get("started", now))
        drops = sum(i.get("evicted", 0) for i in st.get("inputs", {}).values())
        table.add_row(name, str(st.get("received", 0)), str(st.get("processed", 0)),
                      figure(st.get("processed", 0) / active), figure(st.get("tau_p50_ms", 0)),
                      figure(st.get("tau_p95_ms", 0)), figure(st.get("queue_p50_ms", 0)), str(drops),
                      str(st.get("errors", 0)), f"{st.get('cpu_percent', 0):.0f}",
                      f"{st.get('pss_mb') or st.get('rss_mb', 0):.0f}")
    return table


def _source_rate(src: dict[str, Any]) -> str:
    """Frames per second the source published, from its first to its last frame."""
    first, last, n = src.get("first_publish"), src.get("last_publish"), int(src.get("frames_in") or 0)
    return f"{(n - 1) / (last - first):.1f}" if first is not None and last is not None and last > first else ""


def camera_row(camera: dict[str, Any]) -> list[str]:
    """The monitor table's row of a live camera (a source's ``info["camera"]``, its own or a remote
    publisher's): frames captured and sent on, its rate, drops, skipped frames, and its outages in
    the name column."""
    outages = int(camera.get("outage_count") or 0)
    name = "  camera"
    if camera.get("state") == "reopening":
        name += f" (reopening, {camera.get('outage_now_s', 0):.0f} s)"
    elif outages:
        name += f" ({outages} outage{'s' if outages > 1 else ''}, {camera.get('outage_s', 0):.1f} s)"
    sent = camera.get("published", camera.get("taken", 0))
    rate = camera.get("rate_hz")
    return [name, str(camera.get("captured", 0)), str(sent), "" if rate is None else f"{rate:.1f}", "", "", "",
            str(camera.get("dropped", 0)), str(sum((camera.get("skipped") or {}).values())), "", ""]


@dataclass
class MonitorSpec:
    """Everything the monitor process needs; plain data so it crosses a ``spawn``."""

    run: str
    run_dir: str
    final_topic: str
    entry_stages: list[str]
    workers: dict[str, list[str]]
    meta: dict[str, Any] = field(default_factory=dict)
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    shm: bool = False
    live: bool = False
    final_wait_s: float = 10.0
    #: seconds between two lines of stats.jsonl
    snapshot_every_s: float = 5.0
    #: the run's control secret (bus.ControlGate): control messages without it are refused
    control_token: str = ""
    #: the message types of the run with their schemas (the plan's): the final topic's among them
    topics: list[Topic] = field(default_factory=list)
    #: ``--trace FILE``: every frame's path through the stages as a Chrome / Perfetto trace (trace.py)
    trace: str = ""
    #: the run's start (s, epoch): the trace's zero
    started: float = 0.0


def write_timeline_row(writer: Any, t0: float, stats: dict[str, dict[str, Any]]) -> None:
    now = time.time()
    for name, st in stats.items():
        if name == "source":
            writer.writerow([f"{now - t0:.2f}", name, "", st.get("frames_in", 0), "", "", "", "", "", "", "", ""])
            continue
        drops = sum(i.get("evicted", 0) for i in st.get("inputs", {}).values())
        depth = sum(i.get("depth", 0) for i in st.get("inputs", {}).values())
        writer.writerow([f"{now - t0:.2f}", name, st.get("received", 0), st.get("processed", 0),
                         f"{st.get('tau_p50_ms', 0):.3f}", f"{st.get('tau_p95_ms', 0):.3f}", depth, drops,
                         st.get("errors", 0), f"{st.get('cpu_percent', 0):.1f}", f"{st.get('rss_mb', 0):.1f}",
                         "" if st.get("pss_mb") is None else f"{st['pss_mb']:.1f}"])


TIMELINE_HEADER = ["t_s", "stage", "received", "processed", "tau_p50_ms", "tau_p95_ms", "queue_depth",
                   "dropped", "errors", "cpu_percent", "rss_mb", "pss_mb"]


#: per-stage fields kept in stats.jsonl (the stage's own ``info`` too: sizes of its state)
SNAPSHOT_FIELDS = ("worker", "received", "processed", "errors", "tau_recent_p50_ms", "tau_recent_p95_ms",
                   "tau_p50_ms", "cpu_percent", "rss_mb", "pss_mb", "info")


def stats_snapshot(t0: float, stats: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """One line of stats.jsonl: every stage's counters, recent service times, CPU, RSS and info."""
    return {"t_s": round(time.time() - t0, 3),
            "frames_in": stats.get("source", {}).get("frames_in", 0),
            "stages": {name: {k: st.get(k) for k in SNAPSHOT_FIELDS if k in st}
                       for name, st in stats.items() if name != "source"}}


def run_monitor(spec: MonitorSpec) -> None:
    """Monitor process: collect until told to stop, then write report.json and timeline.csv."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s monitor %(levelname)s %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the supervisor decides when the monitor stops
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    register_topics(spec.topics)
    session = open_session(spec.listen, spec.connect, spec.shm)
    collector = StatsCollector()
    final = FinalTracker(entry_stages=set(spec.entry_stages))
    trace = TraceWriter(spec.trace, spec.workers, spec.started) if spec.trace else None
    if trace is not None:
        final.on_frame = trace.add
    subs = [session.declare_subscriber(key_for(spec.run, "stats/**"), collector.on_sample),
            session.declare_subscriber(key_for(spec.run, spec.final_topic), final.on_sample)]

    from .bus import ControlGate

    gate = ControlGate(spec.control_token, "monitor")

    def _on_control(sample: Any) -> None:
        data = gate.check(sample.payload.to_bytes())  # None: not from this run's supervisor
        if data is not None and data["command"] == "stop" and data.get("target") == "monitor":
            stop.set()

    subs.append(session.declare_subscriber(key_for(spec.run, "control"), _on_control))
    token = session.liveliness().declare_token(key_for(spec.run, "alive/monitor"))
    run_dir = Path(spec.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    # every process's log lines (runlog.py) into log.jsonl; the monitor's own on the bus too
    log_file = runlog.LogFile(run_dir, t0)
    subs.append(session.declare_subscriber(key_for(spec.run, str(LOG)), log_file.on_sample))
    logs = runlog.attach(session, spec.run, "monitor")
    live = None
    if spec.live:
        from rich.live import Live

        live = Live(stats_table({}), refresh_per_second=1, transient=False)
        live.start()
    last_snapshot = 0.0
    # appended, not truncated: a restarted monitor (its first life was killed) keeps what the
    # first one wrote; the supervisor starts the files afresh for a new run in the same folder
    timeline = run_dir / "timeline.csv"
    fresh = not timeline.exists() or timeline.stat().st_size == 0
    with open(timeline, "a", newline="") as fh, open(run_dir / "stats.jsonl", "a") as jfh:
        writer = csv.writer(fh)
        if fresh:
            writer.writerow(TIMELINE_HEADER)
        while not stop.wait(1.0):
            snap = collector.snapshot()
            write_timeline_row(writer, t0, snap)
            fh.flush()
            if time.time() - last_snapshot >= spec.snapshot_every_s:
                last_snapshot = time.time()
                jfh.write(json.dumps(stats_snapshot(t0, snap), default=_json_default) + "\n")
                jfh.flush()
            if live is not None:
                live.update(stats_table(snap, f"neoslam run {spec.run}"))
            if trace is not None:
                with final.lock:
                    trace.flush()
        # wait for every stage's final stats (sent after its flush)
        expected = [n for names in spec.workers.values() for n in names]
        deadline = time.monotonic() + spec.final_wait_s
        while time.monotonic() < deadline:
            snap = collector.snapshot()
            if all(snap.get(n, {}).get("final") for n in expected):
                break
            time.sleep(0.1)
        snap = collector.snapshot()
        write_timeline_row(writer, t0, snap)
    if live is not None:
        live.update(stats_table(snap, f"neoslam run {spec.run}"))
        live.stop()
    if trace is not None:
        with final.lock:
            final.on_frame = None
            trace.close()
    report = build_report(snap, final, spec.workers, spec.meta)
    report["control_refused_monitor"] = gate.refused
    write_report(run_dir / "report.json", report)
    token.undeclare()
    runlog.detach(logs)
    for s in subs:
        s.undeclare()
    log_file.close()
    session.close()


def attach(run: str, connect: list[str], refresh_s: float = 1.0, duration: float | None = None) -> None:
    """Live table of a running pipeline's stats (``neoslam monitor``)."""
    from rich.live import Live

    session = open_session(listen=[], connect=connect, mode="client")
    collector = StatsCollector()
    sub = session.declare_subscriber(key_for(run, "stats/**"), collector.on_sample)
    t_end = None if duration is None else time.monotonic() + duration
    try:
        with Live(stats_table({}), refresh_per_second=max(1, int(1 / refresh_s))) as live:
            while t_end is None or time.monotonic() < t_end:
                time.sleep(refresh_s)
                live.update(stats_table(collector.snapshot(), f"neoslam run {run}"))
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
