"""The live viewer of a run (``neoslam view RUN_DIR``, ``neoslam run --view``), recorded with rerun.

:func:`view` records a run into one rerun recording (``RUN_DIR/view.rrd``, and a window when a
display is there): live while the run runs (:mod:`.live`), else from its files (:mod:`.files`);
:mod:`.recording` is what is shown and where. What each view holds: docs/end_to_end.md.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

from .files import log_run_folder, log_timeline, timeline_rates
from .live import END_FILES, IMAGE_RING, LIVE_TOPICS, LiveFeed, LiveLogger, is_running, watch_live
from .recording import APP_ID, RunView, ViewStats

__all__ = ["APP_ID", "END_FILES", "IMAGE_RING", "LIVE_TOPICS", "LiveFeed", "LiveLogger", "RunView", "ViewStats",
           "has_display", "is_running", "log_run_folder", "log_timeline", "timeline_rates", "view", "watch_live"]

log = logging.getLogger("neoslam.viewer")


def has_display() -> bool:
    """Whether a viewer window can open here (a desktop session, or X11 / Wayland)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def view(run_dir: str | Path, save: str | Path | None = None, window: bool | None = None,
         duration: float | None = None, wait_s: float = 0.0) -> ViewStats:
    """``neoslam view``: record (and show) a run, live while it runs, else from its files.

    ``save``: the .rrd to write (default ``RUN_DIR/view.rrd``); ``window``: open a rerun window
    (default: when a display is there and no ``save`` was given); ``wait_s``: wait this long for
    the run to start (``run --view`` starts the viewer with the run)."""
    run_dir = Path(run_dir)
    deadline = time.monotonic() + wait_s
    while not (run_dir / "endpoints.json").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run folder {run_dir}")
    if window is None:
        window = save is None and has_display()
    out = Path(save) if save is not None else run_dir / "view.rrd"
    rv = RunView(run_dir.name, out, window=window)
    try:
        live = is_running(run_dir)
        if live:
            try:
                watch_live(run_dir, rv, duration)
            except Exception as exc:  # zenoh: the router is gone (a run killed without its report)
                log.warning("cannot attach to the run in %s (%s); showing its files", run_dir, exc)
                live = False
        if not live:
            if not any((run_dir / f).exists() for f in ("templates.csv", "trajectory.tum", "timeline.csv")):
                raise FileNotFoundError(f"{run_dir} has no run outputs (templates.csv, trajectory.tum, "
                                        f"timeline.csv) and no running run (endpoints.json)")
            log_run_folder(run_dir, rv)
    finally:
        rv.close()
    return rv.stats
