"""ROS 2 nodes running rmw_zenoh (ROS 2's zenoh middleware): keys, attachments, and a camera source.

rmw_zenoh publishes a topic on the key ``<domain_id>/<fully qualified name without its leading
slash>/<DDS type name>/<type hash>`` (the REP-2011 RIHS01 hash from Jazzy on, Humble writes
``TypeHashNotSupported``). Every sample carries an attachment with the publisher's sequence number,
a source timestamp and its GID (int64 LE, int64 LE ns, one length byte and the 16 GID bytes, as
rmw_zenoh's design document describes; :func:`parse_attachment` also reads the key/value form of
the first releases).

:class:`RmwZenohCameraSource` (source kind ``rmw-zenoh``) subscribes to an image topic (and
optionally a nav_msgs/Odometry topic) with a wildcard on the type name and the hash, so it takes
any distribution's; the payload is the CDR that :class:`~.zenoh_camera.ZenohRos2CameraSource`
decodes, and the sequence numbers count, per publisher, the messages lost before they reached us.
Details: docs/sources.md, "rmw-zenoh".
"""

from __future__ import annotations

import logging
import struct
import threading
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .imaging import DEFAULT_MAX_SIDE
from .zenoh_camera import ZenohRos2CameraSource, _Live

log = logging.getLogger("neoslam.sources.rmw_zenoh")

#: length of a ROS 2 GID as rmw_zenoh sends it (RMW_GID_STORAGE_SIZE)
GID_SIZE = 16
#: the hash chunk of Humble's rmw_zenoh, which has no type hashes
HASH_NOT_SUPPORTED = "TypeHashNotSupported"
#: rmw_zenoh's router (rmw_zenohd) listens here by default
DEFAULT_ROUTER = "tcp/localhost:7447"

IMAGE_TYPES = {"sensor_msgs::msg::dds_::Image_": "sensor_msgs/msg/Image",
               "sensor_msgs::msg::dds_::CompressedImage_": "sensor_msgs/msg/CompressedImage"}
ODOM_TYPE = "nav_msgs/msg/Odometry"


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the type chunk of a key)."""
    parts = msgtype.strip("/").split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"message type {msgtype!r} must look like 'package/msg/Name'")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str:
    """Inverse of :func:`dds_type_name`: ``nav_msgs::msg::dds_::Odometry_`` -> ``nav_msgs/msg/Odometry``."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"{dds_name!r} is not a DDS type name such as 'sensor_msgs::msg::dds_::Image_'")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _topic_chunks(topic: str) -> str:
    name = topic.strip()
    if not name or not name.strip("/"):
        raise ValueError(f"topic name {topic!r} is empty")
    if any(c in name for c in "*$?#"):
        raise ValueError(f"topic name {topic!r} holds a character ROS 2 names cannot have")
    return name.strip("/")


def topic_key(domain_id: int, topic: str, type_chunk: str = "*", hash_chunk: str = "*") -> str:
    """The key rmw_zenoh uses for ``topic`` in ``domain_id``; the defaults make a key expression
    that matches any type and any hash."""
    return f"{int(domain_id)}/{_topic_chunks(topic)}/{type_chunk}/{hash_chunk}"


@dataclass
class Attachment:
    """What an rmw_zenoh publisher attaches to each sample."""

    sequence_number: int
    source_timestamp: int  # ns since the UNIX epoch
    gid: bytes

    def encode(self) -> bytes:
        """The compact layout of current rmw_zenoh (see the module docstring)."""
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        return struct.pack("<qqB", self.sequence_number, self.source_timestamp, GID_SIZE) + bytes(self.gid)


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    """An unsigned LEB128 integer (zenoh's serializer writes lengths so) at ``pos``."""
    value, shift = 0, 0
    while True:
        if pos >= len(buf) or shift > 63:
            raise ValueError("truncated length")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7


def parse_attachment(data: bytes) -> Attachment:
    """Read an rmw_zenoh attachment, compact or key/value; ``ValueError`` names what is wrong."""
    buf = bytes(data)
    kv_prefix = bytes([len("sequence_number")]) + b"sequence_number"
    if buf.startswith(kv_prefix):
        values: dict[str, Any] = {}
        pos = 0
        for key in ("sequence_number", "source_timestamp", "source_gid"):
            n, pos = _varint(buf, pos)
            name = buf[pos:pos + n].decode("utf-8", "replace")
            pos += n
            if name != key:
                raise ValueError(f"attachment key {name!r} where {key!r} was expected")
            if key == "source_gid":
                n, pos = _varint(buf, pos)
                values[key] = buf[pos:pos + n]
                pos += n
            else:
                if pos + 8 > len(buf):
                    raise ValueError(f"attachment truncated in {key}")
                (values[key],) = struct.unpack_from("<q", buf, pos)
                pos += 8
        gid = values["source_gid"]
    else:
        if len(buf) < 17:
            raise ValueError(f"attachment of {len(buf)} bytes is too short (sequence number, timestamp, GID)")
        seq, stamp = struct.unpack_from("<qq", buf, 0)
        n, pos = _varint(buf, 16)
        gid = buf[pos:pos + n]
        values = {"sequence_number": seq, "source_timestamp": stamp}
    if len(gid) != GID_SIZE:
        raise ValueError(f"attachment GID has {len(gid)} bytes, not {GID_SIZE}")
    return Attachment(int(values["sequence_number"]), int(values["source_timestamp"]), bytes(gid))


