"""The embedded default data: a deterministic synthetic world with loops, odometry and ground truth.

A 10 m x 8 m floor plan of textured walls: an outer wall, a central block that makes the space a
ring corridor (a loop), and a partition that makes a side room. Every wall has its own procedural
texture (seeded stripes, blobs and colour) so places are recognisable; two walls deliberately share
a texture so that perceptual aliasing exists. Frames are rendered per image column by ray casting
(default 416x240 RGB, 90 deg field of view, iRat-like), floor and ceiling shaded by distance.

The robot drives the ring at 0.3 m/s, 10 Hz: two laps clockwise, then one lap counter-clockwise
(revisits in both directions), so at least three laps. Wheel odometry = true motion with a speed
scale bias, a yaw-rate bias and a random walk; ground truth is exact. ``loop: true`` repeats the
route for long runs. Everything is vectorised numpy and seeded.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from .base import Source, SourceFrame

#: wall segments (x0, y0, x1, y1, texture id); texture 7 is used twice (aliasing)
WALLS = np.array([
    # outer boundary 10 x 8
    (0, 0, 5, 0, 0), (5, 0, 10, 0, 1), (10, 0, 10, 4, 2), (10, 4, 10, 8, 3),
    (10, 8, 5, 8, 4), (5, 8, 0, 8, 5), (0, 8, 0, 4, 6), (0, 4, 0, 0, 7),
    # central block 3..7 x 2.5..5.5: the ring corridor is between it and the outer wall
    (3, 2.5, 7, 2.5, 8), (7, 2.5, 7, 5.5, 9), (7, 5.5, 3, 5.5, 10), (3, 5.5, 3, 2.5, 7),
    # a partition that narrows the top-right part of the ring
    (8.5, 8, 8.5, 6.8, 11),
], dtype=np.float64)
WALL_HEIGHT = 1.2
CAMERA_HEIGHT = 0.6
#: the route: the middle of the ring corridor (clockwise seen from above)
ROUTE = np.array([(1.5, 1.25), (8.5, 1.25), (8.5, 6.6), (1.5, 6.6), (1.5, 1.25)])


def _textures(seed: int, n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"freq": rng.uniform(1.0, 6.0, (n, 3)), "phase": rng.uniform(0, 2 * np.pi, (n, 3)),
            "vfreq": rng.uniform(0.5, 4.0, (n, 2)), "colour": rng.uniform(0.25, 1.0, (n, 3)),
            "stripe": rng.uniform(0.15, 0.6, n), "blob": rng.uniform(0, 1, (n, 4, 2))}


def _route_poses(step: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions every ``step`` metres along the closed route, and the cumulative distance."""
    seg = np.diff(ROUTE, axis=0)
    lens = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0], np.cumsum(lens)])
    s = np.arange(0, cum[-1], step)
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[k]) / lens[k]
    pts = ROUTE[k] + seg[k] * t[:, None]
    return pts, s


