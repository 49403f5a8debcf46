"""What a run computes, as standard ROS 2 messages: published live over zenoh, and written to MCAP.

:class:`Ros2Messages` turns the recorder's topics (``visual_template``, ``experience_map/pose``,
``experience_map/map``) into ROS 2 messages under ``prefix`` (``/neoslam``), in ``frame_id``:
``odom``, ``pose``, ``path``, ``map_markers``, ``template_id``, ``loop_closure`` (types and
meanings: docs/ros2.md). It knows no algorithm, only those messages' fields. Until the run's end
the markers are drawn from the poses; the experience map's final, relaxed map then replaces them.

CDR comes from rosbags' serialiser with the message definitions of ``distro``. Key formats:
``bridge`` (as zenoh-bridge-ros2dds: the topic without its leading slash, no attachment) and
``rmw`` (as an rmw_zenoh node: domain, topic, DDS type and RIHS01 type hash, with an attachment
and liveliness tokens, so ROS 2 tools can see the publishers; :mod:`neoslam_stream.sources.rmw_zenoh`).
:class:`Ros2OutNode` publishes them in a run, an observer next to the experience map;
:func:`mcap_bytes` writes the same messages as the recorder's ``outputs.mcap``.
"""

from __future__ import annotations

import io
import json
import logging
import math
import secrets
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .run_rows import PoseRow, TemplateRow
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, VISUAL_TEMPLATE

log = logging.getLogger("neoslam.ros2_out")

#: role -> (topic name under the prefix, ROS 2 message type)
TOPICS: dict[str, tuple[str, str]] = {
    "odom": ("odom", "nav_msgs/msg/Odometry"),
    "pose": ("pose", "geometry_msgs/msg/PoseStamped"),
    "path": ("path", "nav_msgs/msg/Path"),
    "markers": ("map_markers", "visualization_msgs/msg/MarkerArray"),
    "template_id": ("template_id", "std_msgs/msg/Int32"),
    "loop_closure": ("loop_closure", "std_msgs/msg/String"),
}
DISTROS = ("humble", "jazzy", "kilted")
#: visualization_msgs/Marker constants (the message's own)
SPHERE_LIST, LINE_LIST, ADD, DELETE = 7, 5, 0, 2
#: rmw_zenoh's compact QoS of a reliable, volatile publisher keeping the last 10 (its liveliness tokens)
RMW_QOS = "::,10:,:,:,,"

_STORES: dict[str, Any] = {}


def typestore(distro: str = "jazzy") -> Any:
    """rosbags' type store of a ROS 2 distribution (message definitions and CDR)."""
    if distro not in DISTROS:
        raise ValueError(f"distro {distro!r} is not one of {', '.join(DISTROS)}")
    if distro not in _STORES:
        from rosbags.typesys import Stores, get_typestore

        _STORES[distro] = get_typestore(getattr(Stores, f"ROS2_{distro.upper()}"))
    return _STORES[distro]


