"""Live cameras over zenoh: ROS 2 topics bridged by zenoh-bridge-ros2dds, and native image topics.

``zenoh-ros2`` (:class:`ZenohRos2CameraSource`): the bridge publishes a ROS 2 topic on the key of
its name without the leading slash (with ``namespace`` prefixed when the bridge runs with one), as
raw CDR with its 4-byte encapsulation header and no encoding; the message type is known from the
config. Image and CompressedImage frames are decoded (:mod:`.cdr`); an optional nav_msgs/Odometry
topic gives the odometry of the interval since the previous frame. Connect to the bridge's router
(``connect: [tcp/<bridge-host>:7447]``).

``zenoh`` (:class:`ZenohImageSource`): our own msgpack ``image`` messages on any key (a non-ROS
camera publishing with :func:`neoslam_stream.runtime.messages.encode`, such as ``neoslam camera``,
whose figures on ``<key>/stats`` reach the run's report and monitor through this source).

Both are live (length None): they yield frames as they arrive, newest first when the consumer is
slower (a small ring), until ``close()`` or ``timeout_s`` without frames. A bad sample is counted
and logged once with its cause, never fatal.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator

from ..runtime.bus import open_session
from ..runtime.messages import MessageError
from ..runtime.messages import decode as decode_message
from ..runtime.pixels import decode_bounded, fit, needs_resize
from .base import Source, SourceFrame
from .capture import loss_causes
from .cdr import CdrError, decode
from .imaging import DEFAULT_MAX_SIDE
from .odometry import OdometrySubscription, frame_odometry
from .params import PositiveFloat, PositiveInt

log = logging.getLogger("neoslam.sources.zenoh")


def ros2_key(topic: str, namespace: str | None = None) -> str:
    """The key zenoh-bridge-ros2dds uses for a ROS 2 topic."""
    key = topic.lstrip("/")
    if namespace:
        key = f"{namespace.strip('/')}/{key}"
    return key


def _bridge_namespace(namespace: Any) -> Any:
    if namespace is not None and not isinstance(namespace, str):
        # `-p namespace=1` parses as a number: a ROS domain id, which this source has no use for
        raise ValueError(f"namespace {namespace!r} must be the bridge's namespace (a name such as bot1); "
                         "for ROS 2 nodes running rmw_zenoh use --source rmw-zenoh -p domain_id=N")
    return namespace


#: the bridge's namespace, checked before a run starts (sources/params.py)
Namespace = Annotated[str, BeforeValidator(_bridge_namespace)]
ImageType = Literal["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"]


class _Live(Source):
    """A source fed from the bus as frames come (Source.live)."""

    live = True

    def __init__(self, connect: list[str] | None, listen: list[str] | None, capacity: int, timeout_s: float | None,
                 mode: str = "peer") -> None:
        self.length = None
        self.rate_hz = None
        self._session = open_session(listen=listen or [], connect=connect or [], mode=mode)
        self._ring: deque = deque(maxlen=capacity)
        self._cond = threading.Condition()
        self._closed = False
        self.timeout_s = timeout_s
        self.received = 0
        self.dropped = 0

    def _push(self, item: dict[str, Any]) -> None:
        with self._cond:
            if len(self._ring) == self._ring.maxlen:
                # the oldest frame is dropped, its motion is not: the next frame carries it
                old = self._ring.popleft()
                nxt = self._ring[0] if self._ring else item
                nxt["acc"] = (old["acc"][0] + nxt["acc"][0], old["acc"][1] + nxt["acc"][1])
                self.dropped += 1
            self._ring.append(item)
            self.received += 1
            self._cond.notify_all()

    def _error(self, cause: str) -> None:
        self.record_error(f"skipped a sample: {cause}")

    def _next(self) -> Any | None:
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        with self._cond:
            while not self._ring and not self._closed:
                wait = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
                if wait <= 0:
                    return None
                self._cond.wait(wait)
            return self._ring.popleft() if self._ring else None

    def interrupt(self) -> None:
        """End a waiting iteration soon (the run's stop or duration); ``close`` ends the session."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def close(self) -> None:
        self.interrupt()
        try:
            self._session.close()
        except Exception:
            pass


class ZenohRos2CameraSource(_Live):
    """Frames of a ROS 2 camera topic bridged by zenoh-bridge-ros2dds (raw CDR payloads).

    ``image_topic`` / ``odom_topic`` are ROS 2 topic names; ``namespace`` the bridge's ``-n``
    option; ``connect`` / ``listen`` zenoh endpoints (the bridge's router: ``tcp/host:7447``);
    ``capacity`` frames are kept when the consumer is slower (the oldest go first);
    ``timeout_s`` ends the stream after that long without a frame (None: only ``close()`` does);
    frames whose long side exceeds ``max_side`` pixels are resized (16-bit encodings become
    8-bit: :mod:`.imaging`).
    """

    def __init__(self, image_topic: str, image_type: ImageType = "sensor_msgs/msg/Image", odom_topic: str | None = None,
                 namespace: Namespace | None = None, connect: list[str] | None = None, listen: list[str] | None = None,
                 capacity: PositiveInt = 2, timeout_s: PositiveFloat | None = None,
                 mode: Literal["peer", "client"] = "peer", max_side: PositiveInt | None = DEFAULT_MAX_SIDE) -> None:
        _bridge_namespace(namespace)
        if image_type not in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"):
            raise ValueError(f"image_type {image_type!r} must be sensor_msgs/msg/Image or CompressedImage")
        super().__init__(connect, listen, capacity, timeout_s, mode)
        self.image_type = image_type
        self.max_side = max_side
        self.keys = {"image": ros2_key(image_topic, namespace)}
        self._odom: tuple[float, float, float] | None = None  # t, v, w
        self._acc = [0.0, 0.0]
        self._lock = threading.Lock()
        self._subs = [self._session.declare_subscriber(self.keys["image"], self._on_image)]
        if odom_topic:
            self.keys["odom"] = ros2_key(odom_topic, namespace)
            self._subs.append(self._session.declare_subscriber(self.keys["odom"], self._on_odom))

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        return bool(params.get("odom_topic"))

    def _on_odom(self, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), "nav_msgs/msg/Odometry")
        except CdrError as exc:
            self._error(str(exc))
            return
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        with self._lock:
            if self._odom is not None and t > self._odom[0]:
                self._acc[0] += self._odom[1] * (t - self._odom[0])
                self._acc[1] += self._odom[2] * (t - self._odom[0])
            self._odom = (t, float(msg.twist.twist.linear.x), float(msg.twist.twist.angular.z))

    def _on_image(self, sample: Any) -> None:
        try:
            payload = sample.payload.to_bytes()
            if self.image_type == "sensor_msgs/msg/Image":
                m = decode(payload, self.image_type)
                img = fit(m["image"], self.max_side)
                item = {"stamp": m["stamp"], "image": img.copy() if img is m["image"] else img,
                        "encoding": m["encoding"]}
            else:
                m = decode(payload, self.image_type)
                fmt = "png" if "png" in str(m.format).lower() else "jpeg"
                item = {"stamp": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                        "compressed": bytes(m.data), "format": fmt}
                if needs_resize(item["compressed"], self.max_side):  # decoded here, reduced
                    bgr = decode_bounded(item["compressed"], self.max_side)
                    if bgr is not None:
                        del item["compressed"], item["format"]
                        item.update(image=bgr[:, :, ::-1].copy(), encoding="rgb8")
        except CdrError as exc:
            self._error(str(exc))
            return
        with self._lock:
            t = item["stamp"]
            if self._odom is not None and t > self._odom[0]:
                # the last twist holds until the frame (as the bag reader integrates it)
                t0, v, w = self._odom
                self._acc[0] += v * (t - t0)
                self._acc[1] += w * (t - t0)
                self._odom = (t, v, w)
            item["acc"] = tuple(self._acc)
            self._acc = [0.0, 0.0]
        self._push(item)

    def __iter__(self) -> Iterator[SourceFrame]:
        frame = 0
        prev_t: float | None = None
        while True:
            item = self._next()
            if item is None:
                return
            t = item.pop("stamp")
            d, th = item.pop("acc")
            dt = 0.0 if prev_t is None else max(0.0, t - prev_t)
            prev_t = t
            odom = ((d / dt, th / dt, dt) if dt > 0 else (0.0, 0.0, 0.0)) if "odom" in self.keys else None
            yield SourceFrame(frame=frame, stamp=t, odom=odom, **item)
            frame += 1

    def info(self) -> dict[str, Any]:
        return {"kind": "zenoh-ros2", "keys": self.keys, "type": self.image_type, "received": self.received,
                "dropped": self.dropped, "errors": self.errors}


