"""A live viewer of a run (``neoslam view RUN_DIR``, ``neoslam run --view``), recorded with rerun.

What it shows, each under its own entity path of one rerun recording:

* ``camera/image``: the camera frame I_t (live runs only: images are not stored in a run folder);
* ``template/id`` and ``template/loop_closure``: the visual template id of each frame (D's
  spatial-view cell, or RatSLAM's local-view cell) and, as 1, the frames that closed a loop;
  ``events`` has one text line per loop closure;
* ``map/trajectory`` (experience-map pose per frame), ``map/groundtruth``, ``map/odometry``
  (dead reckoning of the odometry, integrated as the source integrates it for odometry.tum),
  ``map/loop_closures`` (the pose of each closing frame), ``map/robot`` (the newest pose) and, once
  the map is published (map.json), ``map/experiences`` and ``map/links``;
* ``stats/<stage>/rate_hz``: the rate at which each stage processed messages, as the monitor's
  ``stats/<stage>`` messages (live) or ``timeline.csv`` (finished run) tell it.

Poses are logged one point per frame on the ``frame`` timeline (and ``stamp``, the source time);
the blueprint shows every point up to the time cursor, so the map grows as the cursor moves
without logging the whole path again for each frame.

A live viewer attaches in client mode to the run's router (``endpoints.json``, as ``neoslam
monitor``) and subscribes to ``image``, ``odom``, ``groundtruth``, ``visual_template``,
``experience_map/pose``, ``experience_map/map`` and ``stats/**``. Its zenoh callbacks only put
messages in queues: images in a ring of ``IMAGE_RING`` (the oldest dropped and counted, so a slow
viewer never back-pressures a lossless run through zenoh's blocking congestion control), the small
messages in an unbounded deque. One thread decodes and logs them. It ends when the run's
``report.json`` appears (the run is over), then logs the final map.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("neoslam.viewer")

#: images waiting to be logged; beyond this the oldest is dropped (counted in ``ViewStats``)
IMAGE_RING = 4
#: the rerun application id of every recording the viewer makes
APP_ID = "neoslam"


def _rerun() -> Any:
    try:
        import rerun as rr
    except ImportError as exc:  # a clear line instead of a traceback
        raise SystemExit(f"error: the viewer needs rerun-sdk ({exc}); pip install 'neoslam-stream[view]' (or rerun-sdk)") from None
    return rr


def has_display() -> bool:
    """Whether a viewer window can open here (a desktop session, or X11 / Wayland)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


@dataclass
class ViewStats:
    """What the viewer logged, per kind; ``images_dropped``: images it had no time for."""

    images: int = 0
    images_dropped: int = 0
    templates: int = 0
    loop_closures: int = 0
    poses: int = 0
    groundtruth: int = 0
    odometry: int = 0
    stats: int = 0
    bad_messages: int = 0
    map_nodes: int = 0
    stages: set[str] = field(default_factory=set)

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["stages"] = sorted(self.stages)
        return d


