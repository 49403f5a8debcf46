"""Turning ``image`` messages into pixel arrays, shared by every node that looks at the camera.

One place decodes JPEG/PNG, checks sizes and channel counts and converts colour, so that the
NeoSLAM feature extractor, RatSLAM's local-view cells and visual odometry all see the same pixels
and reject the same bad frames with the same error text.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..algorithms.errors import InvalidInput

# MAX_PIXELS: frames larger than this are refused (a corrupt header can claim gigapixels)
from ..runtime.imageinfo import MAX_PIXELS, too_large, truncation

#: ITU-R BT.601 luma weights, the ones OpenCV's and the ROS 2 NeoSLAM's grey conversion use.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def _check_shape(img: np.ndarray) -> np.ndarray:
    if img.ndim not in (2, 3):
        raise InvalidInput(f"image must be HxW or HxWxC, got shape {img.shape}")
    if img.ndim == 3 and img.shape[2] not in (1, 3, 4):
        raise InvalidInput(f"image has {img.shape[2]} channels; 1, 3 or 4 are supported")
    h, w = img.shape[:2]
    if h == 0 or w == 0:
        raise InvalidInput(f"image is empty ({h}x{w})")
    if h * w > MAX_PIXELS:
        raise InvalidInput(f"image of {h}x{w} pixels exceeds the limit of {MAX_PIXELS}")
    return img


def decode_rgb(data: dict) -> np.ndarray:
    """An ``image`` message's data as an HxWx3 uint8 **RGB** array (grey frames are replicated to 3
    channels).

    Accepts raw arrays with ``encoding`` rgb8 (default), bgr8, mono8, rgba8/bgra8, and compressed
    JPEG/PNG bytes. Raises :class:`InvalidInput` with the cause for anything it cannot use.
    """
    if data.get("image") is not None:
        img = _check_shape(np.asarray(data["image"]))
        if img.dtype != np.uint8:
            raise InvalidInput(f"image dtype {img.dtype} unsupported; expected uint8")
        enc = str(data.get("encoding") or ("mono8" if img.ndim == 2 else "rgb8")).lower()
        if img.ndim == 2 or img.shape[2] == 1:
            if enc not in ("mono8", "8uc1", "rgb8", "bgr8"):
                raise InvalidInput(f"single-channel image with encoding {enc!r}")
            g = img.reshape(img.shape[0], img.shape[1])
            return np.repeat(g[:, :, None], 3, axis=2)
        channels = img.shape[2]
        if enc in ("mono8", "8uc1"):
            raise InvalidInput(f"encoding mono8 but image has {channels} channels")
        if enc in ("rgb8", "8uc3") and channels == 3:
            return img
        if enc == "bgr8" and channels == 3:
            return img[:, :, ::-1]
        if enc in ("rgba8", "bgra8") and channels == 4:
            rgb = img[:, :, :3]
            return rgb if enc == "rgba8" else rgb[:, :, ::-1]
        raise InvalidInput(f"encoding {enc!r} does not match {channels} channels or is unsupported")
    comp = data.get("compressed")
    if comp is None:
        raise InvalidInput("image message carries neither 'image' nor 'compressed'")
    buf = np.frombuffer(comp, dtype=np.uint8)
    if buf.size == 0:
        raise InvalidInput("compressed image is empty")
    cut = truncation(comp)
    if cut is not None:
        raise InvalidInput(f"compressed image of {buf.size} bytes: {cut}")
    big = too_large(comp)
    if big is not None:  # refuse before the decoder allocates the whole frame
        raise InvalidInput(f"compressed image header says {big[0]}x{big[1]} pixels, "
                              f"beyond the limit of {MAX_PIXELS}")
    try:
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    except cv2.error as exc:
        raise InvalidInput(f"cannot decode {data.get('format') or 'compressed'} image: {exc}") from None
    if bgr is None:
        raise InvalidInput(f"cannot decode {data.get('format') or 'compressed'} image "
                              f"({buf.size} bytes): corrupt or truncated")
    _check_shape(bgr)
    return np.ascontiguousarray(bgr[:, :, ::-1])


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """HxWx3 RGB uint8 -> HxW float32 luma in [0, 255] (BT.601 weights)."""
    return rgb.astype(np.float32) @ _LUMA


def decode_grey(data: dict) -> np.ndarray:
    """An ``image`` message's data as HxW float32 grey levels in [0, 255]."""
    img = data.get("image")
    if img is not None and np.asarray(img).ndim == 2:
        g = _check_shape(np.asarray(img))
        if g.dtype != np.uint8:
            raise InvalidInput(f"image dtype {g.dtype} unsupported; expected uint8")
        return g.astype(np.float32)
    return to_grey(decode_rgb(data))


def camera_pixels(data: dict) -> np.ndarray:
    """The frame as OpenRatSLAM reads it: grey frames as HxW, colour frames as HxWx3 (the RatSLAM
    stages sum the channels as the C++ does, rather than using luma weights)."""
    raw = data.get("image")
    if raw is not None and np.asarray(raw).ndim == 2:
        return decode_grey(data)
    return decode_rgb(data)
