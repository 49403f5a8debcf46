"""RatSLAM experience map: experiences (nodes), links, dead reckoning and graph relaxation.

As OpenRatSLAM: odometry is integrated into ``accum_dx/dy`` (absolute heading ``accum_facing``,
starting at exp_initial_em_deg) since the current experience; CREATE_NODE places a node at the
current one plus that displacement and links them; CREATE_EDGE links the current experience to an
existing one (no duplicate in either direction); both then make the destination current (resetting
the accumulators, heading = node heading + relative_rad). After every action the graph is relaxed:
``exp_loops`` sequential Gauss-Seidel sweeps in node order and link insertion order, each link
pulling both ends by ``exp_correction`` of its position and heading error.

``openratslam_compat=True`` keeps two C++ quirks that the default fixes: a link's ``delta_time_s``
accumulates without reset (fixed: reset with the other accumulators), and the first experience
does not reset the dead-reckoning accumulators (the C++ current id starts at 0, so making node 0
current is a no-op and the second node is placed with the first node's displacement counted twice).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from .pose_cells import CREATE_EDGE, CREATE_NODE, SET_NODE


class ExperienceMapConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    exp_loops: int = Field(10, ge=0)
    exp_correction: float = 0.5
    exp_initial_em_deg: float = 90.0
    openratslam_compat: bool = False


def clip_pi(a: float) -> float:
    """Wrap into (-pi, pi]."""
    while a > math.pi:
        a -= 2 * math.pi
    while a <= -math.pi:
        a += 2 * math.pi
    return a


def signed_delta(a1: float, a2: float) -> float:
    """Signed smallest rotation from a1 to a2."""
    return clip_pi(a2 - a1)


@njit(cache=True)
def _clip(a):  # pragma: no cover - compiled
    while a > math.pi:
        a -= 2 * math.pi
    while a <= -math.pi:
        a += 2 * math.pi
    return a


@njit(cache=True)
def _relax(x, y, th, lfrom, lto, ld, lhead, lface, order_ptr, order_idx, loops, corr):  # pragma: no cover
    n = x.shape[0]
    for _ in range(loops):
        for e0 in range(n):
            for p in range(order_ptr[e0], order_ptr[e0 + 1]):
                li = order_idx[p]
                e1 = lto[li]
                lx = x[e0] + ld[li] * math.cos(th[e0] + lhead[li])
                ly = y[e0] + ld[li] * math.sin(th[e0] + lhead[li])
                dx = (x[e1] - lx) * corr
                dy = (y[e1] - ly) * corr
                x[e0] += dx
                y[e0] += dy
                x[e1] -= dx
                y[e1] -= dy
                df = _clip(th[e1] - (th[e0] + lface[li]))
                th[e0] = _clip(th[e0] + df * corr)
                th[e1] = _clip(th[e1] - df * corr)


class ExperienceMap:
    def __init__(self, **params: Any) -> None:
        self.cfg = ExperienceMapConfig(**params)
        self.x: list[float] = []
        self.y: list[float] = []
        self.th: list[float] = []
        self.stamp: list[float] = []
        self.links: list[tuple[int, int, float, float, float, float]] = []  # from, to, d, heading, facing, dt
        self.links_from: list[list[int]] = []
        self.link_set: set[tuple[int, int]] = set()
        self.current = -1
        self.accum_dx = self.accum_dy = self.accum_t = 0.0
        self.accum_facing = math.radians(self.cfg.exp_initial_em_deg)
        self.relax_time_s = 0.0

    @property
    def n_experiences(self) -> int:
        return len(self.x)

    def on_odo(self, vtrans: float, vrot: float, dt: float) -> None:
        vtrans, vrot = vtrans * dt, vrot * dt
        self.accum_facing = clip_pi(self.accum_facing + vrot)
        self.accum_dx += vtrans * math.cos(self.accum_facing)
        self.accum_dy += vtrans * math.sin(self.accum_facing)
        self.accum_t += dt

    def create_experience(self, new_id: int, stamp: float = 0.0) -> None:
        if new_id != self.n_experiences:
            raise ValueError(f"new experience id {new_id}, expected {self.n_experiences}")
        cx = self.x[self.current] if self.current >= 0 else 0.0
        cy = self.y[self.current] if self.current >= 0 else 0.0
        self.x.append(cx + self.accum_dx)
        self.y.append(cy + self.accum_dy)
        self.th.append(clip_pi(self.accum_facing))
        self.stamp.append(stamp)
        self.links_from.append([])
        if self.current >= 0:
            self.create_link(self.current, new_id, 0.0)
        self.set_experience(new_id, 0.0)

    def create_link(self, a: int, b: int, rel_rad: float) -> None:
        if not (0 <= a < self.n_experiences and 0 <= b < self.n_experiences):
            raise ValueError(f"link {a} -> {b} names an unknown experience ({self.n_experiences} known)")
        if a == b or (a, b) in self.link_set or (b, a) in self.link_set:
            return
        d = math.hypot(self.accum_dx, self.accum_dy)
        heading = signed_delta(self.th[a], math.atan2(self.accum_dy, self.accum_dx))
        facing = signed_delta(self.th[a], clip_pi(self.accum_facing + rel_rad))
        self.links.append((a, b, d, heading, facing, self.accum_t))
        self.links_from[a].append(len(self.links) - 1)
        self.link_set.add((a, b))

    def set_experience(self, e: int, rel_rad: float) -> None:
        if e == self.current:
            return
        if not 0 <= e < self.n_experiences:
            raise ValueError(f"experience {e} does not exist ({self.n_experiences} known)")
        if self.current < 0 and e == 0 and self.cfg.openratslam_compat:
            # the C++ starts with current id 0, so making the first node current is a no-op and
            # its dead-reckoning accumulators are never reset (the second node lands twice as far)
            self.current = 0
            return
        self.current = e
        self.accum_dx = self.accum_dy = 0.0
        if not self.cfg.openratslam_compat:
            self.accum_t = 0.0
        self.accum_facing = clip_pi(self.th[e] + rel_rad)

    def on_action(self, action: int, src: int, dst: int, rel_rad: float, stamp: float = 0.0) -> None:
        if action == CREATE_NODE:
            self.create_experience(dst, stamp)
        elif action == CREATE_EDGE:
            self.create_link(src, dst, rel_rad)
            self.set_experience(dst, rel_rad)
        elif action == SET_NODE:
            self.set_experience(dst, rel_rad)
        self.iterate()

    def iterate(self) -> None:
        if not self.links or self.cfg.exp_loops == 0:
            return
        import time

        t0 = time.perf_counter()
        x, y, th = np.array(self.x), np.array(self.y), np.array(self.th)
        L = np.array(self.links)
        counts = np.array([len(lf) for lf in self.links_from], dtype=np.int64)
        ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        idx = np.array([li for lf in self.links_from for li in lf], dtype=np.int64)
        _relax(x, y, th, L[:, 0].astype(np.int64), L[:, 1].astype(np.int64), L[:, 2], L[:, 3], L[:, 4],
               ptr, idx, self.cfg.exp_loops, self.cfg.exp_correction)
        self.x, self.y, self.th = x.tolist(), y.tolist(), th.tolist()
        self.relax_time_s = time.perf_counter() - t0

    def current_pose(self) -> tuple[float, float, float]:
        """The current experience's pose (what OpenRatSLAM publishes as RobotPose)."""
        if self.current < 0:
            return (self.accum_dx, self.accum_dy, self.accum_facing)
        return (self.x[self.current], self.y[self.current], self.th[self.current])

    def robot_pose(self) -> tuple[float, float, float]:
        """Current experience plus the dead reckoning since it: a pose for every frame."""
        if self.current < 0:
            return (self.accum_dx, self.accum_dy, self.accum_facing)
        return (self.x[self.current] + self.accum_dx, self.y[self.current] + self.accum_dy, self.accum_facing)

    def export(self) -> dict[str, Any]:
        return {"nodes": [{"id": i, "x": self.x[i], "y": self.y[i], "theta": self.th[i], "stamp": self.stamp[i]}
                          for i in range(self.n_experiences)],
                "links": [{"from": int(a), "to": int(b), "d": d, "heading": h, "facing": f, "dt": t}
                          for a, b, d, h, f, t in self.links]}

    def state_dict(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "th": self.th, "stamp": self.stamp, "links": [list(lk) for lk in self.links],
                "scalars": [self.current, self.accum_dx, self.accum_dy, self.accum_t, self.accum_facing]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.x, self.y, self.th = [float(v) for v in st["x"]], [float(v) for v in st["y"]], [float(v) for v in st["th"]]
        self.stamp = [float(v) for v in st["stamp"]]
        self.links, self.links_from, self.link_set = [], [[] for _ in self.x], set()
        for a, b, d, h, f, t in st["links"]:
            self.links.append((int(a), int(b), float(d), float(h), float(f), float(t)))
            self.links_from[int(a)].append(len(self.links) - 1)
            self.link_set.add((int(a), int(b)))
        c, self.accum_dx, self.accum_dy, self.accum_t, self.accum_facing = st["scalars"]
        self.current = int(c)
