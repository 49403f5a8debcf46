"""Pixels at the sources: ROS image encodings to 8-bit frames.

:func:`ros_image`: 8-bit encodings pass through (a zero-copy view of the rows, padding dropped);
16-bit encodings (``is_bigendian`` honoured) become 8-bit by mapping the frame's own range
[min, max] linearly onto 0..255, colour channels together, alpha dropped. Why not ``>> 8``: 16-bit
cameras rarely fill 16 bits (10-14-bit sensors, thermal, depth in millimetres), and the high byte
alone would leave such frames almost black.

Images bounded in size (``max_side``, :data:`DEFAULT_MAX_SIDE`) are decoded and resized by
:mod:`neoslam_stream.runtime.pixels`, which the run's camera.zip shares. Details: docs/sources.md,
"Large images and 16-bit frames".
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: default bound on a frame's long side, in pixels (sources' ``max_side`` parameter)
DEFAULT_MAX_SIDE = 1920

#: encoding -> (channels, bytes per channel, the 8-bit encoding of the frame it becomes)
ROS_ENCODINGS: dict[str, tuple[int, int, str]] = {
    "rgb8": (3, 1, "rgb8"), "bgr8": (3, 1, "bgr8"), "8uc3": (3, 1, "rgb8"),
    "mono8": (1, 1, "mono8"), "8uc1": (1, 1, "mono8"),
    "rgba8": (4, 1, "rgba8"), "bgra8": (4, 1, "bgra8"),
    "mono16": (1, 2, "mono8"), "16uc1": (1, 2, "mono8"),
    "rgb16": (3, 2, "rgb8"), "bgr16": (3, 2, "bgr8"),
    "rgba16": (4, 2, "rgb8"), "bgra16": (4, 2, "bgr8"),
}
SUPPORTED = "rgb8, bgr8, mono8/8UC1, rgba8, bgra8, 8UC3, mono16/16UC1, rgb16, bgr16, rgba16, bgra16"

class ImageEncodingError(ValueError):
    """A ROS image that cannot be turned into a frame; the text says why."""


def stretch_to_8bit(v: np.ndarray) -> np.ndarray:
    """uint16 -> uint8: the frame's range [min, max] mapped linearly onto 0..255 (rounded)."""
    lo, hi = int(v.min()), int(v.max())
    if hi <= lo:
        return np.zeros(v.shape, np.uint8)
    return np.rint((v.astype(np.float64) - lo) * 255.0 / (hi - lo)).astype(np.uint8)


def ros_image(data: Any, height: int, width: int, step: int, encoding: str,
              is_bigendian: bool = False) -> tuple[np.ndarray, str]:
    """(HxW or HxWxC uint8 frame, its encoding) of a ROS Image's fields. ``data`` is the pixel
    buffer (bytes, memoryview or uint8 array, at least ``height * step`` bytes)."""
    enc = str(encoding).lower()
    spec = ROS_ENCODINGS.get(enc)
    if spec is None:
        raise ImageEncodingError(f"image encoding {encoding!r} is not supported ({SUPPORTED})")
    channels, depth, out_enc = spec
    row = width * channels * depth
    if height <= 0 or width <= 0:
        raise ImageEncodingError(f"image of {width}x{height} pixels is empty")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
    if step < row or buf.size < height * step:
        raise ImageEncodingError(f"Image of {width}x{height} {encoding} with step {step} does not fit "
                                 f"{buf.size} data bytes")
    rows = buf[: height * step].reshape(height, step)[:, :row]
    if depth == 1:
        img = rows.reshape(height, width, channels) if channels > 1 else rows
        return img, out_enc
    dtype = ">u2" if is_bigendian else "<u2"
    v = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    v = v[:, :, :3] if channels == 4 else v  # alpha carries no view
    out = stretch_to_8bit(v)
    return (out[:, :, 0] if channels == 1 else np.ascontiguousarray(out)), out_enc