def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The hash chunk of an rmw_zenoh key: RIHS01 (REP-2011) from the type description, or
    ``TypeHashNotSupported`` on Humble, whose rmw_zenoh has no type hashes."""
    return "TypeHashNotSupported" if distro == "humble" else typestore(distro).hash_rihs01(msgtype)


@dataclass
class RosOut:
    """One ROS 2 message to send: topic name, type, the message object, source time (s)."""

    topic: str
    msgtype: str
    msg: Any
    stamp: float


class Ros2Messages:
    """Our messages in, ROS 2 messages (:class:`RosOut`) out. Plain state, no I/O."""

    def __init__(self, frame_id: str = "map", child_frame_id: str = "base_link", prefix: str = "/neoslam",
                 distro: str = "jazzy", map_period_s: float = 1.0, marker_scale: float = 0.1,
                 path_max_poses: int = 1000) -> None:
        self.ts = typestore(distro)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self.prefix = "/" + prefix.strip("/") if prefix.strip("/") else ""
        self.map_period_s = float(map_period_s)
        self.marker_scale = float(marker_scale)
        #: the path's PoseStamped messages: every ``_stride``-th pose, at most ``path_max_poses``
        #: (the stride doubles when they would be more), so a long run's path costs the same to
        #: send as a short one's
        self.path: list[Any] = []
        self.path_max_poses = max(2, int(path_max_poses))
        self._stride, self._n_poses = 1, 0
        self._last_pose: Any = None
        self._last_stamp = 0.0
        #: experience id -> (x, y): where the robot first was in it (until the final map)
        self.exps: dict[int, tuple[float, float]] = {}
        self.links: dict[tuple[int, int], None] = {}  # ordered set
        self.last_exp = -1
        self.last_map_stamp: float | None = None
        self.changed = False
        self.exp_of_frame: dict[int, int] = {}

    def topic(self, role: str) -> str:
        return f"{self.prefix}/{TOPICS[role][0]}"

    def _out(self, role: str, msg: Any, stamp: float) -> RosOut:
        return RosOut(self.topic(role), TOPICS[role][1], msg, stamp)

    # ----------------------------------------------------------------- builders
    def _time(self, t: float) -> Any:
        sec = math.floor(t)
        nsec = min(int(round((t - sec) * 1e9)), 999_999_999)
        return self.ts.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nsec)

    def _header(self, t: float) -> Any:
        return self.ts.types["std_msgs/msg/Header"](stamp=self._time(t), frame_id=self.frame_id)

    def _pose(self, x: float, y: float, th: float) -> Any:
        T = self.ts.types
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)))

    def _pose_stamped(self, t: float, x: float, y: float, th: float) -> Any:
        return self.ts.types["geometry_msgs/msg/PoseStamped"](header=self._header(t), pose=self._pose(x, y, th))

    def _odometry(self, t: float, x: float, y: float, th: float) -> Any:
        T = self.ts.types
        V3 = T["geometry_msgs/msg/Vector3"]
        zero = V3(x=0.0, y=0.0, z=0.0)
        return T["nav_msgs/msg/Odometry"](
            header=self._header(t), child_frame_id=self.child_frame_id,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(x, y, th), covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)))

    def _marker(self, t: float, ns: str, kind: int, points: list[tuple[float, float]], rgba: tuple, scale: float) -> Any:
        T = self.ts.types
        V3, P = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Point"]
        fields: dict[str, Any] = {
            "header": self._header(t), "ns": ns, "id": 0, "type": kind, "action": ADD if points else DELETE,
            "pose": self._pose(0.0, 0.0, 0.0), "scale": V3(x=scale, y=scale, z=scale),
            "color": T["std_msgs/msg/ColorRGBA"](r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
            "lifetime": T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), "frame_locked": False,
            "points": [P(x=float(x), y=float(y), z=0.0) for x, y in points], "colors": [],
            "text": "", "mesh_resource": "", "mesh_use_embedded_materials": False}
        names = [f[0] for f in self.ts.fielddefs["visualization_msgs/msg/Marker"][1]]
        if "texture" in names:  # Jazzy and later: texture and mesh file fields, all empty
            fields.update(texture_resource="", uv_coordinates=[],
                          texture=T["sensor_msgs/msg/CompressedImage"](header=self._header(t), format="",
                                                                       data=np.zeros(0, np.uint8)),
                          mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)))
        return T["visualization_msgs/msg/Marker"](**fields)

    # ----------------------------------------------------------------- inputs
    def on_template(self, frame: int, stamp: float, template_id: int, is_loop_closure: bool) -> list[RosOut]:
        """A frame's visual template: its id, and a loop-closure event when it was recognised."""
        out = [self._out("template_id", self.ts.types["std_msgs/msg/Int32"](data=int(template_id)), stamp)]
        if is_loop_closure:
            event = {"frame": int(frame), "stamp": float(stamp), "template_id": int(template_id),
                     "exp_id": self.exp_of_frame.get(frame, self.last_exp)}
            out.append(self._out("loop_closure", self.ts.types["std_msgs/msg/String"](data=json.dumps(event)), stamp))
        return out

    def on_pose(self, frame: int, stamp: float, x: float, y: float, th: float, exp_id: int) -> list[RosOut]:
        """The experience-map pose of a frame: Odometry and PoseStamped, and now and then the path
        and the map drawn so far."""
        pose = self._pose_stamped(stamp, x, y, th)  # also the path's (built once: paths are long)
        out = [self._out("odom", self._odometry(stamp, x, y, th), stamp), self._out("pose", pose, stamp)]
        if self._n_poses % self._stride == 0:
            self.path.append(pose)
            if len(self.path) > self.path_max_poses:
                self.path = self.path[::2]
                self._stride *= 2
        self._n_poses += 1
        self._last_pose, self._last_stamp = pose, stamp
        if len(self.exp_of_frame) > 4096:  # only recent frames are looked up (loop-closure events)
            self.exp_of_frame.clear()
        self.exp_of_frame[frame] = exp_id
        if exp_id >= 0:
            if exp_id not in self.exps:
                self.exps[exp_id] = (x, y)
            if self.last_exp >= 0 and exp_id != self.last_exp:
                self.links[(self.last_exp, exp_id)] = None
            self.last_exp = exp_id
        self.changed = True
        if self.last_map_stamp is None or stamp - self.last_map_stamp >= self.map_period_s:
            out.extend(self.map_messages(stamp))
        return out

    def on_map(self, stamp: float, export: dict[str, Any]) -> list[RosOut]:
        """The experience map's own map at the end of a run (relaxed positions, every link)."""
        try:
            exps = {int(n["id"]): (float(n["x"]), float(n["y"])) for n in export.get("nodes", [])}
            links = {(int(lk["from"]), int(lk["to"])): None for lk in export.get("links", [])}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            log.warning("ros2 output: the map message is not a map export (%s: %s); the drawn map stays",
                        type(exc).__name__, exc)
            return []
        self.exps, self.links = exps, links
        self.changed = True
        return self.map_messages(stamp)

    def finish(self, stamp: float | None = None) -> list[RosOut]:
        """The path and map once more if they changed since they were last sent."""
        if not self.changed:
            return []
        return self.map_messages(stamp if stamp is not None else self._last_stamp)

    # ----------------------------------------------------------------- the map
    def map_messages(self, stamp: float) -> list[RosOut]:
        """nav_msgs/Path of the poses so far (every one, or every ``_stride``-th and the last),
        and the MarkerArray of the map."""
        self.last_map_stamp, self.changed = stamp, False
        T = self.ts.types
        poses = list(self.path)
        if self._last_pose is not None and (not poses or poses[-1] is not self._last_pose):
            poses.append(self._last_pose)
        path = T["nav_msgs/msg/Path"](header=self._header(stamp), poses=poses)
        fwd, closures = [], []
        for a, b in self.links:
            if a in self.exps and b in self.exps:
                # a link to an experience older than where the robot came from closes a loop
                (closures if b < a else fwd).extend([self.exps[a], self.exps[b]])
        s = self.marker_scale
        markers = [self._marker(stamp, "experiences", SPHERE_LIST, list(self.exps.values()), (0.2, 0.5, 1.0, 1.0), s),
                   self._marker(stamp, "links", LINE_LIST, fwd, (0.6, 0.6, 0.6, 1.0), s * 0.3),
                   self._marker(stamp, "loop_closures", LINE_LIST, closures, (1.0, 0.1, 0.1, 1.0), s * 0.5)]
        return [self._out("path", path, stamp),
                self._out("markers", T["visualization_msgs/msg/MarkerArray"](markers=markers), stamp)]

    def serialize(self, out: RosOut) -> bytes:
        """CDR bytes with their 4-byte encapsulation header, as a ROS 2 publisher sends them."""
        return bytes(self.ts.serialize_cdr(out.msg, out.msgtype))

    def msgdef(self, msgtype: str) -> str:
        """The ROS 2 message definition with its dependencies (an MCAP ``ros2msg`` schema)."""
        return self.ts.generate_msgdef(msgtype, ros_version=2)[0]