class RunView:
    """One rerun recording of a run: the logging calls the live and the file reader share.

    ``save``: the .rrd file to write; ``window``: also stream to a rerun viewer window it spawns.
    """

    def __init__(self, name: str, save: str | Path | None, window: bool = False) -> None:
        rr = self.rr = _rerun()
        self.rec = rr.RecordingStream(APP_ID, recording_id=name)
        blueprint = self._blueprint()
        sinks = []
        if save is not None:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(save)))
        if window:
            self.rec.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        if not sinks:
            raise ValueError("a view needs a file to save to or a window")
        self.rec.set_sinks(*sinks, default_blueprint=blueprint)
        self.stats = ViewStats()
        self._odo = [0.0, 0.0, 0.0]  # dead-reckoned x, y, theta
        #: x, y of each frame's pose, and closing frames whose pose has not arrived yet: a frame's
        #: template and its pose come on different topics, in either order
        self._xy: dict[int, tuple[float, float]] = {}
        self._closures_waiting: set[int] = set()

    def _blueprint(self) -> Any:
        rr = self.rr
        import rerun.blueprint as rrb

        everything = [rr.VisibleTimeRange("frame", start=rr.TimeRangeBoundary.infinite(),
                                          end=rr.TimeRangeBoundary.cursor_relative())]
        return rrb.Blueprint(rrb.Horizontal(
            rrb.Vertical(rrb.Spatial2DView(origin="camera", name="camera"),
                         rrb.TextLogView(origin="events", name="loop closures")),
            rrb.Spatial2DView(origin="map", name="experience map", time_ranges=everything),
            rrb.Vertical(rrb.TimeSeriesView(origin="template", name="template id"),
                         rrb.TimeSeriesView(origin="stats", name="stage rates (Hz)"))))

    # ------------------------------------------------------------------ time
    def _at(self, frame: int | None, stamp: float | None) -> None:
        self.rec.reset_time()
        if frame is not None:
            self.rec.set_time("frame", sequence=int(frame))
        if stamp is not None and math.isfinite(stamp):
            self.rec.set_time("stamp", duration=float(stamp))

    # ------------------------------------------------------------------ what is logged
    def image(self, frame: int, stamp: float | None, rgb: np.ndarray) -> None:
        self._at(frame, stamp)
        self.rec.log("camera/image", self.rr.Image(rgb))
        self.stats.images += 1

    def template(self, frame: int, stamp: float | None, tid: int, loop: bool) -> None:
        self._at(frame, stamp)
        self.rec.log("template/id", self.rr.Scalars(float(tid)))
        self.rec.log("template/loop_closure", self.rr.Scalars(1.0 if loop else 0.0))
        self.stats.templates += 1
        if loop:
            self.stats.loop_closures += 1
            self.rec.log("events", self.rr.TextLog(f"frame {frame}: loop closure on template {tid}"))
            if frame in self._xy:
                self._closure_point(frame, self._xy[frame])
            else:
                self._closures_waiting.add(int(frame))

    def _closure_point(self, frame: int, xy: tuple[float, float]) -> None:
        self._at(frame, None)
        self.rec.log("map/loop_closures", self.rr.Points2D([xy], colors=[(230, 60, 60)], radii=0.08))

    def pose(self, frame: int, stamp: float | None, pose: np.ndarray) -> None:
        """The experience map's pose (x, y, theta) of ``frame``."""
        p = np.asarray(pose, dtype=np.float64)
        self._at(frame, stamp)
        self.rec.log("map/trajectory", self.rr.Points2D([p[:2]], colors=[(40, 110, 230)], radii=0.03))
        self.rec.log("map/robot", self.rr.Arrows2D(origins=[p[:2]], vectors=[[0.3 * math.cos(p[2]),
                                                                               0.3 * math.sin(p[2])]]))
        self.stats.poses += 1
        xy = (float(p[0]), float(p[1]))
        self._xy[int(frame)] = xy
        if frame in self._closures_waiting:
            self._closures_waiting.discard(frame)
            self._closure_point(frame, xy)

    def groundtruth(self, frame: int | None, stamp: float | None, pose: np.ndarray) -> None:
        self._at(frame, stamp)
        self.rec.log("map/groundtruth", self.rr.Points2D([np.asarray(pose, dtype=np.float64)[:2]],
                                                         colors=[(60, 170, 60)], radii=0.03))
        self.stats.groundtruth += 1

    def odometry_pose(self, frame: int | None, stamp: float | None, pose: np.ndarray) -> None:
        self._at(frame, stamp)
        self.rec.log("map/odometry", self.rr.Points2D([np.asarray(pose, dtype=np.float64)[:2]],
                                                      colors=[(150, 150, 150)], radii=0.02))
        self.stats.odometry += 1

    def odometry_step(self, frame: int, stamp: float | None, vtrans: float, vrot: float, dt: float) -> None:
        """Integrate one odometry sample as the source does for odometry.tum (heading first)."""
        x, y, th = self._odo
        th += vrot * dt
        x += vtrans * dt * math.cos(th)
        y += vtrans * dt * math.sin(th)
        self._odo = [x, y, th]
        self.odometry_pose(frame, stamp, np.array([x, y, th]))

    def stage_rate(self, t_s: float, stage: str, rate_hz: float) -> None:
        """The rate (Hz) at which ``stage`` processed messages, at ``t_s`` seconds into the run."""
        self.rec.reset_time()
        self.rec.set_time("run_time", duration=float(t_s))
        self.rec.log(f"stats/{stage}/rate_hz", self.rr.Scalars(float(rate_hz)))
        self.stats.stats += 1
        self.stats.stages.add(stage)

    def experience_map(self, export: dict[str, Any], frame: int | None = None) -> None:
        """The map as map.json holds it: experiences (nodes) and the links between them."""
        nodes = _map_nodes(export)
        if not nodes:
            return
        self._at(frame, None)
        xy = {i: (x, y) for i, x, y in nodes}
        self.rec.log("map/experiences", self.rr.Points2D([v for v in xy.values()], colors=[(240, 160, 30)],
                                                         radii=0.06), static=frame is None)
        strips = [[xy[a], xy[b]] for a, b in _map_links(export) if a in xy and b in xy]
        if strips:
            self.rec.log("map/links", self.rr.LineStrips2D(strips, colors=[(240, 160, 30)]),
                         static=frame is None)
        self.stats.map_nodes = len(nodes)

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def _map_nodes(export: dict[str, Any]) -> list[tuple[int, float, float]]:
    out = []
    for i, e in enumerate(export.get("experiences") or export.get("nodes") or []):
        if isinstance(e, dict):
            out.append((int(e.get("id", i)), float(e["x_m"] if "x_m" in e else e["x"]),
                        float(e["y_m"] if "y_m" in e else e["y"])))
        else:  # a row (id, x, y, ...)
            out.append((int(e[0]), float(e[1]), float(e[2])))
    return out