class SyntheticWorld:
    """Geometry, textures and the renderer."""

    def __init__(self, width: int = 416, height: int = 240, fov_deg: float = 90.0, seed: int = 0) -> None:
        self.width, self.height = width, height
        self.fov = math.radians(fov_deg)
        self.walls = WALLS.copy()
        self.tex = _textures(seed, int(self.walls[:, 4].max()) + 1)
        self.focal = (width / 2) / math.tan(self.fov / 2)
        # column ray angles relative to the heading (left of the image = positive angle)
        self.col_angles = np.arctan((width / 2 - (np.arange(width) + 0.5)) / self.focal)
        self.rows = np.arange(height)[:, None] + 0.5

    def cast(self, x: float, y: float, th: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per column: distance along the ray, texture id, coordinate along the wall (m)."""
        ang = th + self.col_angles
        dx, dy = np.cos(ang)[:, None], np.sin(ang)[:, None]
        x0, y0, x1, y1 = (self.walls[:, i][None] for i in range(4))
        ex, ey = x1 - x0, y1 - y0
        den = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((x0 - x) * ey - (y0 - y) * ex) / den
            u = ((x0 - x) * dy - (y0 - y) * dx) / den
        valid = (np.abs(den) > 1e-12) & (t > 1e-6) & (u >= 0) & (u <= 1)
        t = np.where(valid, t, np.inf)
        k = np.argmin(t, axis=1)
        cols = np.arange(len(k))
        dist = t[cols, k] * np.cos(self.col_angles)  # perpendicular distance: no fish-eye
        seglen = np.hypot(ex, ey)[0, k]
        return dist, self.walls[k, 4].astype(int), u[cols, k] * seglen

    def render(self, x: float, y: float, th: float) -> np.ndarray:
        dist, tid, along = self.cast(x, y, th)
        dist = np.maximum(dist, 0.05)
        h2 = self.height / 2
        top = h2 - self.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / dist
        bottom = h2 + self.focal * CAMERA_HEIGHT / dist
        r = self.rows
        v = (r - top[None]) / (bottom - top)[None]  # 0 at the top of the wall, 1 at the floor
        inside = (v >= 0) & (v <= 1)
        T = self.tex
        f, p, vf = T["freq"][tid], T["phase"][tid], T["vfreq"][tid]
        u = along[None]
        pattern = (0.5 + 0.25 * np.sin(f[None, :, 0] * u * 2 * np.pi / 2 + p[None, :, 0])
                   + 0.15 * np.sin(f[None, :, 1] * u * 2 * np.pi + vf[None, :, 0] * v * 6 + p[None, :, 1])
                   + 0.1 * np.sign(np.sin(vf[None, :, 1] * v * 2 * np.pi * 3 + f[None, :, 2] * u)))
        # large-scale landmarks: a few dark blobs per wall, positioned by the texture's seed
        for b in range(4):
            cu = T["blob"][tid, b, 0] * 5.0
            cv = T["blob"][tid, b, 1]
            pattern -= 0.35 * np.exp(-(((u - cu) / 0.35) ** 2 + ((v - cv) / 0.18) ** 2))
        shade = 1.0 / (1.0 + 0.15 * dist)[None]
        wall = np.clip(pattern * shade, 0, 1)[..., None] * T["colour"][tid][None]
        floor_d = np.where(r > h2, self.focal * CAMERA_HEIGHT / np.maximum(r - h2, 1e-3), np.inf)
        ceil_d = np.where(r < h2, self.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / np.maximum(h2 - r, 1e-3), np.inf)
        bg = np.where(r > h2, 0.45 / (1 + 0.3 * floor_d), 0.8 / (1 + 0.3 * ceil_d))
        bg = np.broadcast_to(bg, (self.height, self.width))[..., None] * np.array([0.9, 0.85, 0.8])
        img = np.where(inside[..., None], wall, bg)
        return (img * 255).astype(np.uint8)


class SyntheticWorldSource(Source):
    """Frames, wheel odometry and ground truth of a drive through :class:`SyntheticWorld`."""

    def __init__(self, frames: int | None = None, laps_cw: int = 2, laps_ccw: int = 1, speed: float = 0.3,
                 rate_hz: float = 10.0, width: int = 416, height: int = 240, seed: int = 0,
                 loop: bool = False, odom_scale_bias: float = 1.03, odom_yaw_bias: float = 0.01,
                 odom_noise: float = 0.01) -> None:
        if laps_cw + laps_ccw < 1:
            raise ValueError("the route needs at least one lap")
        self.world = SyntheticWorld(width, height, seed=seed)
        self.rate_hz = rate_hz
        self.seed = seed
        self.loop = loop
        self.bias = (odom_scale_bias, odom_yaw_bias, odom_noise)
        step = speed / rate_hz
        pts, _ = _route_poses(step)
        laps = [pts] * laps_cw + [pts[::-1]] * laps_ccw
        xy = np.concatenate(laps)
        ahead = np.roll(xy, -10, axis=0)  # look 10 frames ahead: smooth turns at the corners
        ahead[-10:] = xy[-1] + (xy[-1] - xy[-11])
        heading = np.unwrap(np.arctan2(ahead[:, 1] - xy[:, 1], ahead[:, 0] - xy[:, 0]))
        self.gt = np.column_stack([xy, heading])
        self.route_len = len(self.gt)
        self.length = frames if frames is not None else (None if loop else self.route_len)

    def __iter__(self) -> Iterator[SourceFrame]:
        rng = np.random.default_rng(self.seed + 1)
        scale, yaw_bias, noise = self.bias
        dt = 1.0 / self.rate_hz
        walk = 0.0
        i = 0
        while self.length is None or i < self.length:
            k = i % self.route_len
            x, y, th = self.gt[k]
            pk = self.gt[k - 1] if k > 0 else self.gt[self.route_len - 1 if i else 0]
            dist = math.hypot(x - pk[0], y - pk[1])
            dth = (th - pk[2] + math.pi) % (2 * math.pi) - math.pi
            if k == 0 and i > 0:
                dist, dth = 0.0, 0.0
            walk += rng.normal(0, noise * 0.1)
            vtrans = dist / dt * scale * (1 + rng.normal(0, noise))
            vrot = dth / dt + yaw_bias + walk + rng.normal(0, noise)
            img = self.world.render(x, y, th)
            yield SourceFrame(frame=i, stamp=i * dt, image=img, encoding="rgb8",
                              odom=(vtrans, vrot, dt if i else 0.0),
                              groundtruth=(float(x), float(y), float(math.atan2(math.sin(th), math.cos(th)))))
            i += 1

    def info(self) -> dict[str, Any]:
        return {"kind": "synthetic", "frames": self.length, "route_frames": self.route_len,
                "size": [self.world.width, self.world.height], "rate_hz": self.rate_hz, "seed": self.seed}
