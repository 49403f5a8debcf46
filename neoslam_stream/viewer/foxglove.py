"""A run served over the Foxglove WebSocket protocol, with the foxglove-sdk package.

``neoslam run --foxglove`` and ``neoslam view RUN_DIR --foxglove`` (docs/foxglove.md). A
:class:`FoxgloveView` has the calls of the rerun :class:`~.recording.RunView` (image, template,
pose, ground truth, odometry, stage stats, the map, log lines), so the live feed (live.py) and the
replay of a run folder (replay.py) drive either. It publishes :data:`TOPICS`: Foxglove's own
schemas (protobuf, from the SDK) for what its panels draw, and JSON with the JSON schemas of
:data:`JSON_SCHEMAS` for the run's own records. Per frame: the pose, the template; the paths and
the map at most every :data:`STATE_PERIOD_S` (wall clock) when they changed, and all of them again
every :data:`REPUBLISH_S` for a client that joined late; the camera as the caller thins it.

The server advertises no capability: a client can subscribe and nothing else (no publishing, no
parameters, no services). Each client gets its own bounded queue in the SDK (``backlog`` messages;
beyond, the oldest is dropped), so a slow or vanished client never slows this process, and this
process never slows the run (live.py).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from .recording import ViewStats

log = logging.getLogger("neoslam.viewer")

#: the frame of every pose and of the map
FRAME = "map"
#: the layout that shows these topics (package data): Foxglove's Layouts -> Import from file
LAYOUT = Path(__file__).with_name("foxglove_layout.json")
#: what to install when the SDK is missing
NEEDS = "the Foxglove server needs foxglove-sdk: pip install 'neoslam-stream[foxglove]' (or foxglove-sdk)"


def sdk_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("foxglove") is not None
#: topic -> schema name. Every channel is advertised when the server starts: one the SDK advertises
#: to a connected client later can meet that client's subscription before the SDK knows it ("Unknown
#: channel ID"), so the stages share one stats topic (plot one with ``/neoslam/stats{stage=="A"}.rate_hz``)
TOPICS: dict[str, str] = {
    "/camera/image": "foxglove.CompressedImage",
    "/neoslam/pose": "foxglove.PoseInFrame",
    "/neoslam/trajectory": "foxglove.PosesInFrame",
    "/neoslam/groundtruth": "foxglove.PosesInFrame",
    "/neoslam/odometry": "foxglove.PosesInFrame",
    "/neoslam/map": "foxglove.SceneUpdate",
    "/neoslam/log": "foxglove.Log",
    "/neoslam/template": "neoslam.Template",
    "/neoslam/loop_closure": "neoslam.LoopClosure",
    "/neoslam/run": "neoslam.RunProgress",
    "/neoslam/stats": "neoslam.StageStats",
}


def _object(props: dict[str, str], nullable: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"type": "object", "required": sorted(props),
            "properties": {k: {"type": [t, "null"] if k in nullable else t} for k, t in props.items()}}


#: the JSON schemas of the run's own records
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "neoslam.Template": _object({"frame": "integer", "stamp": "number", "template_id": "integer",
                                 "is_loop_closure": "boolean"}),
    "neoslam.LoopClosure": _object({"frame": "integer", "stamp": "number", "template_id": "integer",
                                    "exp_id": "integer", "x": "number", "y": "number"}, ("x", "y")),
    "neoslam.StageStats": _object({"stage": "string", "received": "integer", "processed": "integer",
                                   "rate_hz": "number", "tau_p50_ms": "number", "tau_p95_ms": "number",
                                   "queue_p50_ms": "number", "dropped": "integer", "errors": "integer",
                                   "cpu_percent": "number"}),
    "neoslam.RunProgress": _object({"frames_in": "integer", "frames_out": "integer", "behind": "integer",
                                    "loss": "number", "status": "string"}, ("loss",)),
}
#: seconds (wall clock) between two messages of a path or of the map, at most
STATE_PERIOD_S = 0.5
#: seconds between two sendings of every path and the map, for clients that joined since
REPUBLISH_S = 2.0
_LEVELS = {"DEBUG": "Debug", "INFO": "Info", "WARNING": "Warning", "ERROR": "Error", "CRITICAL": "Fatal"}


def _num(v: Any) -> float:
    """A figure as a float: 0 where it is missing or empty (a timeline.csv cell)."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return 0.0
    return f if math.isfinite(f) else 0.0


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port); a ValueError names what is wrong."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--foxglove takes HOST:PORT (e.g. 127.0.0.1:8765), not {text!r}")
    return host, int(port)