class ZenohImageSource(_Live):
    """Our msgpack ``image`` messages from any zenoh key (a non-ROS camera), with optional
    odometry: our ``odom`` messages on ``odom_key`` (:class:`~.odometry.OdometrySubscription`), each
    the motion (vtrans, vrot, dt) of its own interval; the motions received between two images are
    summed into the later image's odometry. Raw frames whose long side exceeds ``max_side`` pixels
    are resized.

    A publisher that numbers its frames consecutively (``neoslam camera`` does) has the gaps in
    its numbers counted as frames lost on the way (``lost_before_source``; a number that goes back
    is a publisher started again); ``stats`` messages on ``<key>/stats`` (``neoslam camera``'s
    capture figures) become ``info()["camera"]``, and the camera's drops, outages and skipped frames
    since this source first heard of it count as frames lost at the source.
    """

    def __init__(self, key: str, odom_key: str | None = None, connect: list[str] | None = None,
                 listen: list[str] | None = None, capacity: PositiveInt = 2, timeout_s: PositiveFloat | None = None,
                 mode: Literal["peer", "client"] = "peer", max_side: PositiveInt | None = DEFAULT_MAX_SIDE) -> None:
        super().__init__(connect, listen, capacity, timeout_s, mode)
        self.max_side = max_side
        self.key = key
        self.odom_key = odom_key
        self._lock = threading.Lock()
        self._last_number: int | None = None
        self.lost_before_source = 0
        self.camera: dict[str, Any] | None = None  # the publisher's newest figures, and the first
        self._camera_baseline: dict[str, Any] | None = None
        self.odometry = OdometrySubscription(odom_key, self._session, self._error) if odom_key else None
        self._sub = self._session.declare_subscriber(key, self._on_sample)
        self._stats_sub = self._session.declare_subscriber(f"{key}/stats", self._on_camera_stats)

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        return bool(params.get("odom_key"))

    def _on_camera_stats(self, sample: Any) -> None:
        try:
            msg = decode_message(sample.payload.to_bytes(), expected_type="stats")
        except MessageError as exc:
            self._error(f"camera stats: {exc}")
            return
        with self._lock:
            self.camera = dict(msg.data)
            if self._camera_baseline is None:
                self._camera_baseline = dict(msg.data)

    def _on_sample(self, sample: Any) -> None:
        try:
            msg = decode_message(sample.payload.to_bytes(), expected_type="image")
        except MessageError as exc:
            self._error(str(exc))
            return
        with self._lock:
            last, self._last_number = self._last_number, msg.frame
            if last is not None and msg.frame > last + 1:
                self.lost_before_source += msg.frame - last - 1
        self._push({"msg": msg, "acc": self.odometry.take() if self.odometry else (0.0, 0.0)})

    def __iter__(self) -> Iterator[SourceFrame]:
        frame = 0
        prev_t: float | None = None
        while True:
            item = self._next()
            if item is None:
                return
            msg = item["msg"]
            dt = 0.0 if prev_t is None else max(0.0, msg.stamp - prev_t)
            prev_t = msg.stamp
            odom = frame_odometry(item["acc"], dt) if self.odometry else None
            data = msg.data
            if data.get("image") is not None:
                img = fit(data["image"], self.max_side)
                yield SourceFrame(frame, msg.stamp, image=img.copy() if img is data["image"] else img,
                                  encoding=data.get("encoding") or "rgb8", odom=odom)
            else:
                yield SourceFrame(frame, msg.stamp, compressed=bytes(data["compressed"]),
                                  format=data.get("format"), odom=odom)
            frame += 1

    def info(self) -> dict[str, Any]:
        with self._lock:
            camera, baseline = self.camera, self._camera_baseline
            lost_on_way = self.lost_before_source
        out: dict[str, Any] = {"kind": "zenoh", "key": self.key, "odom_key": self.odom_key, "received": self.received,
                               "odometry_received": self.odometry.received if self.odometry else 0,
                               "dropped": self.dropped, "errors": self.errors, "lost_before_source": lost_on_way}
        lost = {"lost between the publisher and this source (gaps in its frame numbers)": lost_on_way}
        if camera is not None and baseline is not None:
            out["camera"] = camera
            lost.update(loss_causes(camera, baseline, where="remote camera"))
            drops = int(camera.get("dropped", 0)) - int(baseline.get("dropped", 0))
            lost["remote camera: frames dropped by its publisher (it could not keep up)"] = drops
        out["lost"] = {cause: n for cause, n in lost.items() if n > 0}
        return out