def _map_links(export: dict[str, Any]) -> list[tuple[int, int]]:
    out = []
    for ln in export.get("links") or []:
        if isinstance(ln, dict):
            a = ln.get("exp_from_id", ln.get("from"))
            b = ln.get("exp_to_id", ln.get("to"))
        else:
            a, b = ln[0], ln[1]
        if a is not None and b is not None:
            out.append((int(a), int(b)))
    return out


# ---------------------------------------------------------------------- a finished run's files
def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _read_tum(path: Path) -> np.ndarray:
    """(stamp, x, y, yaw) rows of a TUM file; an empty (0, 4) array when it is missing or
    unreadable (then logged with its cause: a damaged file must not stop the rest being shown)."""
    if not path.exists():
        return np.zeros((0, 4))
    from .tum import read_tum

    try:
        return read_tum(path)
    except (OSError, ValueError) as exc:
        log.warning("%s not shown: %s", path, exc)
        return np.zeros((0, 4))


def log_run_folder(run_dir: str | Path, view: RunView) -> None:
    """Log what a run folder holds: templates.csv, trajectory.tum, groundtruth.tum, odometry.tum,
    map.json and the per-stage rates of timeline.csv. Each pose is put on the ``frame`` timeline
    through the stamp -> frame map of templates.csv (the stamps the recorder wrote with the frame
    numbers), and on ``stamp`` in any case."""
    run_dir = Path(run_dir)
    templates = _read_csv(run_dir / "templates.csv")
    frame_of: dict[str, int] = {}
    for row in templates:
        frame_of[f"{float(row['stamp']):.6f}"] = int(row["frame"])
    traj = _read_tum(run_dir / "trajectory.tum")
    for stamp, x, y, th in traj:
        view.pose(frame_of.get(f"{stamp:.6f}", -1) if frame_of else -1, stamp, np.array([x, y, th]))
    for row in templates:
        view.template(int(row["frame"]), float(row["stamp"]), int(row["template_id"]),
                      row.get("is_loop_closure", "0") not in ("0", "", "false", "False"))
    for stamp, x, y, th in _read_tum(run_dir / "groundtruth.tum"):
        view.groundtruth(frame_of.get(f"{stamp:.6f}"), stamp, np.array([x, y, th]))
    for stamp, x, y, th in _read_tum(run_dir / "odometry.tum"):
        view.odometry_pose(frame_of.get(f"{stamp:.6f}"), stamp, np.array([x, y, th]))
    log_timeline(run_dir / "timeline.csv", view)
    map_path = run_dir / "map.json"
    if map_path.exists():
        try:
            view.experience_map(json.loads(map_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("map.json not shown: %s", exc)


def timeline_rates(path: Path) -> list[tuple[float, str, float]]:
    """(t_s, stage, rate_hz) from timeline.csv: each stage's processed count difference over the
    time between two of its rows."""
    last: dict[str, tuple[float, int]] = {}
    out = []
    for row in _read_csv(path):
        try:
            t, stage, done = float(row["t_s"]), row["stage"], int(row["processed"])
        except (KeyError, ValueError):
            continue
        if stage in last and t > last[stage][0]:
            t0, n0 = last[stage]
            out.append((t, stage, (done - n0) / (t - t0)))
        last[stage] = (t, done)
    return out


def log_timeline(path: Path, view: RunView) -> None:
    for t, stage, rate in timeline_rates(path):
        view.stage_rate(t, stage, rate)


# ---------------------------------------------------------------------- a live run
#: the run's topics the live viewer subscribes to (the stats of every stage come on stats/**)
LIVE_TOPICS = ("image", "odom", "groundtruth", "visual_template", "experience_map/pose",
               "experience_map/map", "stats/**")


class LiveFeed:
    """Subscriptions to a running pipeline; callbacks only queue (see the module docstring)."""

    def __init__(self, run: str, connect: list[str]) -> None:
        from .runtime.bus import key_for, open_session

        self.session = open_session(listen=[], connect=connect, mode="client")
        self.images: deque[bytes] = deque(maxlen=IMAGE_RING)
        self.images_dropped = 0
        self.small: deque[tuple[str, bytes]] = deque()
        self.cond = threading.Condition()
        self.subs = []
        for topic in LIVE_TOPICS:
            self.subs.append(self.session.declare_subscriber(key_for(run, topic), self._callback(topic)))

    def _callback(self, topic: str) -> Any:
        def on(sample: Any) -> None:
            payload = sample.payload.to_bytes()
            with self.cond:
                if topic == "image":
                    if len(self.images) == self.images.maxlen:
                        self.images_dropped += 1
                    self.images.append(payload)
                else:
                    self.small.append((topic, payload))
                self.cond.notify()
        return on

    def take(self, timeout: float) -> tuple[list[tuple[str, bytes]], list[bytes]]:
        with self.cond:
            if not self.small and not self.images:
                self.cond.wait(timeout)
            small, self.small = list(self.small), deque()
            images = list(self.images)
            self.images.clear()
        return small, images

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


class LiveLogger:
    """Decodes the queued messages and logs them to a :class:`RunView`."""

    def __init__(self, view: RunView) -> None:
        # the nodes' topic declarations register their schemas: decoding validates them
        from .nodes import topics  # noqa: F401

        self.view = view
        self.t0 = time.monotonic()
        self.last_stats: dict[str, tuple[float, int]] = {}
        self._bad_logged = False

    def _bad(self, what: str, exc: Exception) -> None:
        self.view.stats.bad_messages += 1
        if not self._bad_logged:  # once: a stream of bad messages must not flood the log
            log.warning("viewer: skipping a bad %s message: %s", what, exc)
            self._bad_logged = True

    def image(self, payload: bytes) -> None:
        from .nodes.camera import decode_rgb
        from .runtime.messages import decode

        try:
            msg = decode(payload, expected_type="image")
            rgb = decode_rgb(msg)
        except ValueError as exc:  # MessageError and StageInputError are ValueErrors
            self._bad("image", exc)
            return
        self.view.image(msg.frame, msg.stamp, rgb)

    def message(self, topic: str, payload: bytes) -> None:
        from .runtime.messages import decode

        try:
            msg = decode(payload)
        except ValueError as exc:
            self._bad(topic, exc)
            return
        d = msg.data
        try:
            if topic == "visual_template":
                self.view.template(msg.frame, msg.stamp, int(d["id"]), bool(d.get("is_loop_closure")))
            elif topic == "experience_map/pose":
                self.view.pose(msg.frame, msg.stamp, np.asarray(d["pose"], dtype=np.float64))
            elif topic == "groundtruth":
                self.view.groundtruth(msg.frame, msg.stamp, np.asarray(d["pose"], dtype=np.float64))
            elif topic == "odom":
                self.view.odometry_step(msg.frame, msg.stamp, float(d["vtrans"]), float(d["vrot"]),
                                        float(d.get("dt") or 0.0))
            elif topic == "experience_map/map":
                if d.get("export"):
                    self.view.experience_map(d["export"], msg.frame)
            elif msg.type == "stats":
                self.stats(d)
        except (KeyError, TypeError, ValueError) as exc:
            self._bad(topic, exc)

    def stats(self, d: dict[str, Any]) -> None:
        stage = d.get("stage")
        if not isinstance(stage, str) or stage == "source" or "processed" not in d:
            return
        now = time.monotonic() - self.t0
        done = int(d["processed"])
        prev = self.last_stats.get(stage)
        self.last_stats[stage] = (now, done)
        if prev is not None and now > prev[0]:
            self.view.stage_rate(now, stage, (done - prev[1]) / (now - prev[0]))


def watch_live(run_dir: Path, view: RunView, duration: float | None = None,
               connect: list[str] | None = None) -> None:
    """Log a running pipeline until its report.json (or part.json) appears (the run ended),
    ``duration`` seconds pass or Ctrl-C; then log the final map from map.json when the run wrote one."""
    ep = json.loads((run_dir / "endpoints.json").read_text())
    feed = LiveFeed(ep["run"], list(ep["connect"]) + list(connect or []))
    logger = LiveLogger(view)
    t_end = None if duration is None else time.monotonic() + duration
    ended_at: float | None = None
    try:
        while t_end is None or time.monotonic() < t_end:
            small, images = feed.take(0.2)
            for topic, payload in small:
                logger.message(topic, payload)
            for payload in images:
                logger.image(payload)
            if not small and not images:
                if ended_at is None and _ended(run_dir):
                    ended_at = time.monotonic()
                if ended_at is not None and time.monotonic() - ended_at > 1.0:
                    break
    except KeyboardInterrupt:
        pass
    finally:
        view.stats.images_dropped = feed.images_dropped
        feed.close()
    map_path = run_dir / "map.json"
    if ended_at is not None and map_path.exists() and not view.stats.map_nodes:
        try:
            view.experience_map(json.loads(map_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("map.json not shown: %s", exc)


def _started(run_dir: Path) -> float:
    """When this run started (endpoints.json is written at start): a report older than that
    belongs to an earlier run in the same folder."""
    return (run_dir / "endpoints.json").stat().st_mtime


#: what a run writes into its folder when it ends: report.json (the host with the source), or
#: part.json (a host running only some stages of a run split over hosts: runtime/parts.py)
END_FILES = ("report.json", "part.json")


def _ended(run_dir: Path) -> bool:
    started = _started(run_dir)
    return any((run_dir / f).exists() and (run_dir / f).stat().st_mtime >= started for f in END_FILES)


def is_running(run_dir: Path) -> bool:
    """A run folder whose run has not ended: endpoints.json and no end file newer than it."""
    return (run_dir / "endpoints.json").exists() and not _ended(run_dir)


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
