"""The embedded default data: a deterministic synthetic world with loops, odometry and ground truth.

A 10 m x 8 m floor plan of textured walls: an outer wall and a central block make a ring corridor
(the loop), door frames split it into four rooms, a pillar and a partition stand in two of them.
Every wall has its own seeded procedural texture with dark "poster" blobs as landmarks; one texture
is used twice and all door frames share one, so perceptual aliasing exists. Frames are ray cast per
image column (default 416x240 RGB, 90 deg field of view, iRat-like).

The robot drives the ring: ``laps_cw`` laps one way, then ``laps_ccw`` the other (revisits in both
directions), turning on the spot where the direction changes; the route is closed, so ``loop:
true`` or ``frames`` beyond one route repeat it seamlessly. Wheel odometry = true motion with a
speed scale bias, a yaw-rate bias, a yaw-rate random walk and white noise; ground truth is exact.
Everything is vectorised numpy and seeded, the frame's composition a compiled loop (docs/sources.md, "synthetic").
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .base import Source, SourceFrame

#: wall segments (x0, y0, x1, y1, texture id); texture 7 is used twice and texture 12 by every
#: door frame (aliasing)
WALLS = np.array([
    # outer boundary 10 x 8
    (0, 0, 5, 0, 0), (5, 0, 10, 0, 1), (10, 0, 10, 4, 2), (10, 4, 10, 8, 3),
    (10, 8, 5, 8, 4), (5, 8, 0, 8, 5), (0, 8, 0, 4, 6), (0, 4, 0, 0, 7),
    # central block 3..7 x 2.5..5.5: the ring corridor is between it and the outer wall
    (3, 2.5, 7, 2.5, 8), (7, 2.5, 7, 5.5, 9), (7, 5.5, 3, 5.5, 10), (3, 5.5, 3, 2.5, 7),
    # a partition that narrows the top-right part of the ring
    (8.5, 8, 8.5, 6.8, 11),
    # door frames: 1.3 m doors on the route split the ring into four rooms
    (5, 0, 5, 0.6, 12), (5, 2.5, 5, 1.9, 12), (5, 8, 5, 7.3, 12), (5, 5.5, 5, 5.9, 12),
    (10, 4, 9.3, 4, 12), (7, 4, 7.7, 4, 12),
    # a 0.4 m pillar in the north-west room
    (0.4, 5.0, 0.8, 5.0, 13), (0.8, 5.0, 0.8, 5.4, 14), (0.8, 5.4, 0.4, 5.4, 13), (0.4, 5.4, 0.4, 5.0, 14),
], dtype=np.float64)
WALL_HEIGHT = 1.2
TEX_PX_PER_M = 200
TEX_ROWS = 256
CAMERA_HEIGHT = 0.6
#: the route: the middle of the ring corridor (counter-clockwise seen from above), corners rounded
#: with CORNER_RADIUS so that the robot always moves along its heading, as a wheeled robot does
ROUTE = np.array([(1.5, 1.25), (8.5, 1.25), (8.5, 6.6), (1.5, 6.6), (1.5, 1.25)])
CORNER_RADIUS = 0.6
#: every lap starts and ends here, facing east, in the middle of the south corridor
ROUTE_START = np.array([3.0, 1.25])


def _textures(seed: int, n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"freq": rng.uniform(1.0, 6.0, (n, 3)), "phase": rng.uniform(0, 2 * np.pi, (n, 3)),
            "vfreq": rng.uniform(0.5, 4.0, (n, 2)), "colour": rng.uniform(0.25, 1.0, (n, 3)),
            "stripe": rng.uniform(0.15, 0.6, n), "blob": rng.uniform(0, 1, (n, 4, 2))}


def _route_polyline(per_arc: int = 64) -> np.ndarray:
    """Dense closed polyline of the route from ROUTE_START: straight legs and quarter circles."""
    corners = ROUTE[1:]
    pts = [ROUTE_START]
    for i, c in enumerate(corners):
        d_in = corners[i] - corners[i - 1] if i else corners[0] - ROUTE[0]
        d_in = d_in / np.linalg.norm(d_in)
        centre = c - d_in * CORNER_RADIUS + np.array([-d_in[1], d_in[0]]) * CORNER_RADIUS  # left turns
        a0 = math.atan2(-d_in[0], d_in[1])  # the angle of (start - centre) = the right normal
        ang = a0 + np.linspace(0.0, math.pi / 2, per_arc)
        pts.extend(centre + CORNER_RADIUS * np.column_stack([np.cos(ang), np.sin(ang)]))
    pts.append(ROUTE_START)
    return np.array(pts)


def _route_poses(step: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions every ``step`` metres along the closed route (the start not repeated at the end),
    and the distance of each from the start."""
    poly = _route_polyline()
    seg = np.diff(poly, axis=0)
    lens = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0], np.cumsum(lens)])
    n = int(round(cum[-1] / step))
    s = np.arange(n) * (cum[-1] / n)  # an integral number of equal steps: the lap closes exactly
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[k]) / lens[k]
    return poly[k] + seg[k] * t[:, None], s


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

    @property
    def segments(self) -> np.ndarray:
        """Wall segments as (n, 2, 2) end points in metres, for plots (``ax.add_collection``)."""
        return self.walls[:, :4].reshape(-1, 2, 2).copy()

    @staticmethod
    def bounds() -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the floor plan."""
        return (float(WALLS[:, [0, 2]].min()), float(WALLS[:, [1, 3]].min()),
                float(WALLS[:, [0, 2]].max()), float(WALLS[:, [1, 3]].max()))

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
        """The (height, width, 3) uint8 RGB frame seen from (x, y) facing th: per column the wall
        it hits spans rows top..bottom, textured from the atlas and shaded by its distance; the
        other rows are floor and ceiling (:func:`_compose`, a compiled loop: the source's cost per
        frame, which a camera does not have, is not taken from the stages' cores)."""
        if not hasattr(self, "atlas"):
            self._build_atlas()
        dist, _tid, along = self.cast_walls(x, y, th)
        dist = np.maximum(dist, 0.05)
        h2 = self.height / 2
        top = h2 - self.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / dist
        bottom = h2 + self.focal * CAMERA_HEIGHT / dist
        ui = np.minimum((along * TEX_PX_PER_M).astype(np.int32), self.atlas.shape[2] - 1)
        shade = (1.0 / (1.0 + 0.15 * dist)).astype(np.float32)
        img = np.empty((self.height, self.width, 3), np.uint8)
        _compose(self.atlas, self._hit_wall, top, bottom, ui, shade, self.background[:, 0, :], img)
        return img

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


@njit(cache=True)
def _compose(atlas: np.ndarray, seg: np.ndarray, top: np.ndarray, bottom: np.ndarray, ui: np.ndarray,
             shade: np.ndarray, background: np.ndarray, img: np.ndarray) -> None:
    """img[r, c] = the atlas texel of wall seg[c] at row v (0 at the top of the wall, 1 at the
    floor; v = (r + 0.5 - top[c]) / (bottom[c] - top[c])) times shade[c] where 0 <= v < 1, else
    background[r]; float32 products truncated to uint8, as numpy's astype does."""
    height, width = img.shape[0], img.shape[1]
    tex_rows = atlas.shape[1]
    for c in range(width):
        span = bottom[c] - top[c]
        k, u, s = seg[c], ui[c], shade[c]
        for r in range(height):
            v = (r + 0.5 - top[c]) / span
            if v >= 0 and v < 1:
                vi = min(max(np.int32(v * tex_rows), 0), tex_rows - 1)
                for ch in range(3):
                    img[r, c, ch] = np.uint8(np.float32(atlas[k, vi, u, ch]) * s)
            else:
                for ch in range(3):
                    img[r, c, ch] = np.uint8(background[r, ch])


class SyntheticConfig(BaseModel):
    """Parameters of :class:`SyntheticWorldSource` (the ``source.params`` of ``kind: synthetic``)."""

    model_config = ConfigDict(extra="forbid")

    #: frames to emit; None = one route (or endless with ``loop``); more than a route repeats it
    frames: int | None = Field(None, ge=1)
    laps_cw: int = Field(2, ge=0)
    laps_ccw: int = Field(1, ge=0)
    #: forward speed (m/s) and in-place turning speed where the direction changes (rad/s)
    speed: float = Field(0.3, gt=0)
    turn_rate: float = Field(0.8, gt=0)
    rate_hz: float = Field(10.0, gt=0)
    width: int = Field(416, ge=8)
    height: int = Field(240, ge=8)
    fov_deg: float = Field(90.0, gt=0, lt=180)
    seed: int = 0
    loop: bool = False
    #: wheel odometry: speed scale, yaw-rate bias (rad/s), white noise (relative speed, rad/s yaw)
    odom_scale_bias: float = Field(1.03, gt=0)
    odom_yaw_bias: float = 0.01
    odom_noise: float = Field(0.01, ge=0)
    #: standard deviation of the yaw-rate bias random walk per frame, as a fraction of odom_noise
    odom_walk: float = Field(0.1, ge=0)
    #: the odometry noise's seed (None: seed + 1): the same images with another odometry
    odom_seed: int | None = None

    @model_validator(mode="after")
    def _one_lap(self) -> SyntheticConfig:
        if self.laps_cw + self.laps_ccw < 1:
            raise ValueError("the route needs at least one lap (laps_cw + laps_ccw >= 1)")
        return self


def _lap_headings(lap: np.ndarray) -> np.ndarray:
    """The direction of motion along the closed lap (central difference: the tangent on arcs)."""
    d = np.roll(lap, -1, axis=0) - np.roll(lap, 1, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def _turn(xy: np.ndarray, h_from: float, h_to: float, step: float) -> np.ndarray:
    """Poses strictly between two headings at one position, turning the short way by <= step rad."""
    delta = math.remainder(h_to - h_from, 2 * math.pi)
    n = max(0, math.ceil(abs(delta) / step) - 1)
    h = h_from + delta * np.arange(1, n + 1) / (n + 1)
    return np.column_stack([np.repeat(xy[None], n, axis=0).reshape(n, 2), h])


def build_route(step: float, laps_cw: int, laps_ccw: int, turn_step: float) -> tuple[np.ndarray, list]:
    """(x, y, theta) per frame of the whole closed route, and (start, stop, direction) per lap.

    Every lap starts at ``ROUTE_START``; where the direction changes, and at the end when the last lap's
    direction differs from the first's, the robot turns on the spot there, so consecutive poses are
    always one step or one turn increment apart, also across the wrap-around.
    """
    pts, _ = _route_poses(step)
    laps = {+1: pts, -1: np.roll(pts[::-1], 1, axis=0)}  # both start at pts[0]
    heads = {d: _lap_headings(lap) for d, lap in laps.items()}
    dirs = [+1] * laps_cw + [-1] * laps_ccw
    parts: list[np.ndarray] = []
    spans: list[tuple[int, int, int]] = []
    n = 0
    for j, d in enumerate(dirs):
        if j and d != dirs[j - 1]:
            t = _turn(pts[0], heads[dirs[j - 1]][0], heads[d][0], turn_step)
            parts.append(t)
            n += len(t)
        parts.append(np.column_stack([laps[d], heads[d]]))
        spans.append((n, n + len(pts), "cw" if d > 0 else "ccw"))
        n += len(pts)
    if dirs[-1] != dirs[0]:
        parts.append(_turn(pts[0], heads[dirs[-1]][0], heads[dirs[0]][0], turn_step))
    route = np.concatenate(parts)
    route[:, 2] = np.unwrap(route[:, 2])
    return route, spans


class SyntheticWorldSource(Source):
    """Frames, wheel odometry and ground truth of a drive through :class:`SyntheticWorld`.

    Parameters are those of :class:`SyntheticConfig`. ``gt`` holds the (x, y, theta) of every frame
    of one route, ``laps`` the (start, stop, "cw"/"ccw") frame span of each lap.
    """

    #: the parameters, checked before a run starts (sources/params.py)
    params_model = SyntheticConfig

    def __init__(self, **params: Any) -> None:
        cfg = SyntheticConfig(**params)
        self.config = cfg
        self.world = SyntheticWorld(cfg.width, cfg.height, cfg.fov_deg, seed=cfg.seed)
        self.rate_hz = cfg.rate_hz
        self.seed = cfg.seed
        self.loop = cfg.loop
        self.gt, self.laps = build_route(cfg.speed / cfg.rate_hz, cfg.laps_cw, cfg.laps_ccw,
                                         cfg.turn_rate / cfg.rate_hz)
        self.route_len = len(self.gt)
        self.length = cfg.frames if cfg.frames is not None else (None if cfg.loop else self.route_len)

    def odometry(self, n: int) -> np.ndarray:
        """(vtrans, vrot, dt) of the first ``n`` frames: the true motion since the previous frame
        with v' = v * scale * (1 + N(0, noise)) and w' = w + yaw_bias + b_k + N(0, noise), where the
        bias b_k is a random walk. Seeded by ``odom_seed`` (None: ``seed + 1``), independent of the
        images."""
        cfg = self.config
        rng = np.random.default_rng(cfg.seed + 1 if cfg.odom_seed is None else cfg.odom_seed)
        dt = 1.0 / cfg.rate_hz
        k = np.arange(n) % self.route_len
        cur = self.gt[k]
        prev = self.gt[(k - 1) % self.route_len]
        prev[0] = cur[0]  # the first frame has not moved
        dist = np.hypot(cur[:, 0] - prev[:, 0], cur[:, 1] - prev[:, 1])
        dth = np.remainder(cur[:, 2] - prev[:, 2] + math.pi, 2 * math.pi) - math.pi
        noise = rng.normal(0.0, 1.0, (n, 3))
        walk = np.cumsum(noise[:, 0] * cfg.odom_noise * cfg.odom_walk)
        vtrans = dist / dt * cfg.odom_scale_bias * (1 + cfg.odom_noise * noise[:, 1])
        vrot = dth / dt + cfg.odom_yaw_bias + walk + cfg.odom_noise * noise[:, 2]
        dts = np.full(n, dt)
        vtrans[0] = vrot[0] = dts[0] = 0.0  # nothing precedes the first frame
        return np.column_stack([vtrans, vrot, dts])

    def __iter__(self) -> Iterator[SourceFrame]:
        dt = 1.0 / self.rate_hz
        chunk = max(self.route_len, 1)
        i = 0
        odo = self.odometry(chunk if self.length is None else self.length)
        while self.length is None or i < self.length:
            if i >= len(odo):  # endless: extend the (deterministic) odometry stream
                odo = self.odometry(len(odo) + chunk)
            x, y, th = self.gt[i % self.route_len]
            img = self.world.render(x, y, th)
            yield SourceFrame(frame=i, stamp=i * dt, image=img, encoding="rgb8",
                              odom=(float(odo[i, 0]), float(odo[i, 1]), float(odo[i, 2])),
                              groundtruth=(float(x), float(y), float(math.remainder(th, 2 * math.pi))))
            i += 1

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        return True  # the simulated wheel odometry

    def info(self) -> dict[str, Any]:
        return {"kind": "synthetic", "frames": self.length, "route_frames": self.route_len,
                "laps": [list(lap) for lap in self.laps],
                "size": [self.world.width, self.world.height], "rate_hz": self.rate_hz, "seed": self.seed}