def replay(conv: Ros2Messages, templates: list[TemplateRow], trajectory: list[PoseRow],
           map_export: dict[str, Any] | None) -> Iterator[RosOut]:
    """The messages of a whole run from the run folder's rows, in frame order, the template of a
    frame before its pose, then the final map."""
    events = sorted([(r.frame, 0, r) for r in templates] + [(r.frame, 1, r) for r in trajectory],
                    key=lambda e: (e[0], e[1]))
    for _, kind, r in events:
        if kind == 0:
            yield from conv.on_template(r.frame, r.stamp, r.template_id, bool(r.is_loop_closure))
        else:
            yield from conv.on_pose(r.frame, r.stamp, r.x, r.y, r.theta, r.exp_id)
    last = max([r.stamp for r in trajectory] + [r.stamp for r in templates] + [0.0])
    if map_export is not None:
        yield from conv.on_map(last, map_export)
    yield from conv.finish(last)


def mcap_bytes(conv: Ros2Messages, outs: Iterable[RosOut]) -> bytes:
    """An MCAP file (ros2msg schemas, CDR messages, zstd chunks) of ``outs``, serialised one by
    one as they come; log and publish times are the messages' source stamps."""
    from mcap.writer import CompressionType, Writer

    buf = io.BytesIO()
    w = Writer(buf, compression=CompressionType.ZSTD)
    w.start(profile="ros2", library="neoslam-stream")
    channels: dict[str, int] = {}
    schemas: dict[str, int] = {}
    for seq, o in enumerate(outs):
        if o.topic not in channels:
            if o.msgtype not in schemas:
                schemas[o.msgtype] = w.register_schema(o.msgtype, "ros2msg", conv.msgdef(o.msgtype).encode())
            channels[o.topic] = w.register_channel(o.topic, "cdr", schemas[o.msgtype])
        t = max(0, int(round(o.stamp * 1e9)))
        w.add_message(channels[o.topic], log_time=t, data=conv.serialize(o), publish_time=t, sequence=seq)
    w.finish()
    return buf.getvalue()


