"""Throughput monitor: per-stage service times, rates, drops, loss and the bottleneck frequency.

Figures (see docs/runtime.md for the definitions):

* tau_i: service time of stage i per message (p50, p95, max, mean), measured by its worker;
  queueing time: from arrival in the stage's input queue to the start of service.
* f_in: frame rate the source published; f_out = frames_out / duration.
* f_pipeline (paper eq. 2): min over worker processes of 1 / (sum of tau_i hosted in it), i.e.
  min_i 1/tau_i for the pipeline topology and 1/sum_i tau_i for the monolithic one (mean tau).
* predicted loss = 1 - min(1, f_pipeline / f_in).
* measured loss, counted by frame numbers: of the frames the camera produced (those the source
  published, plus those lost in the source itself: its ring, gaps in its frame numbers, images it
  could not publish), minus the frames removed on purpose by ``frame_stride``, the share that never
  reached the final topic. A frame counts as arrived when a message of the final topic carries the
  number of a frame the source published and its trace went through the image entry stage (so
  odometry-only updates of the back end and messages injected by others are not counted).
  Frames refused as bad input, dropped in a ring or in transport, lost while a worker restarted:
  all are in this one figure (``loss``), with the breakdown by cause and stage beside it
  (``loss_breakdown``). Without the source's stats the loss is unknown (``None``), never 0.
* drops per stage: evicted from its input ring + messages its upstream published that never
  arrived (transport drops). Counters add up over a restarted stage's lives (StatsCollector).

The monitor runs as its own process during a run (live ``rich`` table, ``report.json`` and
``timeline.csv`` at the end) and ``neoslam monitor`` attaches to a running pipeline.
"""

from __future__ import annotations

import csv
import json
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bus import key_for, open_session
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
    inputs = {t: dict(i) for t, i in (now.get("inputs") or {}).items()}
    for t, i in (earlier.get("inputs") or {}).items():
        cur = inputs.setdefault(t, {"received": 0, "evicted": 0, "depth": 0})
        cur["received"] = cur.get("received", 0) + i.get("received", 0)
        cur["evicted"] = cur.get("evicted", 0) + i.get("evicted", 0)
    if inputs or "inputs" in now:
        out["inputs"] = inputs
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
    """Frames that reached the final topic, with their end-to-end latency."""

    entry_stages: set[str] = field(default_factory=set)
    frames: set[int] = field(default_factory=set)
    latencies: list[float] = field(default_factory=list)
    arrivals: list[float] = field(default_factory=list)
    messages: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_sample(self, sample: Any) -> None:
        now = time.time()
        try:
            msg = decode(sample.payload.to_bytes())
        except MessageError:
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
            self.arrivals.append(now)
            if trace:
                self.latencies.append(now - trace[0][1])


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else 0.0