class SequenceCounter:
    """Messages lost before they reached us, per publisher GID, from the sequence numbers.

    A publisher numbers its messages 1, 2, 3...; a jump from n to n + k means k - 1 messages were
    lost on the way. A number at or below the last one means the publisher restarted (or a
    duplicate): counting starts again from it.
    """

    def __init__(self) -> None:
        self.last: dict[bytes, int] = {}
        self.received: dict[bytes, int] = {}
        self.lost: dict[bytes, int] = {}
        self.restarts = 0

    def add(self, att: Attachment) -> int:
        """Record one message; returns the number found lost just before it."""
        gid, seq = att.gid, att.sequence_number
        self.received[gid] = self.received.get(gid, 0) + 1
        prev = self.last.get(gid)
        self.last[gid] = seq
        if prev is None:
            self.lost.setdefault(gid, 0)
            return 0
        if seq <= prev:
            self.restarts += 1
            return 0
        gap = seq - prev - 1
        self.lost[gid] = self.lost.get(gid, 0) + gap
        return gap

    @property
    def total_lost(self) -> int:
        return sum(self.lost.values())

    def summary(self) -> dict[str, dict[str, int]]:
        return {gid.hex(): {"received": self.received[gid], "lost": self.lost.get(gid, 0),
                            "last_sequence_number": self.last[gid]} for gid in self.received}


class RmwZenohConfig(BaseModel):
    """Parameters of the ``rmw-zenoh`` source (unknown names are refused)."""

    model_config = ConfigDict(extra="forbid")

    image_topic: str
    odom_topic: str | None = None
    domain_id: int = Field(0, ge=0, le=232)  # ROS_DOMAIN_ID's valid range
    connect: list[str] | None = None
    listen: list[str] | None = None
    mode: str = Field("peer", pattern="^(peer|client)$")
    capacity: int = Field(2, ge=1)
    timeout_s: float | None = Field(None, gt=0)
    #: warn (once) when nothing arrived within this many seconds of the start
    warn_after_s: float = Field(5.0, gt=0)
    #: frames whose long side exceeds this many pixels are resized (sources/imaging.py)
    max_side: int | None = Field(DEFAULT_MAX_SIDE, ge=16)


