"""Every lost frame of a run, counted once, by cause.

A frame is lost when the camera produced it and it never reached the final topic. Each lost frame
gets the first of these causes that explains it: ``source`` (the source never published it, or
published it without the odometry it needs), ``restart`` (a stage was not running when it passed:
between the last frame one life of the stage processed and the first of its next life), ``link``
(published while a link between hosts was out of reach), ``ring`` (dropped by a bounded input, up
to the drops counted), ``refused`` (bad input or an internal error, up to those counted), and
``in flight or unexplained`` (the rest: frames on their way when a real-time run ended).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from typing import Any

#: publication times are known to about a second, and frames in flight when a link went out were lost too
LINK_MARGIN_S = 1.0


def _frames(ranges: Iterable[Iterable[int]]) -> Iterable[int]:
    for a, b in ranges:
        yield from range(int(a), int(b) + 1)


def to_ranges(frames: Iterable[int]) -> list[list[int]]:
    """Sorted frames as ``[first, last]`` ranges."""
    out: list[list[int]] = []
    for f in sorted(set(frames)):
        if out and f == out[-1][1] + 1:
            out[-1][1] = f
        else:
            out.append([f, f])
    return out


def publish_time(frame_times: list[list[float]], frame: int) -> float | None:
    """When the source published ``frame`` (interpolated between its ``[frame, time]`` samples)."""
    if not frame_times:
        return None
    frames = [int(f) for f, _ in frame_times]
    i = bisect.bisect_right(frames, frame) - 1
    if i < 0:
        return float(frame_times[0][1])
    if i + 1 >= len(frame_times):
        f0, t0 = frame_times[i]
        if i > 0:  # beyond the last sample: the rate of the samples before
            f1, t1 = frame_times[i - 1]
            rate = (t0 - t1) / max(1, f0 - f1)
            return float(t0 + (frame - f0) * rate)
        return float(t0)
    (f0, t0), (f1, t1) = frame_times[i], frame_times[i + 1]
    return float(t0 + (t1 - t0) * (frame - f0) / max(1, f1 - f0))


def restart_windows(spans: dict[str, list[list[int]]], stats: dict[str, dict[str, Any]]) -> list[tuple[int, int]]:
    """Frames (exclusive bounds) no life of a stage processed between two of its lives."""
    out = []
    for name, earlier in spans.items():
        if name == "source":
            continue
        cur = stats.get(name, {})
        lives = [*earlier, [cur.get("first_frame", -1), cur.get("last_frame", -1)]]
        for (_a0, b0), (a1, _b1) in zip(lives, lives[1:], strict=False):
            if b0 is not None and a1 is not None and a1 >= 0 and a1 > b0 + 1:
                out.append((int(b0), int(a1)))
            elif a1 is not None and a1 < 0:  # the new life processed nothing yet: lost from b0 on
                out.append((int(b0), 2**62))
    return out


def loss_by_cause(src: dict[str, Any], final_frames: set[int], stats: dict[str, dict[str, Any]],
                  spans: dict[str, list[list[int]]], outages: list[dict[str, Any]], strided: int = 0,
                  stages: Iterable[str] | None = None) -> dict[str, Any]:
    """Counts per cause (module docstring) that add up to the frames lost, and the frames of the
    ``link`` and ``restart`` causes as ranges. ``stages``: the stages whose drops and refusals can
    lose a frame (those on its way to the final topic); all when None."""
    published = list(_frames(src.get("published_ranges") or []))
    lost = [f for f in published if f not in final_frames]
    counts = {"source": 0, "restart": 0, "link": 0, "ring": 0, "refused": 0, "in flight or unexplained": 0}
    counts["source"] = sum(int(v) for v in (src.get("lost_at_source") or {}).values())
    doomed = set(int(f) for f in src.get("doomed_frames") or [])
    windows = restart_windows(spans, stats)
    times = src.get("frame_times") or []
    outs = [(o["start_wall"] - LINK_MARGIN_S, o["end_wall"]) for o in outages
            if o.get("start_wall") is not None and o.get("end_wall") is not None]
    names = list(stats) if stages is None else list(stages)
    rings = sum(sum(int(i.get("evicted", 0)) for i in (stats.get(n, {}).get("inputs") or {}).values())
                for n in names)
    refusals = sum(int(stats.get(n, {}).get("errors", 0)) + int(stats.get(n, {}).get("internal_errors", 0))
                   for n in names)
    by_frame: dict[str, list[int]] = {"restart": [], "link": []}
    for f in lost:
        if f in doomed:
            counts["source"] += 1
        elif any(a < f < b for a, b in windows):
            counts["restart"] += 1
            by_frame["restart"].append(f)
        elif outs and (t := publish_time(times, f)) is not None and any(a <= t <= b for a, b in outs):
            counts["link"] += 1
            by_frame["link"].append(f)
        elif counts["ring"] < rings:
            counts["ring"] += 1
        elif counts["refused"] < refusals:
            counts["refused"] += 1
        else:
            counts["in flight or unexplained"] += 1
    skip = strided  # frames removed on purpose by frame_stride never reach the end: not lost
    for k in ("in flight or unexplained", "refused", "ring", "link", "restart"):
        take = min(counts[k], skip)
        counts[k] -= take
        skip -= take
    return {"by_cause": counts, "frames_lost": sum(counts.values()),
            "frames": {k: to_ranges(v) for k, v in by_frame.items()}}


def useful_stages(stats: dict[str, dict[str, Any]], final_topic: str) -> list[str]:
    """The stages whose output leads to ``final_topic`` (an observer such as the recorder does
    not: its drops lose no frame), from their stats' ``outputs`` and ``consumes``."""
    useful: set[str] = set()
    wanted = {final_topic}
    while True:
        new = {n for n, st in stats.items() if n not in useful and set(st.get("outputs") or []) & wanted}
        if not new:
            return sorted(useful)
        useful |= new
        for n in new:
            wanted |= set(stats[n].get("consumes") or [])
