"""The viewers of a run: rerun (``neoslam view RUN_DIR``, ``neoslam run --view``) and Foxglove
(``neoslam view RUN_DIR --foxglove``, ``neoslam run --foxglove``).

:func:`view` records a run into one rerun recording (``RUN_DIR/view.rrd``, and a window when a
display is there): live while the run runs (:mod:`.live`), else from its files (:mod:`.files`);
:mod:`.recording` is what is shown and where. :func:`serve_foxglove` serves a run over the Foxglove
WebSocket protocol (:mod:`.foxglove`): live while it runs, else played again from its files
(:mod:`.replay`). What each view holds: docs/end_to_end.md and docs/foxglove.md.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from .files import log_run_folder, log_timeline, timeline_rates
from .live import END_FILES, IMAGE_RING, LIVE_TOPICS, LiveFeed, LiveLogger, is_running, watch_live
from .recording import APP_ID, RunView, ViewStats

__all__ = ["APP_ID", "END_FILES", "FOXGLOVE_FILE", "IMAGE_RING", "LIVE_TOPICS", "LiveFeed", "LiveLogger", "RunView",
           "ViewStats", "has_display", "is_running", "log_run_folder", "log_timeline", "serve_foxglove",
           "timeline_rates", "view", "watch_live"]

#: what the Foxglove server of a run says about itself: its address, then what it served
FOXGLOVE_FILE = "foxglove.json"
#: seconds a live server keeps serving after its run ended (the final map reaches the clients)
FOXGLOVE_LINGER_S = 2.0

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
    _wait_for_run(run_dir, wait_s)
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
            _require_outputs(run_dir)
            log_run_folder(run_dir, rv)
    finally:
        rv.close()
    return rv.stats


def _wait_for_run(run_dir: Path, wait_s: float) -> None:
    """Wait up to ``wait_s`` for the run to start (its endpoints.json); the folder must exist."""
    deadline = time.monotonic() + wait_s
    while not (run_dir / "endpoints.json").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"no run folder {run_dir}")


def _require_outputs(run_dir: Path) -> None:
    """A run folder that is not running must hold a run's outputs to be shown."""
    if not any((run_dir / f).exists() for f in ("templates.csv", "trajectory.tum", "timeline.csv")):
        raise FileNotFoundError(f"{run_dir} has no run outputs (templates.csv, trajectory.tum, timeline.csv) "
                                f"and no running run (endpoints.json)")


def foxglove_settings(run_dir: Path) -> Any:
    """The run's ``foxglove`` config section (its config.yaml), or the defaults."""
    import yaml

    from ..config import FoxgloveConfig

    try:
        section = (yaml.safe_load((run_dir / "config.yaml").read_text()) or {}).get("foxglove") or {}
        return FoxgloveConfig(**section)
    except (OSError, ValueError, TypeError, AttributeError, yaml.YAMLError):
        return FoxgloveConfig()


def serve_foxglove(run_dir: str | Path, listen: str, speed: float = 1.0, duration: float | None = None,
                   wait_s: float = 0.0, say: Any = print) -> ViewStats:
    """``neoslam view RUN_DIR --foxglove HOST:PORT``: serve the run over the Foxglove WebSocket
    protocol, live until it ends (``neoslam run --foxglove`` starts this with the run), or a
    finished run's files played again at ``speed`` times source time once a client subscribed,
    then kept until Ctrl-C or ``duration`` seconds. A live run's first frame waits for the first
    client (``foxglove.wait_for_client_s``, bounded). ``foxglove.json`` in the run folder gives the
    address, then what was served."""
    from .foxglove import LAYOUT, FoxgloveView, parse_listen
    from .replay import play, run_events

    run_dir = Path(run_dir)
    host, port = parse_listen(listen)
    _wait_for_run(run_dir, wait_s)
    live = is_running(run_dir)
    if not live:
        _require_outputs(run_dir)
    cfg = foxglove_settings(run_dir)
    fv = FoxgloveView(host, port, f"neoslam {run_dir.name}", cfg.image_max_side, cfg.jpeg_quality,
                      cfg.path_max_poses, cfg.backlog)
    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("Foxglove server on %s: whoever reaches this port sees the run (read-only)", host)
    info: dict[str, Any] = {"url": fv.url, "pid": os.getpid(), "live": live, "layout": str(LAYOUT),
                            "status": "serving"}
    (run_dir / FOXGLOVE_FILE).write_text(json.dumps(info, indent=2))
    say(f"Foxglove: serving {run_dir} on {fv.url} (Open connection -> Foxglove WebSocket; "
        f"layout: {LAYOUT})", flush=True)
    end = None if duration is None else time.monotonic() + duration
    parent = os.getppid()

    def stop() -> bool:  # the time is up, or the process that started this one is gone
        return (end is not None and time.monotonic() >= end) or os.getppid() != parent

    try:
        if live:
            def first_client() -> None:  # the run's first frame waits for it (run.wait_for), bounded
                if cfg.wait_for_client_s > 0:
                    say(f"Foxglove: the run starts when a client subscribes (at most {cfg.wait_for_client_s:g} s)",
                        flush=True)
                    if fv.listener.subscribed.wait(cfg.wait_for_client_s):
                        time.sleep(0.3)  # its subscriptions to the other topics, sent with the first

            watch_live(run_dir, fv, duration, image_interval_s=1.0 / cfg.image_hz, announce="foxglove", stop=stop,
                       ready=first_client)
            time.sleep(FOXGLOVE_LINGER_S)
        else:
            while not fv.listener.subscribed.wait(0.2):  # the replay starts for its first client
                if stop():
                    break
            time.sleep(0.5)  # the client subscribes to every topic the server advertised
            play(run_events(run_dir), fv, speed, stop)
            while not stop():
                fv.tick()
                time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        fv.close()
        info.update(status="ended", clients=len(fv.listener.clients), **fv.stats.as_dict())
        try:
            (run_dir / FOXGLOVE_FILE).write_text(json.dumps(info, indent=2))
        except OSError as exc:
            log.warning("%s not written: %s", run_dir / FOXGLOVE_FILE, exc)
    return fv.stats
