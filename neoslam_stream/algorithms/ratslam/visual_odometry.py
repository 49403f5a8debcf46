"""RatSLAM visual odometry (OpenRatSLAM's ``VisualOdometry``): rates from scanline intensity profiles.

Per image two profiles, the column means of grey levels (/255; colour channels summed and divided
by 3*255, as the C++) over the translation and the rotation windows, are compared with the previous
frame's over shifts of up to ``SLEN`` = 40 columns in the C++'s order (0..-39, then 0..39; only a
strictly smaller mean absolute difference wins). The rotation profile's best shift gives vrot =
shift * camera_fov_deg / width * camera_hz (deg -> rad/s; a positive shift, the scene moving right,
is a left turn), the translation profile's best difference vtrans = min(diff * vtrans_scaling,
vtrans_max). The first frame only stores its profiles.

``openratslam_compat=True`` turns the per-frame measurements into rates with the nominal
``camera_hz``, as the C++; the default divides by the real interval ``dt`` between the two frames
compared when the caller gives it (after a dropped frame the C++'s rates are off by that ratio).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .._config import make_config
from ..errors import InvalidInput

SLEN = 40


class VisualOdometryConfig(BaseModel):
    """OpenRatSLAM's visual-odometry parameters with the C++ code defaults. The C++ window
    defaults (x_max/y_max) read the image size before it is known; here -1 means the image edge."""

    model_config = ConfigDict(extra="forbid")

    vtrans_image_x_min: int = 0
    vtrans_image_x_max: int = -1
    vtrans_image_y_min: int = 0
    vtrans_image_y_max: int = -1
    vrot_image_x_min: int = 0
    vrot_image_x_max: int = -1
    vrot_image_y_min: int = 0
    vrot_image_y_max: int = -1
    camera_fov_deg: float = 50.0
    camera_hz: float = Field(10.0, gt=0)
    vtrans_scaling: float = 100.0
    vtrans_max: float = 20.0
    openratslam_compat: bool = False


def profile(img: np.ndarray, x0: int, x1: int, y0: int, y1: int) -> np.ndarray:
    """Column means of the window [y0, y1) x [x0, x1) scaled to [0, 1] (-1 = image edge)."""
    h, w = img.shape[:2]
    x1 = w if x1 < 0 else min(x1, w)
    y1 = h if y1 < 0 else min(y1, h)
    win = np.asarray(img[y0:y1, x0:x1], dtype=np.float64)
    if win.shape[0] == 0 or win.shape[1] == 0:
        raise InvalidInput(f"empty odometry window x[{x0},{x1}) y[{y0},{y1}) in a {w}x{h} image")
    scale = 255.0
    if win.ndim == 3:
        win, scale = win.sum(axis=2), 255.0 * win.shape[2]
    # integer pixel sums are exact: dividing in the C++'s order reproduces its values
    return win.sum(axis=0) / scale / win.shape[0]


def best_shift(cur: np.ndarray, prev: np.ndarray, slen: int = SLEN) -> tuple[int, float]:
    """(offset, mean abs difference) minimising the difference; offset > 0: cur[k+off] ~ prev[k].

    Offsets are tried in the C++'s order, -0..-(slen-1) then 0..slen-1, and only a strictly
    smaller difference replaces the best (np.argmin's first occurrence).
    """
    n = cur.size
    if prev.size != n:
        raise InvalidInput(f"profiles differ in length: {n} and {prev.size}")
    offs = np.arange(min(slen, n - 1) if n > 1 else 1)
    neg = np.array([np.abs(cur[: n - o] - prev[o:]).sum() / (n - o) for o in offs])
    pos = np.array([np.abs(cur[o:] - prev[: n - o]).sum() / (n - o) for o in offs])
    diffs = np.concatenate([neg, pos])
    k = int(np.argmin(diffs))
    off = -int(offs[k]) if k < offs.size else int(offs[k - offs.size])
    return off, float(diffs[k])


class VisualOdometry:
    """OpenRatSLAM's ``VisualOdometry``: (vtrans m/s, vrot rad/s) per image from two scanlines."""

    def __init__(self, config: VisualOdometryConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(VisualOdometryConfig, config, overrides)
        self.prev_trans: np.ndarray | None = None
        self.prev_rot: np.ndarray | None = None

    def on_image(self, img: np.ndarray, dt: float | None = None) -> tuple[float, float] | None:
        """(vtrans m/s, vrot rad/s) since the previous frame, or None on the first frame.

        ``img`` is HxW grey or HxWxC colour (0..255); ``dt`` the seconds since the previous frame
        (used in the default mode to turn the per-frame shift into rates; None: 1/camera_hz).
        """
        c = self.config
        g = np.asarray(img)
        if g.ndim not in (2, 3):
            raise InvalidInput(f"expected a grey (HxW) or colour (HxWxC) image, got shape {g.shape}")
        if dt is not None and not (math.isfinite(dt) and dt >= 0):
            raise InvalidInput(f"dt must be finite and >= 0, got {dt}")
        pt = profile(g, c.vtrans_image_x_min, c.vtrans_image_x_max, c.vtrans_image_y_min, c.vtrans_image_y_max)
        pr = profile(g, c.vrot_image_x_min, c.vrot_image_x_max, c.vrot_image_y_min, c.vrot_image_y_max)
        if self.prev_trans is None or self.prev_trans.shape != pt.shape or self.prev_rot.shape != pr.shape:
            self.prev_trans, self.prev_rot = pt, pr
            return None
        _, tdiff = best_shift(pt, self.prev_trans)
        roff, _ = best_shift(pr, self.prev_rot)
        self.prev_trans, self.prev_rot = pt, pr
        if c.openratslam_compat or not dt:
            vrot = roff * c.camera_fov_deg / g.shape[1] * c.camera_hz * math.pi / 180.0
            vtrans = tdiff * c.vtrans_scaling
        else:  # per frame: rotation roff * fov / width degrees, translation tdiff * vtrans_scaling / camera_hz
            vrot = roff * c.camera_fov_deg / g.shape[1] / dt * math.pi / 180.0
            vtrans = tdiff * c.vtrans_scaling / (c.camera_hz * dt)
        return min(vtrans, c.vtrans_max), vrot
