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
TEX_PX_PER_M = 200
TEX_ROWS = 256
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
        """Per column: perpendicular distance, texture id, coordinate along the wall (m)."""
        return self.cast_walls(x, y, th)

    def _build_atlas(self) -> None:
        """Every wall's texture rendered once into an image (TEX_PX_PER_M columns per metre, TEX_ROWS
        rows over the wall's height), so a frame is a gather, not a pattern evaluation per pixel."""
        T = self.tex
        lens = np.hypot(self.walls[:, 2] - self.walls[:, 0], self.walls[:, 3] - self.walls[:, 1])
        width = int(np.ceil(lens.max() * TEX_PX_PER_M)) + 1
        u = (np.arange(width) / TEX_PX_PER_M)[None, :]
        v = ((np.arange(TEX_ROWS) + 0.5) / TEX_ROWS)[:, None]
        atlas = np.zeros((len(self.walls), TEX_ROWS, width, 3), dtype=np.float32)
        for k in range(len(self.walls)):
            tid = int(self.walls[k, 4])
            f, p, vf = T["freq"][tid], T["phase"][tid], T["vfreq"][tid]
            pattern = (0.5 + 0.25 * np.sin(f[0] * u * np.pi + p[0])
                       + 0.15 * np.sin(f[1] * u * 2 * np.pi + vf[0] * v * 6 + p[1])
                       + 0.1 * np.sign(np.sin(vf[1] * v * 2 * np.pi * 3 + f[2] * u)))
            for bl in range(4):  # large-scale landmarks: dark blobs positioned by the texture's seed
                cu, cv = T["blob"][tid, bl, 0] * 5.0, T["blob"][tid, bl, 1]
                pattern = pattern - 0.35 * np.exp(-(((u - cu) / 0.35) ** 2 + ((v - cv) / 0.18) ** 2))
            atlas[k] = np.clip(pattern, 0, 1)[..., None] * T["colour"][tid][None, None]
        self.atlas = (atlas * 255).astype(np.uint8)  # 4x smaller than float: the gather stays in cache
        # floor and ceiling shading depends on the row only
        h2 = self.height / 2
        r = self.rows
        floor_d = np.where(r > h2, self.focal * CAMERA_HEIGHT / np.maximum(r - h2, 1e-3), np.inf)
        ceil_d = np.where(r < h2, self.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / np.maximum(h2 - r, 1e-3), np.inf)
        bg = np.where(r > h2, 0.45 / (1 + 0.3 * floor_d), 0.8 / (1 + 0.3 * ceil_d))
        self.background = (bg[..., None] * np.array([0.9, 0.85, 0.8]) * 255).astype(np.float32)  # (H, 1, 3)

    def render(self, x: float, y: float, th: float) -> np.ndarray:
        if not hasattr(self, "atlas"):
            self._build_atlas()
        dist, _tid, along = self.cast_walls(x, y, th)
        seg = self._hit_wall
        dist = np.maximum(dist, 0.05)
        h2 = self.height / 2
        top = h2 - self.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / dist
        bottom = h2 + self.focal * CAMERA_HEIGHT / dist
        v = (self.rows - top[None]) / (bottom - top)[None]  # 0 at the top of the wall, 1 at the floor
        inside = (v >= 0) & (v < 1)
        vi = np.clip((v * TEX_ROWS).astype(np.int32), 0, TEX_ROWS - 1)
        ui = np.minimum((along * TEX_PX_PER_M).astype(np.int32), self.atlas.shape[2] - 1)
        cols = self.atlas[seg[None, :], vi, ui[None, :]]  # (H, W, 3)
        shade = (1.0 / (1.0 + 0.15 * dist)).astype(np.float32)[None, :, None]
        img = np.where(inside[..., None], cols * shade, self.background)
        return img.astype(np.uint8)

    def cast_walls(self, x: float, y: float, th: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`cast`, remembering which wall segment each column hit (for the texture atlas)."""
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
        self._hit_wall = k
        dist = t[cols, k] * np.cos(self.col_angles)
        seglen = np.hypot(ex, ey)[0, k]
        return dist, self.walls[k, 4].astype(int), u[cols, k] * seglen


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
