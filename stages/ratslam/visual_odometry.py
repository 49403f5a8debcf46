"""RatSLAM visual odometry (OpenRatSLAM's scanline intensity profiles).

Two profiles per image, the column means of grey levels (/255) over a translation window and a
rotation window. Each is compared with the previous frame's over shifts of up to ``slen`` = 40
columns in both directions (mean absolute difference over the overlap); the best shift of the
rotation profile gives ``vrot = shift * camera_fov_deg / image_width * camera_hz`` (deg -> rad/s),
the best difference of the translation profile gives ``vtrans = min(diff * vtrans_scaling,
vtrans_max)``. A positive shift (the scene moved right) is a left (counter-clockwise) turn.
The first frame only stores its profiles (OpenRatSLAM's consumers ignore its value).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

SLEN = 40


class VisualOdometryConfig(BaseModel):
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


def profile(grey: np.ndarray, x0: int, x1: int, y0: int, y1: int) -> np.ndarray:
    h, w = grey.shape
    x1 = w if x1 < 0 else min(x1, w)
    y1 = h if y1 < 0 else min(y1, h)
    win = grey[y0:y1, x0:x1]
    if win.size == 0:
        raise ValueError(f"empty odometry window x[{x0},{x1}) y[{y0},{y1}) in a {w}x{h} image")
    return win.mean(axis=0) / 255.0


def best_shift(cur: np.ndarray, prev: np.ndarray, slen: int = SLEN) -> tuple[int, float]:
    """(offset, mean abs difference) minimising the difference; offset > 0: cur[k+off] ~ prev[k]."""
    n = cur.size
    best_off, best = 0, math.inf
    for off in range(min(slen, n - 1)):
        d = float(np.abs(cur[off:] - prev[:n - off]).mean())
        if d < best:
            best_off, best = off, d
        d = float(np.abs(cur[:n - off] - prev[off:]).mean())
        if d < best:
            best_off, best = -off, d
    return best_off, best


class VisualOdometry:
    def __init__(self, **params: Any) -> None:
        self.cfg = VisualOdometryConfig(**params)
        self.prev_trans: np.ndarray | None = None
        self.prev_rot: np.ndarray | None = None

    def on_image(self, grey: np.ndarray) -> tuple[float, float] | None:
        """(vtrans m/s, vrot rad/s) since the previous frame, or None on the first frame."""
        c = self.cfg
        g = np.asarray(grey, dtype=np.float64)
        if g.ndim == 3:
            g = g.mean(axis=2)
        pt = profile(g, c.vtrans_image_x_min, c.vtrans_image_x_max, c.vtrans_image_y_min, c.vtrans_image_y_max)
        pr = profile(g, c.vrot_image_x_min, c.vrot_image_x_max, c.vrot_image_y_min, c.vrot_image_y_max)
        if self.prev_trans is None or self.prev_trans.shape != pt.shape or self.prev_rot.shape != pr.shape:
            self.prev_trans, self.prev_rot = pt, pr
            return None
        _, tdiff = best_shift(pt, self.prev_trans)
        roff, _ = best_shift(pr, self.prev_rot)
        self.prev_trans, self.prev_rot = pt, pr
        vrot = roff * c.camera_fov_deg / g.shape[1] * c.camera_hz * math.pi / 180
        vtrans = min(tdiff * c.vtrans_scaling, c.vtrans_max)
        return vtrans, vrot
