"""One rerun recording of a run: what the viewer shows, and under which entity path.

``camera/image`` (I_t: live, or the run folder's thinned camera.zip), ``template/id`` and
``template/loop_closure`` (and one ``events`` line per closure), ``log`` (the run's log lines),
``map/trajectory``, ``map/groundtruth``, ``map/odometry``, ``map/loop_closures``, ``map/robot``,
``map/experiences`` and ``map/links`` (map.json), ``stats/<stage>/rate_hz``. Poses are
logged one point per frame on the ``frame`` timeline (and ``stamp``); the blueprint shows every
point up to the time cursor, so the map grows as the cursor moves without logging the path again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: the rerun application id of every recording the viewer makes
APP_ID = "neoslam"


def _rerun() -> Any:
    try:
        import rerun as rr
    except ImportError as exc:  # a clear line instead of a traceback
        raise SystemExit(f"error: the viewer needs rerun-sdk ({exc}); pip install 'neoslam-stream[view]' (or rerun-sdk)") from None
    return rr


@dataclass
class ViewStats:
    """What the viewer logged, per kind; ``images_dropped``: images it had no time for;
    ``images_thinned``: images it let pass on purpose (a viewer's camera rate); ``messages_dropped``:
    other messages it had no room for; ``messages``: per topic, what a Foxglove server sent."""

    images: int = 0
    images_dropped: int = 0
    images_thinned: int = 0
    messages_dropped: int = 0
    log_lines: int = 0
    templates: int = 0
    loop_closures: int = 0
    poses: int = 0
    groundtruth: int = 0
    odometry: int = 0
    stats: int = 0
    bad_messages: int = 0
    map_nodes: int = 0
    stages: set[str] = field(default_factory=set)
    messages: dict[str, int] = field(default_factory=dict)

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
                         rrb.TextLogView(origin="events", name="loop closures"),
                         rrb.TextLogView(origin="log", name="log")),
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

    def jpeg(self, frame: int, stamp: float | None, data: bytes) -> None:
        """A camera frame as JPEG bytes (the run folder's camera.zip)."""
        self._at(frame, stamp)
        self.rec.log("camera/image", self.rr.EncodedImage(contents=data, media_type="image/jpeg"))
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

    def pose(self, frame: int, stamp: float | None, pose: np.ndarray, exp_id: int = -1,
             local: np.ndarray | None = None) -> None:
        """The experience map's pose (x, y, theta) of ``frame`` (its experience and the pose in
        that experience's frame are not shown here)."""
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

    def stage_stats(self, t_s: float, stage: str, rate_hz: float, st: dict[str, Any]) -> None:
        """A stage's figures: its rate is shown."""
        self.stage_rate(t_s, stage, rate_hz)

    def source_stats(self, st: dict[str, Any]) -> None:
        """The source's figures: not shown."""

    def run_ended(self, report: dict[str, Any]) -> None:
        """The run's report: not shown (it is in the run folder)."""

    def log_line(self, t: float, level: str, process: str, name: str, message: str) -> None:
        """One log line of the run's processes (``log`` in the text views)."""
        self.rec.reset_time()
        self.rec.set_time("wall_clock", timestamp=float(t))
        self.rec.log("log", self.rr.TextLog(f"{process}: {message}", level=level))
        self.stats.log_lines += 1

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

    def tick(self) -> None:
        """Called now and then while watching a live run: nothing to do for a recording."""

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
