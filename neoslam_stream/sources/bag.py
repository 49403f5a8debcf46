"""ROS 1 bags, ROS 2 bags (.db3 folders) and MCAP files through ``rosbags`` (no ROS installed).

Frames are the messages of ``image_topic`` (sensor_msgs Image or CompressedImage). Each frame
carries the wheel odometry of the interval since the previous frame (``odom_topic``, nav_msgs/Odometry
twist.linear.x and twist.angular.z as OpenRatSLAM reads them; each twist holds until the next one
and is integrated up to the frame's stamp, so the frames' vtrans*dt and vrot*dt sum to the
odometry) and the ground truth at the frame's stamp (``groundtruth_topic``: PoseStamped,
PoseWithCovarianceStamped, Odometry, or NavSatFix in local metres), interpolated linearly in time
between the samples around it; none more than ``groundtruth_max_gap_s`` outside their span.
Without an image topic, frames are the odometry (or ground-truth) messages: odometry-only runs of
the back end. Stamps are header stamps (the receive time when a header stamp is zero). A
ground-truth topic the bag lacks is a warning: the run goes on without ground truth. A bag
rosbags cannot open (an MCAP file or ROS 1 bag cut short) is read up to its first damaged
record (mcap_salvage.py, ros1_salvage.py). Details: docs/sources.md, "bag".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.pixels import decode_bounded, fit, needs_resize
from .base import Source, SourceFrame
from .imaging import DEFAULT_MAX_SIDE, ImageEncodingError, ros_image
from .params import ExistingPath, PositiveFloat, PositiveInt

EARTH_RADIUS = 6378137.0
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "nav_msgs/msg/Odometry", "sensor_msgs/msg/NavSatFix")
ROLE_TYPES = {"image": IMAGE_TYPES, "odom": ("nav_msgs/msg/Odometry",), "groundtruth": POSE_TYPES}


def _stamp(msg: Any, fallback_ns: int) -> float:
    h = getattr(msg, "header", None)
    if h is not None and (h.stamp.sec or h.stamp.nanosec):
        return h.stamp.sec + h.stamp.nanosec * 1e-9
    return fallback_ns * 1e-9


def _yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def interpolate_pose(table: np.ndarray, t: float, max_gap: float) -> tuple[float, float, float] | None:
    """(x, y, theta) at time ``t`` from an (n, 4) table of stamp, x, y, unwrapped theta sorted by
    stamp: linear between the two samples around ``t``; the end sample within ``max_gap`` seconds
    outside the table's span; None farther out."""
    if len(table) == 0:
        return None
    ts = table[:, 0]
    if t < ts[0] - max_gap or t > ts[-1] + max_gap:
        return None
    j = int(np.searchsorted(ts, t))
    if j == 0 or j == len(ts):
        row = table[min(j, len(ts) - 1)]
        return (float(row[1]), float(row[2]), float(math.remainder(row[3], 2 * math.pi)))
    a, b = table[j - 1], table[j]
    w = 0.0 if b[0] <= a[0] else (t - a[0]) / (b[0] - a[0])
    x, y, th = a[1:] + w * (b[1:] - a[1:])
    return (float(x), float(y), float(math.remainder(th, 2 * math.pi)))


def image_from_msg(msg: Any, msgtype: str, max_side: int | None = DEFAULT_MAX_SIDE) -> dict[str, Any]:
    """SourceFrame image fields of a sensor_msgs Image / CompressedImage: 16-bit and big-endian
    encodings become 8-bit frames, frames beyond ``max_side`` pixels are resized (:mod:`.imaging`).
    Raises :class:`~.imaging.ImageEncodingError` for an encoding or a layout that cannot be used."""
    if msgtype.endswith("CompressedImage"):
        fmt = "png" if "png" in str(msg.format).lower() else "jpeg"
        data = bytes(msg.data)
        if needs_resize(data, max_side):  # decoded here, at a reduced scale for a JPEG
            bgr = decode_bounded(data, max_side)
            if bgr is not None:
                return {"image": np.ascontiguousarray(bgr[:, :, ::-1]), "encoding": "rgb8"}
        return {"compressed": data, "format": fmt}
    img, enc = ros_image(msg.data, int(msg.height), int(msg.width), int(msg.step), str(msg.encoding),
                         bool(msg.is_bigendian))
    return {"image": np.ascontiguousarray(fit(img, max_side)), "encoding": enc}