def build_report(stats: dict[str, dict[str, Any]], final: FinalTracker,
                 workers: dict[str, list[str]], meta: dict[str, Any]) -> dict[str, Any]:
    """All figures of a run, from the last stats of every stage and the final-topic tracker.

    ``workers`` maps each worker process to the stages it hosts (in chain order).
    """
    src = stats.get("source", {})
    frames_in = int(src.get("frames_in", 0))
    first, last = src.get("first_publish"), src.get("last_publish")
    if frames_in > 1 and first is not None and last is not None and last > first:
        f_in = (frames_in - 1) / (last - first)
    else:
        f_in = float(meta.get("rate") or 0.0)
    duration = frames_in / f_in if f_in > 0 else 0.0

    published: dict[str, int] = {}
    for st in stats.values():
        for topic, n in (st.get("published") or {}).items():
            published[topic] = published.get(topic, 0) + n
    published["image"] = published.get("image", 0) + frames_in
    published["odom"] = published.get("odom", 0) + int(src.get("odom", 0))

    stage_rows: dict[str, Any] = {}
    strided = 0
    refused: dict[str, int] = {}
    refused_causes: dict[str, int] = {}
    if src:
        refused["source"] = int(src.get("control_refused", 0))
        refused_causes = _add_maps(refused_causes, src.get("control_refused_causes") or {})
    for wname, names in workers.items():
        for name in names:
            st = stats.get(name)
            if st is None:
                stage_rows[name] = {"worker": wname, "missing": True}
                continue
            evicted = sum(i.get("evicted", 0) for i in st.get("inputs", {}).values())
            transport = sum(max(0, published.get(t, 0) - i.get("received", 0))
                            for t, i in st.get("inputs", {}).items())
            active = max(1e-9, st.get("time", 0) - st.get("started", 0))
            counters = st.get("counters", {})
            strided += int(counters.get("strided", 0))
            if name == names[0]:  # a worker's counts ride on its first stage's stats
                refused[wname] = int(st.get("control_refused", 0))
                refused_causes = _add_maps(refused_causes, st.get("control_refused_causes") or {})
            stage_rows[name] = {
                "worker": wname, "incarnations": st.get("incarnations", 1),
                "internal_errors": st.get("internal_errors", 0),
                "tau_mean_ms": st.get("tau_mean_ms", 0.0), "tau_p50_ms": st.get("tau_p50_ms", 0.0),
                "tau_p95_ms": st.get("tau_p95_ms", 0.0), "tau_max_ms": st.get("tau_max_ms", 0.0),
                "queue_p50_ms": st.get("queue_p50_ms", 0.0), "queue_p95_ms": st.get("queue_p95_ms", 0.0),
                "received": st.get("received", 0), "processed": st.get("processed", 0),
                "published": st.get("published", {}), "rate_in_hz": st.get("received", 0) / active,
                "rate_out_hz": st.get("processed", 0) / active,
                "dropped": evicted + transport, "dropped_queue": evicted, "dropped_transport": transport,
                "errors": st.get("errors", 0), "error_causes": st.get("error_causes", {}),
                "counters": counters, "info": st.get("info", {}),
                "cpu_percent": st.get("cpu_percent", 0.0), "rss_mb": st.get("rss_mb", 0.0),
                # PSS: shared pages (libraries) divided among the processes that map them, so the
                # sum over workers is the memory the run really takes; RSS counts them once each
                "pss_mb": st.get("pss_mb"),
                # CPU of the whole worker process over its life (shared by the stages it hosts)
                "cpu_mean_percent": 100.0 * st.get("cpu_s", 0.0) / active,
            }

    # eq. 2 generalised to processes: a worker serves its chain in sequence
    per_worker = {w: sum(stage_rows.get(n, {}).get("tau_mean_ms", 0.0) for n in names)
                  for w, names in workers.items()}
    bottleneck_worker = max(per_worker, key=per_worker.get) if per_worker else None
    tau_b = per_worker.get(bottleneck_worker, 0.0) if bottleneck_worker else 0.0
    f_pipeline = 1e3 / tau_b if tau_b > 0 else float("inf")
    if bottleneck_worker is not None and len(workers[bottleneck_worker]) == 1:
        bottleneck = workers[bottleneck_worker][0]
    else:
        bottleneck = bottleneck_worker
    acct = loss_accounting(src, final, stage_rows, strided) if src else None
    frames_out = acct["frames_out"] if acct else len(final.frames)
    errors = sum(r.get("errors", 0) for r in stage_rows.values()) + int(src.get("errors", 0))
    # memory per worker process (its stages report the same process's figures)
    firsts = [stage_rows[names[0]] for names in workers.values() if names and names[0] in stage_rows
              and not stage_rows[names[0]].get("missing")]
    pss = [r.get("pss_mb") for r in firsts]
    memory = {"rss_total_mb": sum(r.get("rss_mb") or 0.0 for r in firsts),
              "pss_total_mb": sum(pss) if pss and all(v is not None for v in pss) else None,
              "workers": len(firsts)}
    report = {
        **meta,
        "f_in": f_in, "frames_in": frames_in, "frames_out": frames_out, "frames_strided": strided,
        "duration_s": duration, "f_out": frames_out / duration if duration > 0 else 0.0,
        # the one headline loss (None: not measured, e.g. the source never reported)
        "loss": acct["loss"] if acct else None,
        "loss_percent": acct["loss"] * 100 if acct and acct["loss"] is not None else None,
        "frames_lost": acct["frames_lost"] if acct else None,
        "frames_lost_at_source": acct["frames_lost_at_source"] if acct else None,
        "frames_expected": acct["frames_expected"] if acct else None,
        "loss_breakdown": acct["breakdown"] if acct else None,
        "f_pipeline_predicted": f_pipeline if np.isfinite(f_pipeline) else None,
        "predicted_loss": (1.0 - min(1.0, f_pipeline / f_in)) if f_in > 0 and np.isfinite(f_pipeline) else None,
        "bottleneck": bottleneck, "bottleneck_tau_ms": tau_b,
        "latency_p50_ms": _pct(final.latencies, 50) * 1e3,
        "latency_p95_ms": _pct(final.latencies, 95) * 1e3,
        "errors": errors, "final_messages": final.messages,
        "source_errors": int(src.get("errors", 0)), "source_error_causes": src.get("error_causes", {}),
        "source": src.get("info", {}),
        "stages": stage_rows,
        "memory": memory,
        # control messages without the run's token, per process (workers, source)
        "control_refused": refused, "control_refused_causes": refused_causes,
    }
    return report


def _in_ranges(frame: int, starts: list[int], ranges: list[list[int]]) -> bool:
    import bisect

    i = bisect.bisect_right(starts, frame) - 1
    return i >= 0 and ranges[i][0] <= frame <= ranges[i][1]


