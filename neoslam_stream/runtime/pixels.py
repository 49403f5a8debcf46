"""Compressed frames to bounded BGR pixels: what the sources and the run's camera.zip decode.

:func:`fit`, :func:`decode_bounded`: a valid but large image is resized so that its long side is
at most ``max_side`` pixels (INTER_AREA); a JPEG is decoded at a reduced DCT scale so the whole
frame is never held in memory. Headers claiming more than
:data:`~neoslam_stream.runtime.imageinfo.MAX_PIXELS`, or truncated bytes, are not decoded: the
front end refuses them with their cause.
"""

from __future__ import annotations

import cv2
import numpy as np

from .imageinfo import image_dimensions, too_large, truncation

_REDUCED = ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4), (2, cv2.IMREAD_REDUCED_COLOR_2))


def fit(img: np.ndarray, max_side: int | None) -> np.ndarray:
    """``img`` resized (INTER_AREA, aspect kept) so that its long side is at most ``max_side``."""
    h, w = img.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return img
    s = max_side / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def decode_bounded(raw: bytes, max_side: int | None) -> np.ndarray | None:
    """The BGR frame of JPEG/PNG/... bytes with its long side at most ``max_side``, or None when
    the bytes are empty, truncated, claim more than the decode limit, or do not decode (the
    front end then refuses them with the cause)."""
    if not raw or too_large(raw) is not None or truncation(raw) is not None:
        return None
    flag = cv2.IMREAD_COLOR
    dims = image_dimensions(raw)
    if max_side and dims is not None and raw[:2] == b"\xff\xd8":
        # the largest DCT reduction that keeps the long side at or above the bound
        for r, f in _REDUCED:
            if max(dims) // r >= max_side:
                flag = f
                break
    try:
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), flag)
    except cv2.error:
        return None
    return None if img is None else fit(img, max_side)


def needs_resize(raw: bytes, max_side: int | None) -> bool:
    """Whether compressed bytes declare a frame whose long side is beyond ``max_side`` (and
    within the decode limit): such a frame is decoded and resized at the source."""
    if not max_side or too_large(raw) is not None:
        return False
    dims = image_dimensions(raw)
    return dims is not None and max(dims) > max_side
