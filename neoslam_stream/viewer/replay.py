"""A finished run played again from its folder, in time order, into a view (the Foxglove server).

:func:`run_events` reads what the run folder holds (templates.csv, trajectory.tum, groundtruth.tum,
odometry.tum, camera.zip, map.json, timeline.csv, log.jsonl, report.json) as one list of events on
the source's clock; :func:`play` hands them to a view at ``speed`` times that clock (0: as fast as
it goes). The map grows as it was made: each experience of the final map (map.json) appears at the
stamp it was created, every :data:`MAP_STEP_S` of source time, with its final (relaxed) position.
timeline.csv and log.jsonl count wall-clock seconds of the run: they are spread over the source's
time in proportion (a lossless run is faster than its source).
"""

from __future__ import annotations

import bisect
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .files import FrameOfStamp, _read_csv, _read_tum, read_camera, read_log_lines, timeline_rates

log = logging.getLogger("neoslam.viewer")

#: seconds of source time between two drawings of the growing map
MAP_STEP_S = 1.0
Event = tuple[float, int, Callable[[Any], None]]


def _map_steps(mp: dict[str, Any], t0: float, t1: float) -> list[Event]:
    """The final map growing: at every MAP_STEP_S, its experiences created by then and their links
    (each drawing made when it is played, not before: a long run's snapshots are not all held)."""
    nodes = sorted((n for n in mp.get("nodes", []) if isinstance(n, dict)), key=lambda n: float(n.get("stamp", 0.0)))
    stamps = [float(n.get("stamp", 0.0)) for n in nodes]
    links = [lk for lk in mp.get("links", []) if isinstance(lk, dict)]

    def grown(t: float) -> dict[str, Any]:
        seen = nodes[:bisect.bisect_right(stamps, t)]
        ids = {n.get("id") for n in seen}
        return {"nodes": seen, "links": [lk for lk in links if lk.get("from") in ids and lk.get("to") in ids]}

    n_steps = int(np.floor((t1 - t0) / MAP_STEP_S)) + 1 if t1 >= t0 else 0
    events: list[Event] = [(t0 + k * MAP_STEP_S, 3, lambda v, t=t0 + k * MAP_STEP_S: v.experience_map(grown(t)))
                           for k in range(n_steps)]
    events.append((t1, 4, lambda v: v.experience_map(mp)))
    return events


def run_events(run_dir: str | Path) -> list[Event]:
    """Every event of the run folder, sorted by (source time, kind): a frame's template before
    its pose, the map after them."""
    run_dir = Path(run_dir)
    templates = _read_csv(run_dir / "templates.csv")
    frame_of = FrameOfStamp(templates)
    events: list[Event] = []
    for r in templates:
        f, s, tid, loop = int(r["frame"]), float(r["stamp"]), int(r["template_id"]), r["is_loop_closure"] == "1"
        events.append((s, 1, lambda v, f=f, s=s, tid=tid, loop=loop: v.template(f, s, tid, loop)))
    for s, x, y, th in _read_tum(run_dir / "trajectory.tum"):
        f = frame_of(s, -1)
        events.append((s, 2, lambda v, f=f, s=s, p=np.array([x, y, th]): v.pose(f, s, p)))
    for name, call in (("groundtruth.tum", "groundtruth"), ("odometry.tum", "odometry_pose")):
        for s, x, y, th in _read_tum(run_dir / name):
            events.append((s, 0, lambda v, s=s, p=np.array([x, y, th]), c=call: getattr(v, c)(frame_of(s), s, p)))
    for f, s, jpeg in read_camera(run_dir):
        events.append((s, 0, lambda v, f=f, s=s, j=jpeg: v.jpeg(f, s, j)))
    stamps = [e[0] for e in events]
    t0, t1 = (min(stamps), max(stamps)) if stamps else (0.0, 0.0)
    rates = timeline_rates(run_dir / "timeline.csv")
    logs = read_log_lines(run_dir / "log.jsonl")
    wall = max([float(r["t_s"]) for r in logs] + [t_s for t_s, _stage, _rate, _row in rates] + [1e-9])

    def at(t_s: float) -> float:  # the run's wall-clock seconds on the source's clock
        return t0 + (t1 - t0) * min(1.0, max(0.0, t_s / wall))

    for t_s, stage, rate, row in rates:
        if stage == "source":  # its row counts the frames it published
            events.append((at(t_s), 5, lambda v, n=row.get("processed"): v.source_stats({"frames_in": int(n or 0)})))
            continue
        events.append((at(t_s), 5, lambda v, t=t_s, st=stage, r=rate, row=row: v.stage_stats(t, st, r, row)))
    for row in logs:
        events.append((at(float(row["t_s"])), 5, lambda v, r=row: v.log_line(
            float(r.get("t", 0.0)), str(r.get("level", "INFO")), str(r.get("process", "")), str(r.get("name", "")),
            str(r.get("message", "")))))
    try:
        mp = json.loads((run_dir / "map.json").read_text()) if (run_dir / "map.json").exists() else None
    except ValueError as exc:
        log.warning("map.json not shown: %s", exc)
        mp = None
    if isinstance(mp, dict):
        events += _map_steps(mp, t0, t1)
    try:
        report = json.loads((run_dir / "report.json").read_text()) if (run_dir / "report.json").exists() else None
    except ValueError:
        report = None
    if isinstance(report, dict):
        events.append((t1, 6, lambda v: v.run_ended(report)))
    return sorted(events, key=lambda e: (e[0], e[1]))


def play(events: list[Event], view: Any, speed: float = 1.0, stop: Callable[[], bool] = lambda: False) -> int:
    """Hand ``events`` to ``view`` at ``speed`` times source time (0: at once); the number handed."""
    if not events:
        return 0
    t0, start = events[0][0], time.monotonic()
    n = 0
    for t, _kind, call in events:
        if stop():
            break
        if speed > 0:
            delay = start + (t - t0) / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        try:
            call(view)
        except (KeyError, TypeError, ValueError) as exc:  # one bad row must not end the replay
            view.stats.bad_messages += 1
            log.debug("replay: skipped an event: %s", exc)
        n += 1
    return n