class ThinPath:
    """A path of (stamp, x, y, theta) that keeps at most about ``max_poses``: every ``stride``-th,
    the stride doubling when they would be more, and always the newest."""

    def __init__(self, max_poses: int) -> None:
        self.max_poses = max(2, max_poses)
        self.poses: list[tuple[float, float, float, float]] = []
        self.stride, self.seen = 1, 0
        self.last: tuple[float, float, float, float] | None = None

    def add(self, stamp: float, x: float, y: float, th: float) -> None:
        self.last = (stamp, x, y, th)
        if self.seen % self.stride == 0:
            self.poses.append(self.last)
            if len(self.poses) > self.max_poses:
                self.poses, self.stride = self.poses[::2], self.stride * 2
        self.seen += 1

    def all(self) -> list[tuple[float, float, float, float]]:
        if self.last is not None and (not self.poses or self.poses[-1] is not self.last):
            return [*self.poses, self.last]
        return list(self.poses)


class _Listener:
    """The server's callbacks: which clients subscribed (read-only: nothing else is handled)."""

    def __init__(self) -> None:
        self.clients: set[int] = set()
        self.subscribed = threading.Event()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.clients.add(int(client.id))
        self.subscribed.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        pass


class FoxgloveView:
    """The run's topics on a Foxglove WebSocket server at ``host:port`` (port 0: any free one)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "neoslam", image_max_side: int = 640,
                 jpeg_quality: int = 75, path_max_poses: int = 2000, backlog: int = 1024) -> None:
        try:
            import foxglove
            from foxglove import channels as ch
        except ImportError as exc:
            raise SystemExit(f"error: {NEEDS} ({exc})") from None

        self.fg, self.msgs = foxglove, foxglove.messages
        self.ctx = foxglove.Context()
        self.listener = _Listener()
        self.image_max_side, self.jpeg_quality = image_max_side, jpeg_quality
        self.stats = ViewStats()
        self.lock = threading.RLock()
        kw = {"context": self.ctx}
        self.channels: dict[str, Any] = {
            "/camera/image": ch.CompressedImageChannel("/camera/image", **kw),
            "/neoslam/pose": ch.PoseInFrameChannel("/neoslam/pose", **kw),
            **{t: ch.PosesInFrameChannel(t, **kw) for t in ("/neoslam/trajectory", "/neoslam/groundtruth",
                                                             "/neoslam/odometry")},
            "/neoslam/map": ch.SceneUpdateChannel("/neoslam/map", **kw),
            "/neoslam/log": ch.LogChannel("/neoslam/log", **kw),
            **{t: self._json_channel(t, TOPICS[t]) for t in ("/neoslam/template", "/neoslam/loop_closure",
                                                             "/neoslam/run", "/neoslam/stats")}}
        self.paths = {t: ThinPath(path_max_poses) for t in ("/neoslam/trajectory", "/neoslam/groundtruth",
                                                             "/neoslam/odometry")}
        self.changed: set[str] = set()
        self.sent_at: dict[str, float] = {}
        self.republished_at = time.monotonic()
        #: the map: experience id -> (x, y), links in order, loop-closure places
        self.exps: dict[int, tuple[float, float]] = {}
        self.links: dict[tuple[int, int], None] = {}
        self.closure_xy: list[tuple[float, float]] = []
        self.last_exp = -1
        #: a frame's pose (x, y, experience) for its loop closure, which may come before or after it
        self.frame_pose: dict[int, tuple[float, float, int]] = {}
        self.closures_waiting: dict[int, dict[str, Any]] = {}
        self.progress = {"frames_in": 0, "frames_out": 0, "behind": 0, "loss": None, "status": "running"}
        self.server = foxglove.start_server(name=name, host=host, port=port, capabilities=[],
                                            server_listener=self.listener, context=self.ctx,
                                            message_backlog_size=backlog)
        self.host, self.port = host, int(self.server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _json_channel(self, topic: str, schema: str) -> Any:
        data = json.dumps(JSON_SCHEMAS[schema]).encode()
        return self.fg.Channel(topic, schema=self.fg.Schema(name=schema, encoding="jsonschema", data=data),
                               message_encoding="json", context=self.ctx)

    def _send(self, topic: str, msg: Any) -> None:
        self.channels[topic].log(msg)
        self.stats.messages[topic] = self.stats.messages.get(topic, 0) + 1

    # ------------------------------------------------------------------ message builders
    def _stamp(self, t: float | None) -> Any:
        t = 0.0 if t is None or not math.isfinite(t) else max(0.0, float(t))
        sec = math.floor(t)
        return self.msgs.Timestamp(int(sec), min(999_999_999, int(round((t - sec) * 1e9))))

    def _pose(self, x: float, y: float, th: float) -> Any:
        m = self.msgs
        return m.Pose(position=m.Vector3(x=float(x), y=float(y), z=0.0),
                      orientation=m.Quaternion(x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)))

    def _points(self, xy: list[tuple[float, float]]) -> list[Any]:
        return [self.msgs.Point3(x=float(x), y=float(y), z=0.0) for x, y in xy]

    def _color(self, r: float, g: float, b: float, a: float = 1.0) -> Any:
        return self.msgs.Color(r=r, g=g, b=b, a=a)

    # ------------------------------------------------------------------ what the run gives
    def image(self, frame: int, stamp: float | None, rgb: np.ndarray) -> None:
        """A camera frame (RGB pixels): JPEG of at most ``image_max_side`` pixels, when a client
        watches the camera."""
        from ..runtime.camera_log import encode_jpeg

        if not self.channels["/camera/image"].has_sinks():
            return
        jpeg = encode_jpeg(np.asarray(rgb)[:, :, ::-1], self.image_max_side, self.jpeg_quality)
        if jpeg is not None:
            self.jpeg(frame, stamp, jpeg)

    def jpeg(self, frame: int, stamp: float | None, data: bytes) -> None:
        """A camera frame already JPEG-encoded (camera.zip)."""
        with self.lock:
            self._send("/camera/image", self.msgs.CompressedImage(timestamp=self._stamp(stamp), frame_id="camera",
                                                                  data=bytes(data), format="jpeg"))
            self.stats.images += 1

    def template(self, frame: int, stamp: float | None, tid: int, loop: bool) -> None:
        with self.lock:
            self._send("/neoslam/template", {"frame": int(frame), "stamp": float(stamp or 0.0),
                                             "template_id": int(tid), "is_loop_closure": bool(loop)})
            self.stats.templates += 1
            if loop:
                event = {"frame": int(frame), "stamp": float(stamp or 0.0), "template_id": int(tid)}
                if frame in self.frame_pose:
                    self._closure(event, self.frame_pose[frame])
                else:
                    self.closures_waiting[int(frame)] = event

    def _closure(self, event: dict[str, Any], where: tuple[float, float, int] | None) -> None:
        x, y, exp = where if where is not None else (None, None, self.last_exp)
        self._send("/neoslam/loop_closure", {**event, "exp_id": int(exp), "x": x, "y": y})
        self.stats.loop_closures += 1
        if x is not None:
            self.closure_xy.append((x, y))
            self.changed.add("/neoslam/map")

    def pose(self, frame: int, stamp: float | None, pose: np.ndarray, exp_id: int = -1,
             local: np.ndarray | None = None) -> None:
        """The map's pose of the robot after ``frame``; with its experience and the pose in that
        experience's frame, the experience's place on the map now (relaxed as the map is)."""
        x, y, th = (float(v) for v in np.asarray(pose, dtype=np.float64)[:3])
        with self.lock:
            self._send("/neoslam/pose", self.msgs.PoseInFrame(timestamp=self._stamp(stamp), frame_id=FRAME,
                                                              pose=self._pose(x, y, th)))
            self.stats.poses += 1
            self.progress["frames_out"] += 1
            self.paths["/neoslam/trajectory"].add(float(stamp or 0.0), x, y, th)
            self.changed.add("/neoslam/trajectory")
            if len(self.frame_pose) > 4096:  # only recent frames are looked up (closures)
                self.frame_pose.clear()
            self.frame_pose[int(frame)] = (x, y, int(exp_id))
            if exp_id >= 0:
                if local is not None:  # pose = experience o local: the experience is where it is now
                    dx, dy, dth = (float(v) for v in np.asarray(local, dtype=np.float64)[:3])
                    te = th - dth
                    self.exps[int(exp_id)] = (x - math.cos(te) * dx + math.sin(te) * dy,
                                              y - math.sin(te) * dx - math.cos(te) * dy)
                else:
                    self.exps.setdefault(int(exp_id), (x, y))
                if self.last_exp >= 0 and exp_id != self.last_exp:
                    self.links[(self.last_exp, int(exp_id))] = None
                self.last_exp = int(exp_id)
                self.changed.add("/neoslam/map")
            event = self.closures_waiting.pop(int(frame), None)
            if event is not None:
                self._closure(event, self.frame_pose[int(frame)])
            self.tick()

    def groundtruth(self, frame: int | None, stamp: float | None, pose: np.ndarray) -> None:
        self._path("/neoslam/groundtruth", stamp, pose)
        self.stats.groundtruth += 1

    def odometry_pose(self, frame: int | None, stamp: float | None, pose: np.ndarray) -> None:
        self._path("/neoslam/odometry", stamp, pose)
        self.stats.odometry += 1

    def _path(self, topic: str, stamp: float | None, pose: np.ndarray) -> None:
        p = np.asarray(pose, dtype=np.float64)
        with self.lock:
            self.paths[topic].add(float(stamp or 0.0), float(p[0]), float(p[1]), float(p[2]))
            self.changed.add(topic)

    def experience_map(self, export: dict[str, Any], frame: int | None = None) -> None:
        """The whole map (map.json's form, or rows id, x, y): it replaces the one drawn so far."""
        from .recording import _map_links, _map_nodes

        nodes = _map_nodes(export)
        with self.lock:
            self.exps = {i: (x, y) for i, x, y in nodes}
            self.links = dict.fromkeys(_map_links(export))
            self.stats.map_nodes = len(nodes)
            self.changed.add("/neoslam/map")
            self.tick()

    def stage_stats(self, t_s: float, stage: str, rate_hz: float, st: dict[str, Any]) -> None:
        """A stage's figures (the monitor's: a worker's stats message, or a timeline.csv row)."""
        inputs = (st.get("inputs") or {}).values()
        dropped = st["dropped"] if "dropped" in st else sum(int(i.get("evicted", 0)) for i in inputs)
        row = {"stage": stage, "rate_hz": float(rate_hz),
               **{k: int(_num(st.get(k))) for k in ("received", "processed", "errors")}, "dropped": int(_num(dropped)),
               **{k: _num(st.get(k)) for k in ("tau_p50_ms", "tau_p95_ms", "queue_p50_ms", "cpu_percent")}}
        with self.lock:
            self._send("/neoslam/stats", row)
            self.stats.stats += 1
            self.stats.stages.add(stage)

    def stage_rate(self, t_s: float, stage: str, rate_hz: float) -> None:
        self.stage_stats(t_s, stage, rate_hz, {})

    def source_stats(self, st: dict[str, Any]) -> None:
        """The source's frames published: the run's progress (frames in, out, not yet out)."""
        with self.lock:
            self.progress["frames_in"] = int(st.get("frames_in") or 0)
            self.progress["behind"] = max(0, self.progress["frames_in"] - self.progress["frames_out"])
            self._send("/neoslam/run", dict(self.progress))

    def run_ended(self, report: dict[str, Any]) -> None:
        """The run's report: the closures still waiting, the paths and the map, and last its
        frames and loss (a client that sees ``status`` change has everything before it)."""
        with self.lock:
            for frame, event in sorted(self.closures_waiting.items()):  # their pose never came
                self._closure(event, self.frame_pose.get(frame))
            self.closures_waiting.clear()
            self.tick(force=True)
            loss = report.get("loss")
            self.progress.update(frames_in=int(report.get("frames_in") or self.progress["frames_in"]),
                                 loss=None if loss is None else float(loss), status=str(report.get("status") or "ended"))
            self.progress["behind"] = max(0, self.progress["frames_in"] - self.progress["frames_out"])
            self._send("/neoslam/run", dict(self.progress))

    def log_line(self, t: float, level: str, process: str, name: str, message: str) -> None:
        m = self.msgs
        lvl = getattr(m.LogLevel, _LEVELS.get(level.upper(), "Unknown"))
        with self.lock:
            self._send("/neoslam/log", m.Log(timestamp=self._stamp(t), level=lvl, message=message,
                                             name=f"{process}: {name}" if name else process))
            self.stats.log_lines += 1

    # ------------------------------------------------------------------ paths and the map
    def tick(self, force: bool = False) -> None:
        """Send the paths and the map that changed (at most every STATE_PERIOD_S), and all of
        them every REPUBLISH_S (a client that joined late sees them too)."""
        now = time.monotonic()
        with self.lock:
            again = force or now - self.republished_at >= REPUBLISH_S
            if again:
                self.republished_at = now
                self.changed |= {"/neoslam/map", *(t for t, p in self.paths.items() if p.seen)}
            for topic in sorted(self.changed):
                if not force and not again and now - self.sent_at.get(topic, 0.0) < STATE_PERIOD_S:
                    continue
                if not self.channels[topic].has_sinks():  # nobody watches it: built when someone does
                    continue
                self.changed.discard(topic)
                self.sent_at[topic] = now
                self._send(topic, self._map() if topic == "/neoslam/map" else self._poses(topic))

    def _poses(self, topic: str) -> Any:
        poses = self.paths[topic].all()
        return self.msgs.PosesInFrame(timestamp=self._stamp(poses[-1][0] if poses else 0.0), frame_id=FRAME,
                                      poses=[self._pose(x, y, th) for _, x, y, th in poses])

    def _map(self) -> Any:
        """The map as a scene: experiences (blue spheres), links (grey), links back to an older
        experience (red: loop closures) and the places where loops closed (red, hollow-looking)."""
        m = self.msgs
        ident = self._pose(0.0, 0.0, 0.0)
        size = m.Vector3(x=0.12, y=0.12, z=0.12)
        fwd, back = [], []
        for a, b in self.links:
            if a in self.exps and b in self.exps:
                (back if b < a else fwd).extend([self.exps[a], self.exps[b]])
        line = m.LinePrimitiveLineType.LineList

        def entity(eid: str, **prims: Any) -> Any:
            return m.SceneEntity(frame_id=FRAME, id=eid, **prims)

        blue, grey, red = self._color(0.2, 0.5, 1.0), self._color(0.6, 0.6, 0.6), self._color(1.0, 0.15, 0.15)
        return m.SceneUpdate(entities=[
            entity("experiences", spheres=[m.SpherePrimitive(pose=self._pose(x, y, 0.0), size=size, color=blue)
                                           for x, y in self.exps.values()]),
            entity("links", lines=[m.LinePrimitive(type=line, pose=ident, thickness=0.02, points=self._points(fwd),
                                                   color=grey)]),
            entity("loop_links", lines=[m.LinePrimitive(type=line, pose=ident, thickness=0.04,
                                                        points=self._points(back), color=red)]),
            entity("loop_closures", spheres=[m.SpherePrimitive(pose=self._pose(x, y, 0.0),
                                                               size=m.Vector3(x=0.25, y=0.25, z=0.02),
                                                               color=self._color(1.0, 0.15, 0.15, 0.35))
                                             for x, y in self.closure_xy])])

    def close(self) -> None:
        self.server.stop()
