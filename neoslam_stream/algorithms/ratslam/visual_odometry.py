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

``rotation: pinhole_centre`` reads the rotation as a pinhole camera's: the rotation profile is the
middle third of the window's columns, and a shift of s columns there is atan(s / f) radians, f =
(width / 2) / tan(camera_fov_deg / 2) the focal length in pixels. OpenRatSLAM's s * fov / width holds
for a camera whose every column spans the same angle; a pinhole camera's edge columns span half the
angle of its centre's at a 90 degree field of view, so the best shift over the whole width depends
on where the texture is (on the default route, lap by lap, 5 % under to 11 % over, against 4 % over
for the centre's third read as a pinhole). The translation is then measured with that rotation undone
(:func:`rotated_difference`): a pure rotation of a pinhole camera moves column u (from the centre)
to f tan(atan(u / f) + angle), and OpenRatSLAM's best shift, which moves every column alike, leaves a
difference that reads as driving (on the default route a turn on the spot read 1.6 times the straight
speed, a corner 1.6 times; undone, 0.5 and 1.0 times).

Three readings of the same profiles go beyond the C++ (each off in OpenRatSLAM's settings, on in the
default; studies/visual_odometry_choices.py chose them):

* ``subpixel``: the rotation's best shift refined by the parabola through the differences at its
  neighbours (:func:`refined_shift`). A whole-column shift reads a turn slower than a column a frame
  as none, which integrates into a heading error on every gentle curve.
* ``rotation_check`` (``pinhole_centre``): the centre's shift stands only if, undone over the
  translation window, it leaves a smaller difference than no rotation. Driving at a wall of repeated
  texture, the looming centre matches best a whole period away (0.15 rad in one frame) while the
  sides stay put; a real turn moves every column.
* ``translation: normal_flow``: the difference over the two profiles' mean absolute gradient. A
  column whose brightness changes by d where the profile's slope is g has moved about d / g columns
  (the normal flow of a 1-D image), so a contrasted wall no longer reads faster than a pale one.

``scale: platform`` calibrates the translation online instead of by ``vtrans_scaling`` (a number
that holds for one camera and one scene only): the profile difference per second r is VO's raw
speed, and the robot's typical speed is what its typical raw speed means, so
vtrans = speed_mps * r / median(r over the frames so far, this one included)
(:class:`TypicalSpeedScale`; ``speed_mps`` the platform's typical speed). It is causal: each frame
is scaled by what was seen up to it, and the first moving frame reads exactly the typical speed.
"""

from __future__ import annotations

import math
from bisect import insort
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ...tallies import LogHistogram
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
    #: fixed: vtrans = diff * vtrans_scaling (OpenRatSLAM; a scaling measured for your camera);
    #: platform: the raw speed's median over the run so far is the platform's typical speed
    scale: Literal["fixed", "platform"] = "fixed"
    #: openratslam: vrot = shift * camera_fov_deg / width over the whole window; pinhole_centre: the
    #: window's middle third, a shift read as a pinhole camera's angle atan(shift / focal length)
    rotation: Literal["openratslam", "pinhole_centre"] = "openratslam"
    #: the rotation's best shift refined to a fraction of a column (parabola through its neighbours)
    subpixel: bool = False
    #: pinhole_centre: the centre's shift stands only if, undone over the translation window, it
    #: explains the frame better than no rotation
    rotation_check: bool = False
    #: difference: the profiles' mean absolute difference is the raw speed (OpenRatSLAM);
    #: normal_flow: that difference over the profiles' mean absolute gradient, columns moved
    translation: Literal["difference", "normal_flow"] = "difference"


class TypicalSpeedScale:
    """VO's raw speed r (any unit per second) -> m/s: ``speed_mps`` * r / the median of every r so
    far, this one included (0 while that median is 0: nothing has moved yet). Beyond ``EXACT``
    samples they move into a :class:`~neoslam_stream.tallies.LogHistogram` whose median lies
    within 0.12 % of theirs, so that a camera running all day keeps a fixed memory here."""

    #: samples kept exactly, sorted (about 17 minutes at 10 Hz)
    EXACT = 10_000

    def __init__(self, speed_mps: float) -> None:
        if not (math.isfinite(speed_mps) and speed_mps > 0):
            raise InvalidInput(f"the typical speed must be a positive number, got {speed_mps}")
        self.speed_mps = speed_mps
        #: every raw speed seen, sorted (until there are more than EXACT; then in ``histogram``)
        self.samples: list[float] = []
        self.histogram: LogHistogram | None = None

    @property
    def median(self) -> float:
        if self.histogram is not None:
            return self.histogram.percentile(50)
        s, n = self.samples, len(self.samples)
        return 0.0 if n == 0 else 0.5 * (s[(n - 1) // 2] + s[n // 2])

    def __call__(self, raw: float) -> float:
        if self.histogram is not None:
            self.histogram.add(raw)
        else:
            insort(self.samples, raw)
            if len(self.samples) > self.EXACT:
                self.histogram = LogHistogram()
                for v in self.samples:
                    self.histogram.add(v)
                self.samples = []
        m = self.median
        return self.speed_mps * raw / m if m > 0 else 0.0


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


def shift_difference(cur: np.ndarray, prev: np.ndarray, off: int) -> float:
    """Mean |cur[k + off] - prev[k]| over the columns both profiles cover."""
    n = cur.size
    if off >= 0:
        return float(np.abs(cur[off:] - prev[: n - off]).sum() / (n - off))
    return float(np.abs(cur[: n + off] - prev[-off:]).sum() / (n + off))


def best_shift(cur: np.ndarray, prev: np.ndarray, slen: int = SLEN) -> tuple[int, float]:
    """(offset, mean abs difference) minimising the difference; offset > 0: cur[k+off] ~ prev[k].

    Offsets are tried in the C++'s order, -0..-(slen-1) then 0..slen-1, and only a strictly
    smaller difference replaces the best (np.argmin's first occurrence).
    """
    n = cur.size
    if prev.size != n:
        raise InvalidInput(f"profiles differ in length: {n} and {prev.size}")
    offs = range(min(slen, n - 1) if n > 1 else 1)
    offsets = [-o for o in offs] + list(offs)
    diffs = np.array([shift_difference(cur, prev, o) for o in offsets])
    k = int(np.argmin(diffs))
    return offsets[k], float(diffs[k])


def refined_shift(cur: np.ndarray, prev: np.ndarray, off: int, slen: int = SLEN) -> float:
    """``off`` refined to a fraction of a column: the vertex of the parabola through the differences
    at off - 1, off, off + 1, at most half a column away (``off`` itself at the search's edge or where
    the three do not curve upwards). An integer shift reads a turn slower than a column a frame as
    none at all, and a steady one in whole-column steps."""
    if abs(off) + 1 >= min(slen, cur.size - 1):
        return float(off)
    below, at, above = (shift_difference(cur, prev, o) for o in (off - 1, off, off + 1))
    curve = below - 2.0 * at + above
    if curve <= 0:
        return float(off)
    return off + min(0.5, max(-0.5, 0.5 * (below - above) / curve))


def rotated_difference(cur: np.ndarray, prev: np.ndarray, x0: int, width: int, focal: float, angle: float) -> float:
    """Mean |cur - prev| after a rotation by ``angle`` (rad, > 0: the scene moves right) of a pinhole
    camera of ``focal`` pixels: the profiles' columns start at image column ``x0`` of ``width``; cur's
    column u (from the image centre) shows what prev's column f tan(atan(u / f) - angle) showed
    (interpolated), over the columns that stayed in view."""
    u = np.arange(x0, x0 + cur.size) + 0.5 - width / 2
    src = focal * np.tan(np.arctan(u / focal) - angle)
    seen = (src >= u[0]) & (src <= u[-1])
    if not seen.any():
        return float(np.abs(cur - prev).mean())
    return float(np.abs(cur[seen] - np.interp(src[seen], u, prev)).mean())


class VisualOdometry:
    """OpenRatSLAM's ``VisualOdometry``: (vtrans m/s, vrot rad/s) per image from two scanlines."""

    def __init__(self, config: VisualOdometryConfig | None = None, speed_mps: float | None = None,
                 **overrides: Any) -> None:
        """``speed_mps``: the platform's typical speed, which ``scale: platform`` needs."""
        self.config = make_config(VisualOdometryConfig, config, overrides)
        self.prev_trans: np.ndarray | None = None
        self.prev_rot: np.ndarray | None = None
        self.speed_scale: TypicalSpeedScale | None = None
        if self.config.scale == "platform":
            if speed_mps is None:
                raise InvalidInput("visual_odometry.scale: platform needs the platform's typical speed (speed_mps)")
            self.speed_scale = TypicalSpeedScale(speed_mps)

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
        x0, x1 = c.vrot_image_x_min, c.vrot_image_x_max
        if c.rotation == "pinhole_centre":  # the window's middle third
            n = (g.shape[1] if x1 < 0 else min(x1, g.shape[1])) - x0
            x0, x1 = x0 + n // 3, x0 + n - n // 3
        pr = profile(g, x0, x1, c.vrot_image_y_min, c.vrot_image_y_max)
        if self.prev_trans is None or self.prev_trans.shape != pt.shape or self.prev_rot.shape != pr.shape:
            self.prev_trans, self.prev_rot = pt, pr
            return None
        best, _ = best_shift(pr, self.prev_rot)
        roff: float = refined_shift(pr, self.prev_rot, best) if c.subpixel else best
        if c.rotation == "pinhole_centre":
            focal = g.shape[1] / 2 / math.tan(math.radians(c.camera_fov_deg) / 2)
            roff, tdiff = self._pinhole_rotation(pt, pr, g.shape[1], focal, best, roff)
        else:
            _, tdiff = best_shift(pt, self.prev_trans)
        if c.translation == "normal_flow":  # columns moved: the difference over the profiles' contrast
            contrast = 0.5 * (np.abs(np.diff(pt)).mean() + np.abs(np.diff(self.prev_trans)).mean())
            tdiff = tdiff / contrast if contrast > 0 else 0.0
        self.prev_trans, self.prev_rot = pt, pr
        if c.openratslam_compat or not dt:
            vrot = roff * c.camera_fov_deg / g.shape[1] * c.camera_hz * math.pi / 180.0
            vtrans = tdiff * c.vtrans_scaling
        else:  # per frame: rotation roff * fov / width degrees, translation tdiff * vtrans_scaling / camera_hz
            vrot = roff * c.camera_fov_deg / g.shape[1] / dt * math.pi / 180.0
            vtrans = tdiff * c.vtrans_scaling / (c.camera_hz * dt)
        if c.rotation == "pinhole_centre":  # the angle a shift of the image's centre means, per second
            vrot = math.atan2(roff, focal) * (c.camera_hz if c.openratslam_compat or not dt else 1.0 / dt)
        if self.speed_scale is not None:  # the raw speed: the difference per second
            vtrans = self.speed_scale(tdiff * (c.camera_hz if c.openratslam_compat or not dt else 1.0 / dt))
        return min(vtrans, c.vtrans_max), vrot

    def _pinhole_rotation(self, pt: np.ndarray, pr: np.ndarray, width: int, focal: float, best: int,
                          roff: float) -> tuple[float, float]:
        """(the centre's shift, the translation window's difference with its rotation undone). With
        ``rotation_check`` a shift of the centre that the whole window does not bear out is no turn:
        driving at a wall of repeated texture, the centre matches a whole period away while the
        sides stay put."""
        x0 = self.config.vtrans_image_x_min
        tdiff = rotated_difference(pt, self.prev_trans, x0, width, focal, math.atan2(roff, focal))
        if self.config.rotation_check and best != 0:
            still = refined_shift(pr, self.prev_rot, 0) if self.config.subpixel else 0.0
            tstill = rotated_difference(pt, self.prev_trans, x0, width, focal, math.atan2(still, focal))
            if tstill < tdiff:
                return still, tstill
        return roff, tdiff

    def state_dict(self) -> dict[str, Any]:
        """The previous frame's profiles and the raw speeds seen (``scale: platform``): the sorted
        samples, or their histogram's counts once there were too many."""
        empty = np.zeros(0)
        scale = self.speed_scale
        hist = scale.histogram.state() if scale is not None and scale.histogram is not None else None
        return {"prev_trans": empty if self.prev_trans is None else self.prev_trans,
                "prev_rot": empty if self.prev_rot is None else self.prev_rot,
                "speeds": np.asarray(scale.samples if scale else [], dtype=np.float64),
                **({"speed_counts": hist["counts"], "speeds_below": hist["below"]} if hist else {})}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        trans, rot = np.asarray(st["prev_trans"], np.float64), np.asarray(st["prev_rot"], np.float64)
        self.prev_trans, self.prev_rot = (trans.copy(), rot.copy()) if trans.size else (None, None)
        if self.speed_scale is not None:
            self.speed_scale.samples = sorted(float(v) for v in np.asarray(st["speeds"]).reshape(-1))
            self.speed_scale.histogram = None
            if "speed_counts" in st:
                self.speed_scale.histogram = LogHistogram()
                self.speed_scale.histogram.load({"counts": st["speed_counts"], "below": st["speeds_below"]})