def loss_accounting(src: dict[str, Any], final: FinalTracker, stage_rows: dict[str, Any],
                    strided: int) -> dict[str, Any]:
    """Loss by frame numbers, with its causes.

    ``frames_out``: frames the source published (its ``published_ranges``) that reached the final
    topic. ``frames_expected``: frames the camera produced (published + lost in the source) minus
    the strided ones. ``frames_lost`` = expected - out; ``loss`` = lost / expected. The
    breakdown: the source's losses per cause, and per stage the messages it refused as bad input,
    lost to an internal error, evicted from its ring or lost in transport (counted over every life
    of the stage); ``unattributed`` is what no counter explains (frames in flight when a worker
    died or at the end of a real-time run). Stage counts are messages on a stage's inputs (its
    odometry too), so they explain the loss, they do not add up to it.
    """
    ranges = sorted([int(a), int(b)] for a, b in (src.get("published_ranges") or []))
    if ranges:
        starts = [r[0] for r in ranges]
        with final.lock:
            frames_out = sum(1 for f in final.frames if _in_ranges(f, starts, ranges))
    else:  # a source that does not say which frames it published (an older one)
        frames_out = len(final.frames)
    frames_in = int(src.get("frames_in", 0))
    lost_src = {str(k): int(v) for k, v in (src.get("lost_at_source") or {}).items()}
    at_source = sum(lost_src.values())
    expected = max(0, frames_in + at_source - strided)
    lost = max(0, expected - frames_out)
    stages: dict[str, Any] = {}
    attributed = at_source
    for name, row in stage_rows.items():
        if row.get("missing"):
            continue
        b = {"refused": int(row.get("errors", 0)), "internal_errors": int(row.get("internal_errors", 0)),
             "dropped_queue": int(row.get("dropped_queue", 0)),
             "dropped_transport": int(row.get("dropped_transport", 0))}
        if any(b.values()):
            stages[name] = b
            attributed += sum(b.values())
    breakdown = {"source": lost_src, "stages": stages, "unattributed": max(0, lost - attributed)}
    return {"frames_out": frames_out, "frames_expected": expected, "frames_lost": lost,
            "frames_lost_at_source": at_source, "loss": lost / expected if expected > 0 else 0.0,
            "breakdown": breakdown}


def stats_table(stats: dict[str, dict[str, Any]], title: str = "neoslam") -> Any:
    """A rich Table of the current stats (used by the live view and `neoslam monitor`)."""
    from rich.table import Table

    table = Table(title=title, expand=False)
    for col in ("stage", "recv", "done", "rate Hz", "tau p50 ms", "tau p95 ms", "queue ms", "drop",
                "err", "cpu %", "PSS MB"):
        table.add_column(col, justify="right" if col != "stage" else "left")
    now = time.time()
    src = stats.get("source")
    if src is not None:
        table.add_row("source", "", str(src.get("frames_in", 0)), "", "", "", "", "", str(src.get("errors", 0)), "", "")
    for name, st in sorted(stats.items()):
        if name == "source":
            continue
        active = max(1e-9, now - st.get("started", now))
        drops = sum(i.get("evicted", 0) for i in st.get("inputs", {}).values())
        table.add_row(name, str(st.get("received", 0)), str(st.get("processed", 0)),
                      f"{st.get('processed', 0) / active:.1f}", f"{st.get('tau_p50_ms', 0):.1f}",
                      f"{st.get('tau_p95_ms', 0):.1f}", f"{st.get('queue_p50_ms', 0):.1f}", str(drops),
                      str(st.get("errors", 0)), f"{st.get('cpu_percent', 0):.0f}",
                      f"{st.get('pss_mb') or st.get('rss_mb', 0):.0f}")
    return table


@dataclass
class MonitorSpec:
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


def write_report(path: str | Path, report: dict[str, Any]) -> bool:
    """Write ``report`` as JSON atomically (files.write_atomic): a full disk leaves the previous
    report.json as it was and is said in the log; True when written."""
    from .files import describe_write_error, write_atomic

    try:
        write_atomic(path, json.dumps(report, indent=2, default=_json_default).encode())
    except OSError as exc:
        log.error("report not written: %s (the previous report, if any, is intact)",
                  describe_write_error(path, exc))
        return False
    return True


def run_monitor(spec: MonitorSpec) -> None:
    """Monitor process: collect until told to stop, then write report.json and timeline.csv."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s monitor %(levelname)s %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the supervisor decides when the monitor stops
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = open_session(spec.listen, spec.connect, spec.shm)
    collector = StatsCollector()
    final = FinalTracker(entry_stages=set(spec.entry_stages))
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
    report = build_report(snap, final, spec.workers, spec.meta)
    report["control_refused_monitor"] = gate.refused
    write_report(run_dir / "report.json", report)
    token.undeclare()
    for s in subs:
        s.undeclare()
    session.close()


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


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
