"""Decoding ROS 2 messages as zenoh-bridge-ros2dds delivers them: raw CDR with its 4-byte header.

``parse_image`` is a small zero-copy parser for sensor_msgs/msg/Image (the pixel array is a view on
the payload, far cheaper than rosbags' generic deserialiser: bench/sources.py measures both);
other types go through rosbags' CDR deserialiser. 16-bit image encodings (``is_bigendian``
honoured) become 8-bit frames (:mod:`.imaging`). Big-endian CDR and XCDR2 payloads, unknown
types and unsupported encodings raise :class:`CdrError` with the cause.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from .imaging import ImageEncodingError, ros_image

CDR_LE = b"\x00\x01"
SUPPORTED_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "nav_msgs/msg/Odometry")
_TYPESTORE: Any = None


class CdrError(ValueError):
    """A CDR payload cannot be decoded; the text says why."""


def _typestore() -> Any:
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
    return _TYPESTORE


def _check_header(buf: memoryview) -> None:
    if len(buf) < 4:
        raise CdrError(f"CDR payload of {len(buf)} bytes is shorter than its 4-byte header")
    rep = bytes(buf[:2])
    if rep == b"\x00\x00":
        raise CdrError("big-endian CDR is not supported (the publisher must use little-endian CDR)")
    if rep != CDR_LE:
        raise CdrError(f"unsupported CDR representation {rep.hex()} (only plain little-endian CDR, 0001)")


def parse_image(payload: bytes | memoryview) -> dict[str, Any]:
    """sensor_msgs/msg/Image -> {stamp, frame_id, height, width, encoding, step, image (view)}."""
    buf = memoryview(payload)
    _check_header(buf)
    pos = 4

    def align(n: int) -> None:
        nonlocal pos
        off = (pos - 4) % n
        if off:
            pos += n - off

    def u32() -> int:
        nonlocal pos
        align(4)
        if pos + 4 > len(buf):
            raise CdrError("truncated Image payload")
        (v,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        return v

    def string() -> str:
        nonlocal pos
        n = u32()
        if pos + n > len(buf):
            raise CdrError("truncated string in Image payload")
        raw = bytes(buf[pos:pos + n])
        if raw.endswith(b"\x00"):  # the length counts one terminating NUL; the content may hold more
            raw = raw[:-1]
        s = raw.decode("utf-8", "replace")
        pos += n
        return s

    sec = u32()
    nsec = u32()
    frame_id = string()
    height, width = u32(), u32()
    encoding = string().lower()
    if pos >= len(buf):
        raise CdrError("truncated Image payload")
    is_bigendian = buf[pos] != 0  # the byte order of 16-bit channels
    pos += 1
    step = u32()
    n = u32()
    if pos + n > len(buf):
        raise CdrError(f"Image data claims {n} bytes, payload has {len(buf) - pos}")
    if n < height * step:
        raise CdrError(f"Image of {width}x{height} {encoding} with step {step} does not fit {n} data bytes")
    try:
        # 8-bit: a zero-copy view of the payload; 16-bit: converted to 8-bit (see .imaging)
        img, enc = ros_image(np.frombuffer(buf, dtype=np.uint8, count=height * step, offset=pos),
                             height, width, step, encoding, is_bigendian)
    except ImageEncodingError as exc:
        raise CdrError(str(exc)) from None
    return {"stamp": sec + nsec * 1e-9, "frame_id": frame_id, "height": height, "width": width,
            "encoding": enc, "step": step, "image": img}


def decode(payload: bytes | memoryview, msgtype: str) -> Any:
    """Any supported type: Image via :func:`parse_image`, others via rosbags."""
    if msgtype not in SUPPORTED_TYPES:
        raise CdrError(f"message type {msgtype!r} is not supported ({', '.join(SUPPORTED_TYPES)})")
    buf = memoryview(payload)
    _check_header(buf)
    if msgtype == "sensor_msgs/msg/Image":
        return parse_image(buf)
    try:
        return _typestore().deserialize_cdr(bytes(buf), msgtype)
    except Exception as exc:  # rosbags raises several types on bad input
        raise CdrError(f"cannot decode {msgtype}: {type(exc).__name__}: {exc}") from None


def serialize(msg: Any, msgtype: str) -> bytes:
    """CDR bytes (with header) of a rosbags message object, as a ROS 2 publisher sends them."""
    return bytes(_typestore().serialize_cdr(msg, msgtype))
