"""report.json: every figure of a run, from the stages' last stats and the final-topic tracker.

tau_i (service time per message), queueing times, f_in, f_out, f_pipeline (the paper's eq. 2: the
minimum over worker processes of 1 / the sum of the tau_i they host), the predicted loss, and the
measured loss counted by frame numbers (frames the camera produced that never reached the final
topic, those removed on purpose by ``frame_stride`` left out; unknown, never 0, without the
source's stats), with its breakdown by cause and stage. Counters add up over a restarted stage's
lives (collector.py). Definitions: docs/runtime.md, "The monitor's figures".
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from .collector import FinalTracker, _add_maps

log = logging.getLogger("neoslam.monitor")


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

    # eq. 2 generalised to processes: a worker serves its chain in sequence; no prediction from
    # stages that processed nothing (their service times measure no message)
    measured = any(r.get("processed") for r in stage_rows.values())
    per_worker = {w: sum(stage_rows.get(n, {}).get("tau_mean_ms", 0.0) for n in names)
                  for w, names in workers.items()} if measured else {}
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
        "latency_p50_ms": final.latencies.percentile(50) * 1e3,
        "latency_p95_ms": final.latencies.percentile(95) * 1e3,
        "errors": errors, "final_messages": final.messages,
        "source_errors": int(src.get("errors", 0)), "source_error_causes": src.get("error_causes", {}),
        "source": src.get("info", {}),
        "stages": stage_rows,
        "memory": memory,
        # control messages without the run's token, per process (workers, source)
        "control_refused": refused, "control_refused_causes": refused_causes,
    }
    return report


#: the figures of a run that processed no frame: measured over nothing, they are null in a failed
#: run's report rather than numbers that look real
UNMEASURED = ("f_in", "f_out", "duration_s", "loss", "loss_percent", "frames_lost", "frames_expected",
              "f_pipeline_predicted", "predicted_loss", "bottleneck", "bottleneck_tau_ms",
              "latency_p50_ms", "latency_p95_ms")


def mark_status(report: dict[str, Any], failure: str | None, interrupted: bool,
                source_failure: str | None = None) -> dict[str, Any]:
    """``status`` (``completed``, ``interrupted`` or ``failed``) and ``failure`` (the cause, or
    None) of ``report``. The source's failure counts as one of its errors; a failed run that
    processed no frame keeps none of the :data:`UNMEASURED` figures (null)."""
    report["status"] = "failed" if failure else "interrupted" if interrupted else "completed"
    report["failure"] = failure
    if source_failure:
        causes = dict(report.get("source_error_causes") or {})
        causes[source_failure] = causes.get(source_failure, 0) + 1
        report["source_error_causes"] = causes
        report["source_errors"] = int(report.get("source_errors") or 0) + 1
        report["errors"] = int(report.get("errors") or 0) + 1
    if failure and not report.get("frames_out"):
        report.update(dict.fromkeys(UNMEASURED))
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
    # published, but known at the source to reach no end (no odometry to send with them)
    doomed = {str(k): int(v) for k, v in (src.get("published_doomed") or {}).items() if v}
    expected = max(0, frames_in + at_source - strided)
    lost = max(0, expected - frames_out)
    stages: dict[str, Any] = {}
    attributed = at_source + sum(doomed.values())
    for name, row in stage_rows.items():
        if row.get("missing"):
            continue
        b = {"refused": int(row.get("errors", 0)), "internal_errors": int(row.get("internal_errors", 0)),
             "dropped_queue": int(row.get("dropped_queue", 0)),
             "dropped_transport": int(row.get("dropped_transport", 0))}
        if any(b.values()):
            stages[name] = b
            attributed += sum(b.values())
    breakdown = {"source": {**lost_src, **doomed}, "stages": stages, "unattributed": max(0, lost - attributed)}
    return {"frames_out": frames_out, "frames_expected": expected, "frames_lost": lost,
            "frames_lost_at_source": at_source, "loss": lost / expected if expected > 0 else 0.0,
            "breakdown": breakdown}


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


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)