class RmwZenohCameraSource(ZenohRos2CameraSource):
    """Frames of a ROS 2 camera topic published by a node running rmw_zenoh.

    Parameters (:class:`RmwZenohConfig`): ``image_topic``, ``odom_topic`` (ROS 2 topic names),
    ``domain_id`` (``ROS_DOMAIN_ID``, 0), ``connect`` / ``listen`` zenoh endpoints (rmw_zenoh's
    router: ``tcp/<host>:7447``), ``mode``, ``capacity``, ``timeout_s`` (the stream ends after that
    long without a frame, counted from the first frame), ``warn_after_s``, ``max_side`` (larger
    frames are resized; 16-bit encodings become 8-bit, as for ``zenoh-ros2``).
    """

    #: the parameters, checked before a run starts (sources/params.py)
    params_model = RmwZenohConfig

    def __init__(self, image_topic: str, odom_topic: str | None = None, domain_id: int = 0,
                 connect: list[str] | None = None, listen: list[str] | None = None, mode: str = "peer",
                 capacity: int = 2, timeout_s: float | None = None, warn_after_s: float = 5.0,
                 max_side: int | None = DEFAULT_MAX_SIDE, **unknown: Any) -> None:
        # the signature names the parameters (checked by `neoslam run`'s plan); the model validates
        # their values, and the names nobody knows, in one message
        params = {"image_topic": image_topic, "odom_topic": odom_topic, "domain_id": domain_id, "connect": connect,
                  "listen": listen, "mode": mode, "capacity": capacity, "timeout_s": timeout_s,
                  "warn_after_s": warn_after_s, "max_side": max_side, **unknown}
        try:
            cfg = RmwZenohConfig(**params)
        except ValidationError as exc:
            causes = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'params'}: {e['msg']}" for e in exc.errors())
            raise ValueError(f"rmw-zenoh source: {causes} (parameters: "
                             f"{', '.join(RmwZenohConfig.model_fields)})") from None
        self.cfg = cfg
        self.keys = {"image": topic_key(cfg.domain_id, cfg.image_topic)}
        if cfg.odom_topic:
            self.keys["odom"] = topic_key(cfg.domain_id, cfg.odom_topic, dds_type_name(ODOM_TYPE))
        _Live.__init__(self, cfg.connect, cfg.listen, cfg.capacity, cfg.timeout_s, cfg.mode)
        self.image_type = ""
        self.max_side = cfg.max_side
        self._odom: tuple[float, float, float] | None = None
        self._acc = [0.0, 0.0]
        self._lock = threading.Lock()
        self.sequence = {"image": SequenceCounter(), "odom": SequenceCounter()}
        self.type_hashes: dict[str, str] = {}
        self._heard = threading.Event()
        self._subs = [self._session.declare_subscriber(self.keys["image"], self._on_rmw_image)]
        if cfg.odom_topic:
            self._subs.append(self._session.declare_subscriber(self.keys["odom"], self._on_rmw_odom))
        self._watch = threading.Thread(target=self._warn_if_silent, name="rmw-zenoh-watch", daemon=True)
        self._watch.start()

    def _next(self) -> Any | None:
        # timeout_s counts from the first frame: a robot started after us is waited for (the
        # warning after warn_after_s says that nothing arrives); only close() ends the wait
        with self._cond:
            while self.received == 0 and not self._closed:
                self._cond.wait(0.2)
        return super()._next()

    def _warn_if_silent(self) -> None:
        if self._heard.wait(self.cfg.warn_after_s) or self._closed:
            return
        where = ", ".join(self.cfg.connect or self.cfg.listen or []) or "no endpoint (connect to rmw_zenoh's router)"
        log.warning("rmw-zenoh source: nothing arrived within %.0f s on %s (domain %d; zenoh endpoints: %s). "
                    "Check ROS_DOMAIN_ID and the topic name, and connect to rmw_zenoh's router, e.g. "
                    "-p 'connect=[\"%s\"]'", self.cfg.warn_after_s, " and ".join(self.keys.values()),
                    self.cfg.domain_id, where, DEFAULT_ROUTER)

    def _attachment(self, sample: Any, role: str) -> None:
        """Count the sample's sequence number. A missing or unreadable attachment is counted as an
        error; the message itself is still used (only its loss accounting is missing)."""
        self._heard.set()
        att = sample.attachment
        if att is None:
            self._error(f"{role} sample without an rmw_zenoh attachment (sequence number, timestamp, GID)")
            return
        try:
            parsed = parse_attachment(att.to_bytes())
        except ValueError as exc:
            self._error(f"{role} attachment unreadable: {exc}")
            return
        self.sequence[role].add(parsed)

    def _on_rmw_image(self, sample: Any) -> None:
        key = str(sample.key_expr)
        chunks = key.split("/")
        msgtype = IMAGE_TYPES.get(chunks[-2]) if len(chunks) >= 4 else None
        if msgtype is None:
            self._heard.set()
            self._error(f"type {chunks[-2] if len(chunks) >= 4 else key!r} on the image topic is not "
                        f"sensor_msgs/msg/Image or CompressedImage")
            return
        self.type_hashes[msgtype] = chunks[-1]
        self._attachment(sample, "image")
        self.image_type = msgtype  # one subscriber: its samples come one at a time
        self._on_image(sample)

    def _on_rmw_odom(self, sample: Any) -> None:
        self.type_hashes[ODOM_TYPE] = str(sample.key_expr).split("/")[-1]
        self._attachment(sample, "odom")
        self._on_odom(sample)

    def close(self) -> None:
        super().close()
        self._heard.set()

    def info(self) -> dict[str, Any]:
        img = self.sequence["image"]
        return {"kind": "rmw-zenoh", "domain_id": self.cfg.domain_id, "keys": self.keys, "type": self.image_type,
                "type_hashes": dict(self.type_hashes), "received": self.received, "dropped": self.dropped,
                # messages the publishers sent that never reached us (sequence-number gaps)
                "lost_before_source": img.total_lost, "publishers": img.summary(),
                "odom_lost_before_source": self.sequence["odom"].total_lost,
                "publisher_restarts": img.restarts, "errors": self.errors}


__all__ = ["Attachment", "DEFAULT_ROUTER", "HASH_NOT_SUPPORTED", "RmwZenohCameraSource", "SequenceCounter",
           "dds_type_name", "parse_attachment", "ros_type_name", "topic_key"]