class BagSource(Source):
    """Frames of a recorded bag (see the module docstring for what each frame carries).

    ``path``: a ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml`` + ``.db3``/``.mcap``) or a
    single ``.mcap`` file. ``image_topic`` / ``odom_topic`` / ``groundtruth_topic``: topic names
    (at least one; each is checked against the bag's topics and their types when the source is
    built). ``max_frames`` stops early. ``typestore``: the rosbags type store for bags that carry no
    message definitions (ROS 2). ``groundtruth_max_gap_s``: how far before the first / after the
    last ground-truth sample a frame still gets the nearest one. ``max_side``: frames whose long
    side exceeds it are resized. An image that cannot be used (an unsupported encoding, data
    shorter than its header says) is counted as a source error with its cause and skipped; its
    motion goes to the next frame.
    """

    def __init__(self, path: ExistingPath, image_topic: str | None = None, odom_topic: str | None = None,
                 groundtruth_topic: str | None = None, max_frames: PositiveInt | None = None,
                 typestore: str = "ROS2_HUMBLE", groundtruth_max_gap_s: PositiveFloat = 5.0,
                 max_side: PositiveInt | None = DEFAULT_MAX_SIDE) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"bag {self.path} does not exist")
        self.topics = {"image": image_topic, "odom": odom_topic, "groundtruth": groundtruth_topic}
        if not any(self.topics.values()):
            raise ValueError("name at least one of image_topic, odom_topic, groundtruth_topic")
        self._typestore = get_typestore(getattr(Stores, typestore))
        self.max_frames = max_frames
        self.max_side = max_side
        self.groundtruth_max_gap_s = groundtruth_max_gap_s
        self.salvaged: str | None = None
        self.salvaged_messages: int | None = None
        #: what the run goes on without (report.json's ``source.warnings``, said once in the log)
        self.warnings: list[str] = []
        self._open: Any = lambda: AnyReader([self.path], default_typestore=self._typestore)
        try:
            with self._open():
                pass
        except Exception as exc:
            self._salvage_or_raise(exc)
        with self._open() as reader:
            available = {c.topic: c.msgtype for c in reader.connections}
            for role, topic in self.topics.items():
                if role == "groundtruth" and topic and topic not in available and (image_topic or odom_topic):
                    self._without_groundtruth(topic)  # a user's own bag rarely has ground truth
                    continue
                if topic and topic not in available:
                    raise ValueError(f"{role} topic {topic!r} not in {self.path}; it has {sorted(available)}")
                if topic and available[topic] not in ROLE_TYPES[role]:
                    raise ValueError(f"{role} topic {topic!r} is {available[topic]}; a {role} topic must be one "
                                     f"of {', '.join(ROLE_TYPES[role])}")
            frame_topic = image_topic or odom_topic or groundtruth_topic
            count = sum(c.msgcount for c in reader.connections if c.topic == frame_topic)
            duration = max(1e-9, (reader.end_time - reader.start_time) * 1e-9)
        self.available = available
        self.length = min(count, max_frames) if max_frames else count
        self.rate_hz = count / duration if count > 1 else None

    def __iter__(self) -> Iterator[SourceFrame]:
        frame_topic = self.topics["image"] or self.topics["odom"] or self.topics["groundtruth"]
        wanted = {t for t in self.topics.values() if t}
        with self._open() as reader:
            table = self._groundtruth_table(reader) if self.topics["groundtruth"] else None
            if frame_topic != self.topics["groundtruth"]:
                wanted.discard(self.topics["groundtruth"])  # already in the table
            conns = [c for c in reader.connections if c.topic in wanted]
            frame = 0
            last_odom_t: float | None = None
            v = w = 0.0
            acc_d = acc_th = 0.0
            prev_frame_t: float | None = None
            for conn, t_ns, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                t = _stamp(msg, t_ns)
                if conn.topic == self.topics["odom"]:
                    if last_odom_t is not None and t > last_odom_t:
                        acc_d += v * (t - last_odom_t)
                        acc_th += w * (t - last_odom_t)
                    v, w = float(msg.twist.twist.linear.x), float(msg.twist.twist.angular.z)
                    last_odom_t = t
                if conn.topic != frame_topic:
                    continue
                fields: dict[str, Any] = {}
                if conn.topic == self.topics["image"]:
                    try:
                        fields = image_from_msg(msg, conn.msgtype, self.max_side)
                    except ImageEncodingError as exc:  # skipped before its motion is taken
                        self.record_error(f"image on {conn.topic} skipped: {exc}")
                        continue
                if last_odom_t is not None and conn.topic != self.topics["odom"] and t > last_odom_t:
                    acc_d += v * (t - last_odom_t)  # integrate up to the frame's stamp
                    acc_th += w * (t - last_odom_t)
                    last_odom_t = t
                dt = 0.0 if prev_frame_t is None else max(0.0, t - prev_frame_t)
                odom = None
                if self.topics["odom"] and last_odom_t is not None:
                    odom = (acc_d / dt, acc_th / dt, dt) if dt > 0 else (0.0, 0.0, 0.0)
                acc_d = acc_th = 0.0
                prev_frame_t = t
                gt = None if table is None else interpolate_pose(table, t, self.groundtruth_max_gap_s)
                yield SourceFrame(frame=frame, stamp=t, odom=odom, groundtruth=gt, **fields)
                frame += 1
                if self.max_frames and frame >= self.max_frames:
                    return

    def _without_groundtruth(self, topic: str) -> None:
        note = (f"ground-truth topic {topic!r} is not in {self.path.name}: running without ground truth "
                "(no evaluation; -p groundtruth_topic=null runs without it and without this warning)")
        logging.getLogger(__name__).warning("%s", note)
        self.warnings.append(note)
        self.topics["groundtruth"] = None

    def _salvage_or_raise(self, exc: Exception) -> None:
        """A bag rosbags cannot open: read what is left of a truncated MCAP file or ROS 1 bag
        (counted as one source error with its cause), or fail with a clear message."""
        from .mcap_salvage import MAGIC as MCAP_MAGIC
        from .mcap_salvage import SalvageMcapReader
        from .ros1_salvage import MAGIC, SalvageRos1Reader

        mcaps = [self.path] if self.path.suffix == ".mcap" else sorted(self.path.glob("*.mcap")) \
            if self.path.is_dir() else []
        reader: Any = None
        if len(mcaps) == 1:
            try:
                reader, name, how = SalvageMcapReader(mcaps[0], self._typestore), mcaps[0].name, "record by record"
            except (OSError, ValueError):
                reader = None
        elif self.path.is_file():
            with self.path.open("rb") as f:
                start = f.read(len(MAGIC))
            if not start.startswith((MAGIC, MCAP_MAGIC)):
                raise ValueError(f"cannot read bag {self.path}: not a ROS 1 bag (it would start with "
                                 f"{MAGIC.strip().decode()}), an MCAP file or a ROS 2 bag folder") from None
            if start == MAGIC:
                try:
                    reader, name, how = SalvageRos1Reader(self.path), self.path.name, "chunk by chunk"
                except (OSError, ValueError):
                    reader = None
        if reader is not None and reader.messages_read:
            self.salvaged = (f"{name} cannot be opened normally ({exc}); "
                             f"{'truncated: ' if reader.cut else ''}read its first {reader.messages_read} "
                             f"messages {how}" + (f", up to {reader.stopped}" if getattr(reader, "stopped", None)
                                                  and not reader.cut else ""))
            self.salvaged_messages = reader.messages_read
            self.record_error(self.salvaged)
            self._open = lambda: reader
            return
        raise ValueError(f"cannot read bag {self.path}: {type(exc).__name__}: {exc} "
                         "(a truncated or corrupt file?)") from None

    def _groundtruth_table(self, reader: Any) -> np.ndarray:
        """(n, 4) stamp, x, y, theta of every valid ground-truth message, in time order."""
        conns = [c for c in reader.connections if c.topic == self.topics["groundtruth"]]
        rows: list[tuple[float, float, float, float]] = []
        origin: tuple[float, float] | None = None
        gps = False
        for conn, t_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            t = _stamp(msg, t_ns)
            if conn.msgtype == "sensor_msgs/msg/NavSatFix":
                gps = True
                lat, lon = float(msg.latitude), float(msg.longitude)
                status = getattr(getattr(msg, "status", None), "status", 0)
                if lat == 0.0 or lon == 0.0 or status < 0 or not (math.isfinite(lat) and math.isfinite(lon)):
                    continue  # no fix, or a receiver's zero placeholder (seen in real bags)
                if origin is None:
                    origin = (lat, lon)
                x = EARTH_RADIUS * math.radians(lon - origin[1]) * math.cos(math.radians(origin[0]))
                y = EARTH_RADIUS * math.radians(lat - origin[0])
                rows.append((t, x, y, 0.0))
                continue
            pose = msg.pose.pose if conn.msgtype in ("geometry_msgs/msg/PoseWithCovarianceStamped",
                                                     "nav_msgs/msg/Odometry") else msg.pose
            rows.append((t, float(pose.position.x), float(pose.position.y), _yaw(pose.orientation)))
        table = np.array(rows, dtype=np.float64).reshape(-1, 4)
        table = table[np.argsort(table[:, 0], kind="stable")]
        if gps and len(table) > 1:  # course over ground: the direction of travel between fixes
            d = np.gradient(table[:, 1:3], axis=0)
            table[:, 3] = np.arctan2(d[:, 1], d[:, 0])
        table[:, 3] = np.unwrap(table[:, 3])
        return table

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        return bool(params.get("odom_topic"))

    def info(self) -> dict[str, Any]:
        return {"kind": "bag", "path": str(self.path), "topics": self.topics, "frames": self.length,
                "rate_hz": self.rate_hz, "salvaged": self.salvaged, "salvaged_messages": self.salvaged_messages,
                "warnings": list(self.warnings)}