# --------------------------------------------------------------------------- live output

def _mangle(name: str) -> str:
    return name.replace("/", "%")


class Ros2OutNode(Node):
    """Publishes the run's outputs as ROS 2 messages on the run's zenoh session (``format``:
    ``bridge``, ``rmw`` or ``both``; see the module docstring). An observer: it changes nothing in
    the pipeline, and a slow or absent ROS 2 subscriber never slows it (samples are dropped)."""

    inputs = (VISUAL_TEMPLATE, EXPERIENCE_POSE, EXPERIENCE_MAP)
    outputs = ()
    unordered_inputs = (EXPERIENCE_MAP,)
    observer = True

    def __init__(self, format: str = "bridge", domain_id: int = 0, frame_id: str = "map",
                 child_frame_id: str = "base_link", prefix: str = "/neoslam", distro: str = "jazzy",
                 map_period_s: float = 1.0, marker_scale: float = 0.1, path_max_poses: int = 1000,
                 node_name: str = "neoslam") -> None:
        super().__init__()
        if format not in ("bridge", "rmw", "both"):
            raise ValueError(f"ros2_out format {format!r} must be bridge, rmw or both")
        self.formats = ("bridge", "rmw") if format == "both" else (format,)
        self.domain_id, self.distro, self.node_name = int(domain_id), distro, node_name
        self.conv = Ros2Messages(frame_id, child_frame_id, prefix, distro, map_period_s, marker_scale, path_max_poses)
        self._session: Any = None
        self._pubs: dict[tuple[str, str], Any] = {}
        self._seq: dict[str, int] = {}
        self._gid: dict[str, bytes] = {}
        self._tokens: list[Any] = []
        self.last_stamp = 0.0
        self.counters.update({"published": 0, "not_published": 0})

    # the host worker hands its session over once it is connected (runtime.worker)
    def bind_session(self, session: Any) -> None:
        self._session = session
        if "rmw" in self.formats:
            self._declare_node()

    def keys(self, topic: str, msgtype: str) -> dict[str, str]:
        """The key of ``topic`` in each of this node's formats."""
        from ..sources.rmw_zenoh import dds_type_name, topic_key

        out = {}
        if "bridge" in self.formats:
            out["bridge"] = topic.lstrip("/")
        if "rmw" in self.formats:
            out["rmw"] = topic_key(self.domain_id, topic, dds_type_name(msgtype), type_hash(msgtype, self.distro))
        return out

    def _declare_node(self) -> None:
        """rmw_zenoh's liveliness tokens (graph discovery) for this node and its publishers."""
        from ..sources.rmw_zenoh import dds_type_name

        zid = str(self._session.info.zid())
        base = f"@ros2_lv/{self.domain_id}/{zid}/0"
        node = f"%/%/{self.node_name}"  # no enclave, no namespace
        keys = [f"{base}/0/NN/{node}"]
        for i, (role, (_, msgtype)) in enumerate(TOPICS.items(), start=1):
            topic = self.conv.topic(role)
            keys.append(f"{base}/{i}/MP/{node}/{_mangle(topic)}/{dds_type_name(msgtype)}/"
                        f"{type_hash(msgtype, self.distro)}/{RMW_QOS}")
        for k in keys:
            try:
                self._tokens.append(self._session.liveliness().declare_token(k))
            except Exception as exc:  # discovery only: the data flows without it
                log.warning("ros2 output: liveliness token %s not declared: %s", k, exc)

    def _publish(self, outs: list[RosOut]) -> None:
        if self._session is None:
            self.counters["not_published"] += len(outs)
            return
        import zenoh

        from ..sources.rmw_zenoh import Attachment

        for o in outs:
            payload = self.conv.serialize(o)
            for fmt, key in self.keys(o.topic, o.msgtype).items():
                pub = self._pubs.get((fmt, o.topic))
                if pub is None:
                    pub = self._session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
                    self._pubs[(fmt, o.topic)] = pub
                    self._gid[o.topic] = self._gid.get(o.topic) or secrets.token_bytes(16)
                if fmt == "rmw":
                    self._seq[o.topic] = self._seq.get(o.topic, 0) + 1
                    att = Attachment(self._seq[o.topic], time.time_ns(), self._gid[o.topic]).encode()
                    pub.put(payload, attachment=att)
                else:
                    pub.put(payload)
                self.counters["published"] += 1

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if topic == VISUAL_TEMPLATE:
            outs = self.conv.on_template(msg.frame, msg.stamp, int(d["id"]), bool(d.get("is_loop_closure", False)))
        elif topic == EXPERIENCE_POSE:
            x, y, th = (float(v) for v in d["pose"])
            outs = self.conv.on_pose(msg.frame, msg.stamp, x, y, th, int(d.get("exp_id", -1)))
        else:
            export = d.get("export")
            if export is None:  # the arrays alone: nodes (id, x, y, theta, stamp), links (from, to)
                export = {"nodes": [{"id": n[0], "x": n[1], "y": n[2]} for n in np.asarray(d["nodes"]).tolist()],
                          "links": [{"from": a, "to": b} for a, b in np.asarray(d.get("links", np.zeros((0, 2))))
                                    .reshape(-1, 2).tolist()]}
            outs = self.conv.on_map(msg.stamp, export)
        self.last_stamp = max(self.last_stamp, msg.stamp)
        self._publish(outs)
        return []

    def flush(self) -> Output:
        self._publish(self.conv.finish(self.last_stamp))
        return []

    def info(self) -> dict[str, Any]:
        return {"formats": list(self.formats), "published": self.counters["published"]}

    def close(self) -> None:
        for tok in self._tokens:
            try:
                tok.undeclare()
            except Exception:  # the session is closed already
                pass
        self._tokens = []


def make_node(**params: Any) -> Ros2OutNode:
    return Ros2OutNode(**params)
