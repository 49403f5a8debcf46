"""Whether a long run's memory is flat once it has warmed up: the one verdict of the live soaks
(bench/soak.py: the default at camera rate; bench/camera_soak.py: a served camera stream).

Rows are samples ``{"t_s", "rss_total_mb", "rss_mb": {process: MB}}``; the window is
``after_s <= t_s <= until_s`` (``until_s``: the end of the stream, after which the processes flush,
save and exit). ``range_mb`` = max - min of the summed RSS over the window: memory that rises and
memory that falls both count, so a run whose memory climbs and is freed again is not called flat.
``rise_mb`` (max - the window's first sample, per process too) says who grew.
"""

from __future__ import annotations

from typing import Any

#: the live hour's bound: flat within 50 MB after the first ten minutes (docs/long_runs.md)
FLAT_WITHIN_MB = 50.0
#: the warm-up left out of the verdict, seconds
FLAT_AFTER_S = 600.0


def memory_flat(rows: list[dict[str, Any]], after_s: float = FLAT_AFTER_S, within_mb: float = FLAT_WITHIN_MB,
                until_s: float | None = None) -> dict[str, Any]:
    """The verdict over the window (module docstring): ``flat`` when ``range_mb <= within_mb``;
    ``flat`` None (no verdict, not a made-up one) when no sample lies in the window."""
    later = [r for r in rows if r["t_s"] >= after_s and (until_s is None or r["t_s"] <= until_s)]
    out: dict[str, Any] = {"after_s": after_s, "until_s": until_s, "within_mb": within_mb, "samples": len(later)}
    if not later:
        return {**out, "range_mb": None, "flat": None}
    totals = [r["rss_total_mb"] for r in later]
    base = later[0].get("rss_mb") or {}
    by_process = {}
    for name, first in base.items():
        vals = [r["rss_mb"][name] for r in later if (r.get("rss_mb") or {}).get(name) is not None]
        if vals and first is not None:
            by_process[name] = round(max(vals) - first, 1)
    span = round(max(totals) - min(totals), 1)
    return {**out, "range_mb": span, "flat": span <= within_mb, "first_mb": totals[0], "last_mb": totals[-1],
            "min_mb": min(totals), "max_mb": max(totals), "rise_mb": round(max(totals) - totals[0], 1),
            "rise_mb_by_process": by_process}
