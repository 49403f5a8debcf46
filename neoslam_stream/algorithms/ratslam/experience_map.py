"""RatSLAM experience map (OpenRatSLAM's ``ExperienceMap``): experiences, links, dead reckoning
and graph relaxation.

Odometry accumulates into ``accum_dx/dy`` along the absolute heading ``accum_facing`` (starting at
exp_initial_em_deg) since the current experience. CREATE_NODE places a node at the current one plus
that displacement and links them; CREATE_EDGE links the current experience to an existing one (no
duplicate in either direction); both make the destination current (heading = its heading +
relative_rad). After every action ``exp_loops`` Gauss-Seidel sweeps in node and link order pull
both ends of each link by ``exp_correction`` of its position and heading error; or, with
``relaxation: least_squares``, each new loop link re-solves the whole map exactly (graph_solve.py);
with ``bias_walk``, as a pose graph whose yaw-rate bias wanders as far as the run measured
(pose_graph.py). With ``prune_m`` > 0 the map is then kept at a bounded density: experiences closer
than that to an older one merge into it, their links rewired (map_pruning.py; Milford and Wyeth's
pruning for persistent navigation).

``openratslam_compat=True`` keeps three C++ quirks that the default fixes (marked "fix n" below,
tabled in docs/ratslam.md). The map maps the pose cells' experience ids onto its own indices, so a
lost or repeated action is repaired (a link to a known id, a node for an unknown one), not refused.

Sessions (``neoslam run --map``): a new session's robot is anywhere, so :meth:`new_session` makes no
experience current, and the session's first experience starts a part of the map of its own, linked
to nothing of the old one (a link from the old session's last experience would say the robot drove
from there, a branch through walls). The first link between two parts (the new session's first
recognised old place) moves the newer part rigidly onto the older, so that the link holds exactly:
the old map stays where it was, and the new session's experiences and poses are on it.
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.sparse.csgraph import connected_components

from .._config import make_config
from ..errors import InvalidInput
from .actions import CREATE_EDGE, CREATE_NODE, SET_NODE
from .angles import clip_pi
from .graph_solve import relax_least_squares
from .map_poses import export_node_poses
from .map_pruning import compose, prune
from .pose_graph import bias_walk_weights, relax_pose_graph
from .sweeps import relax_sweeps


class ExperienceMapConfig(BaseModel):
    """OpenRatSLAM's experience-map parameters with the C++ code defaults."""

    model_config = ConfigDict(extra="forbid")

    exp_loops: int = Field(10, ge=0)
    exp_correction: float = 0.5
    exp_initial_em_deg: float = 90.0
    openratslam_compat: bool = False
    #: robust relaxation: k > 0 (metres) scales a link's pull by the Cauchy weight k^2 / (k^2 + r^2)
    #: of its position error r, so a wrong loop closure (r stays large) moves the map by at most
    #: exp_correction * k / 2 per sweep; 0: every link pulls by exp_correction (OpenRatSLAM)
    exp_robust_m: float = Field(0.0, ge=0)
    #: ``sweeps``: OpenRatSLAM's exp_loops sweeps after every action; ``least_squares``: after an
    #: action that adds a loop link, the headings and positions that agree best with every link,
    #: solved exactly (graph_solve.py), and nothing after the others, whose new experience lies
    #: where its link says; exp_loops and exp_correction are then unused; ``bias_walk``: as
    #: least_squares, then a pose graph with a yaw-rate bias per link in a random walk whose step
    #: variance is the wander the bias estimator measured (pose_graph.py; least squares until the
    #: run has measured one, and always without the estimator)
    relaxation: Literal["sweeps", "least_squares", "bias_walk"] = "sweeps"
    #: bias_walk: a link's position error (sd) as a fraction of its length
    walk_position_rel: float = Field(0.05, gt=0)
    #: bias_walk: a link's heading error variance per second of its duration, rad^2/s
    walk_heading_var: float = Field(2e-4, gt=0)
    #: > 0 (metres): after each relaxation that followed a loop link, a settled experience closer
    #: than this to an older one is merged into it and its links rewired (map_pruning.py): the map
    #: grows with the places, not with the laps. 0: every experience stays (OpenRatSLAM)
    prune_m: float = Field(0.0, ge=0)
    #: with prune_m: an experience merges only into one made at least this many seconds of driving
    #: before it (an earlier visit's; one visit's experiences are as far apart as the pose cells
    #: made them). 0: into any older one
    prune_gap_s: float = Field(0.0, ge=0)
    #: with prune_m: an experience merges only once it is this many seconds of driving old (the
    #: closures around it have placed it). 0: as soon as a cycle passes through it
    prune_age_s: float = Field(0.0, ge=0)

    @model_validator(mode="after")
    def _robust_needs_sweeps(self) -> ExperienceMapConfig:
        if self.prune_m > 0 and self.openratslam_compat:
            raise ValueError("prune_m merges experiences, which OpenRatSLAM never does (set prune_m: 0 "
                             "or openratslam_compat: false)")
        if self.relaxation != "sweeps" and self.exp_robust_m > 0:
            raise ValueError(f"exp_robust_m weights the sweeps' pulls; relaxation {self.relaxation} has none "
                             "(set exp_robust_m: 0 or relaxation: sweeps)")
        return self


def signed_delta(a1: float, a2: float) -> float:
    """Signed smallest rotation from a1 to a2."""
    return clip_pi(a2 - a1)


def _grow(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` with room for at least n rows (capacity doubles, so appends are amortised O(1))."""
    if n <= a.shape[0]:
        return a
    out = np.zeros((max(n, 2 * a.shape[0], 64),) + a.shape[1:], dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


class ExperienceMap:
    """OpenRatSLAM's ``ExperienceMap`` driven as ``main_em.cpp`` drives it.

    Per odometry message :meth:`on_odo`; per pose-cell action :meth:`on_action` (which relaxes the
    graph once). Nodes live in growable numpy arrays (``x``, ``y``, ``th``, ``stamp`` are views)
    so that relaxation of large maps needs no conversion.
    """

    def __init__(self, config: ExperienceMapConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(ExperienceMapConfig, config, overrides)
        self._nodes = np.zeros((0, 4))  # x, y, th, stamp
        self._born = np.zeros(0)  # when each experience was made, in seconds of driving (``clock``)
        self._n = 0
        #: seconds of odometry integrated by this map, over every session (what ``prune_gap_s`` reads)
        self.clock = 0.0
        self._lf = np.zeros((0, 2), dtype=np.int64)  # from, to (indices)
        self._lv = np.zeros((0, 4))  # d, heading, facing, delta_time_s
        self._m = 0
        self.link_set: set[tuple[int, int]] = set()
        self.ids: list[int] = []  # index -> experience id (as the pose cells number them)
        self.index: dict[int, int] = {}  # experience id -> index
        #: index -> the connected part of the map it belongs to (a new session starts a part)
        self.part: list[int] = []
        self._cur = -1
        self.accum_dx = self.accum_dy = self.accum_t = 0.0
        self.accum_facing = math.radians(self.config.exp_initial_em_deg)
        self.relax_time_s = 0.0
        self.repaired_actions = 0
        #: the yaw-rate bias's wander (rad^2/s^3) the bias estimator measured; 0: not measured
        self.bias_wander = 0.0
        self._loop_linked = False  # a link to an experience that existed: least squares re-solves
        self._prune_due = False  # a loop link came since the last pruning
        #: merged experience id -> (the id it merged into, its pose dx, dy, dtheta in that one's frame)
        self.merged: dict[int, tuple[int, float, float, float]] = {}
        self.prune_time_s = 0.0
        #: seconds spent in solves and prunings since the map was made (the map's cost, summed)
        self.solve_s_total = 0.0

    @property
    def cfg(self) -> ExperienceMapConfig:
        """Read-only alias of :attr:`config`."""
        return self.config

    # ---------------------------------------------------------------- views
    @property
    def n_experiences(self) -> int:
        return self._n

    @property
    def n_links(self) -> int:
        return self._m

    @property
    def x(self) -> np.ndarray:
        return self._nodes[: self._n, 0]

    @property
    def y(self) -> np.ndarray:
        return self._nodes[: self._n, 1]

    @property
    def th(self) -> np.ndarray:
        return self._nodes[: self._n, 2]

    @property
    def stamp(self) -> np.ndarray:
        return self._nodes[: self._n, 3]

    @property
    def links(self) -> list[tuple[int, int, float, float, float, float]]:
        """(from id, to id, d, heading, facing, delta_time_s) per link, in insertion order."""
        return [(self.ids[a], self.ids[b], *map(float, v))
                for (a, b), v in zip(self._lf[: self._m].tolist(), self._lv[: self._m], strict=True)]

    @property
    def current(self) -> int:
        """The current experience's id (-1 before the first)."""
        return self.ids[self._cur] if self._cur >= 0 else -1

    # ---------------------------------------------------------------- odometry and actions
    def on_odo(self, vtrans: float, vrot: float, dt: float) -> None:
        """Dead reckoning: rotate first, then advance vtrans*dt along the absolute heading."""
        if not (math.isfinite(vtrans) and math.isfinite(vrot) and math.isfinite(dt)):
            raise InvalidInput(f"odometry must be finite, got vtrans={vtrans} vrot={vrot} dt={dt}")
        vtrans, vrot = vtrans * dt, vrot * dt
        self.accum_facing = clip_pi(self.accum_facing + vrot)
        self.accum_dx += vtrans * math.cos(self.accum_facing)
        self.accum_dy += vtrans * math.sin(self.accum_facing)
        self.accum_t += dt
        self.clock += dt

    def _idx(self, exp_id: int) -> int:
        i = self.index.get(int(exp_id), -1)
        if i < 0:
            raise ValueError(f"experience {exp_id} does not exist ({self._n} known)")
        return i

    def create_experience(self, exp_id: int, stamp: float = 0.0) -> None:
        """A node at the current experience plus the dead reckoning, linked from it, made current."""
        exp_id = int(exp_id)
        if exp_id in self.index:
            raise ValueError(f"experience {exp_id} exists already")
        cx, cy = (self._nodes[self._cur, 0], self._nodes[self._cur, 1]) if self._cur >= 0 else (0.0, 0.0)
        i = self._n
        self._nodes = _grow(self._nodes, i + 1)
        self._nodes[i] = (cx + self.accum_dx, cy + self.accum_dy, clip_pi(self.accum_facing), stamp)
        self._born = _grow(self._born, i + 1)
        self._born[i] = self.clock
        self._n += 1
        self.ids.append(exp_id)
        self.index[exp_id] = i
        self.part.append(self.part[self._cur] if self._cur >= 0 else max(self.part, default=-1) + 1)
        if self._cur >= 0:
            self._link(self._cur, i, 0.0, closes_loop=False)
        self._set(i, 0.0)

    def create_link(self, a: int, b: int, rel_rad: float) -> None:
        """Link experience a -> b with the dead reckoning since the current experience (OpenRatSLAM:
        no duplicate in either direction)."""
        self._link(self._idx(a), self._idx(b), rel_rad)

    def _link(self, a: int, b: int, rel_rad: float, closes_loop: bool = True) -> None:
        """``closes_loop`` False: b was just placed where this link says (no map change needed)."""
        if a == b or (a, b) in self.link_set or (b, a) in self.link_set:
            return
        th_a = float(self._nodes[a, 2])
        d = math.hypot(self.accum_dx, self.accum_dy)
        heading = signed_delta(th_a, math.atan2(self.accum_dy, self.accum_dx))
        facing = signed_delta(th_a, clip_pi(self.accum_facing + rel_rad))
        if self.part[a] != self.part[b]:
            self._join(a, b, d, heading, facing)
        j = self._m
        self._lf, self._lv = _grow(self._lf, j + 1), _grow(self._lv, j + 1)
        self._lf[j] = (a, b)
        self._lv[j] = (d, heading, facing, self.accum_t)
        self._m += 1
        self.link_set.add((a, b))
        self._loop_linked |= closes_loop
        self._prune_due |= closes_loop

    def _join(self, a: int, b: int, d: float, heading: float, facing: float) -> None:
        """Link a -> b (``d``, ``heading``, ``facing`` relative to a) joins two parts: the newer part
        (the one without the map's first experience; else a's) moves rigidly so that the link holds
        exactly, and the two become one."""
        nodes = self._nodes
        move_a = self.part[a] != self.part[0]
        fixed, moved = (b, a) if move_a else (a, b)
        xf, yf, thf = nodes[fixed, :3]
        if move_a:  # where a must be for b to lie where the link says
            th_new = thf - facing
            x_new, y_new = xf - d * math.cos(th_new + heading), yf - d * math.sin(th_new + heading)
        else:
            th_new = thf + facing
            x_new, y_new = xf + d * math.cos(thf + heading), yf + d * math.sin(thf + heading)
        xm, ym, thm = nodes[moved, :3]
        turn = th_new - thm
        c, s = math.cos(turn), math.sin(turn)
        old, new = self.part[moved], self.part[fixed]
        sel = np.flatnonzero(np.asarray(self.part) == old)
        dx, dy = nodes[sel, 0] - xm, nodes[sel, 1] - ym
        nodes[sel, 0], nodes[sel, 1] = x_new + c * dx - s * dy, y_new + s * dx + c * dy
        nodes[sel, 2] = [clip_pi(v) for v in nodes[sel, 2] + turn]
        if self._cur >= 0 and self.part[self._cur] == old:  # the dead reckoning since it turns too
            self.accum_dx, self.accum_dy = c * self.accum_dx - s * self.accum_dy, s * self.accum_dx + c * self.accum_dy
            self.accum_facing = clip_pi(self.accum_facing + turn)
        for i in sel.tolist():
            self.part[i] = new

    def new_session(self) -> None:
        """A new session on this map: no experience is current, and the dead reckoning starts from
        the robot's last pose (the best guess until a recognised place joins the new session's part
        to the map: module docstring)."""
        x, y, th = self.robot_pose()
        self._cur = -1
        self.accum_dx, self.accum_dy, self.accum_facing, self.accum_t = x, y, th, 0.0

    def _set(self, e: int, rel_rad: float) -> None:
        if e == self._cur:
            return
        if self._cur < 0 and e == 0 and self.config.openratslam_compat:
            # the C++ quirk that fix 2 removes: its current id starts at 0, so making the first node
            # current is a no-op and the accumulators are never reset (the second node lands twice as far)
            self._cur = 0
            return
        self._cur = e
        self.accum_dx = self.accum_dy = 0.0
        if not self.config.openratslam_compat:  # fix 1: the C++ never resets a link's delta_time_s
            self.accum_t = 0.0
        self.accum_facing = clip_pi(float(self._nodes[e, 2]) + rel_rad)

    def on_action(self, action: int, src: int, dst: int, rel_rad: float, stamp: float = 0.0) -> None:
        """Apply one pose-cell action (CREATE_NODE, CREATE_EDGE, SET_NODE) and relax the graph once.

        Actions that do not fit the map (after a lost message) are repaired rather than refused:
        CREATE_NODE of a known id links to it; CREATE_EDGE or SET_NODE to an unknown id creates it.
        """
        if not math.isfinite(rel_rad):
            raise InvalidInput(f"relative_rad must be finite, got {rel_rad}")
        dst, src = int(dst), int(src)
        if action not in (CREATE_NODE, CREATE_EDGE, SET_NODE):
            raise InvalidInput(f"unknown action {action}")
        if dst in self.merged:
            self.repaired_actions += int(action == CREATE_NODE)
            self._arrive_merged(dst, action != SET_NODE, rel_rad)
        elif dst not in self.index:
            self.repaired_actions += int(action != CREATE_NODE)
            self.create_experience(dst, stamp)
        elif action in (CREATE_NODE, CREATE_EDGE):
            self.repaired_actions += int(action == CREATE_NODE)
            d = self.index[dst]
            a = self._cur
            if self.config.openratslam_compat and src in self.index:
                a = self.index[src]  # the C++ links from src_id (fix 3: from the current one)
            if a >= 0:
                self._link(a, d, rel_rad)
            self._set(d, rel_rad)
        else:
            self._set(self.index[dst], rel_rad)
        self.iterate()

    def resolve(self, exp_id: int) -> tuple[int, tuple[float, float, float]]:
        """A merged experience's survivor (its index) and its pose in the survivor's frame,
        following merges of survivors (map_pruning.py); an experience that is on the map: itself
        and (0, 0, 0)."""
        off = (0.0, 0.0, 0.0)
        e = int(exp_id)
        while e in self.merged:
            into, *o = self.merged[e]
            off = compose(tuple(o), off)
            e = into
        return self._idx(e), off

    def _arrive_merged(self, exp_id: int, link: bool, rel_rad: float) -> None:
        """An action to a merged experience e_j = e_i (+) o_j: the link from the current experience
        goes to e_i with dead reckoning shifted by o_j^-1, and dead reckoning then starts at o_j in
        e_i's frame (where e_j lies), as arriving at e_j itself would."""
        i, o = self.resolve(exp_id)
        if link and self._cur >= 0 and self._cur != i:
            heading = self.accum_facing + rel_rad - o[2]  # e_i's heading, by dead reckoning
            c, s = math.cos(heading), math.sin(heading)
            self.accum_dx -= c * o[0] - s * o[1]
            self.accum_dy -= s * o[0] + c * o[1]
            self.accum_facing -= o[2]
            self._link(self._cur, i, rel_rad)
        th = float(self._nodes[i, 2])
        c, s = math.cos(th), math.sin(th)
        self._cur = i
        self.accum_dx, self.accum_dy = c * o[0] - s * o[1], s * o[0] + c * o[1]
        self.accum_t = 0.0
        self.accum_facing = clip_pi(th + o[2] + rel_rad)

    def prune(self) -> int:
        """Merge each settled experience closer than ``prune_m`` to an older surviving one into it
        (:func:`.map_pruning.prune`). Returns how many were merged."""
        t0 = time.perf_counter()
        merged = prune(self)
        self.prune_time_s = time.perf_counter() - t0
        return merged

    def iterate(self) -> None:
        """One relaxation: exp_loops sequential sweeps with exp_correction (numba), or with
        ``relaxation: least_squares`` (``bias_walk``) the exact solve (the pose graph) when a loop
        link came since the last one."""
        solve = self.config.relaxation != "sweeps"  # least_squares or bias_walk: after a loop link only
        if self._m == 0 or (not solve and self.config.exp_loops == 0):
            return
        if solve and not self._loop_linked:
            return
        t0 = time.perf_counter()
        nodes = self._nodes
        x, y, th = nodes[: self._n, 0].copy(), nodes[: self._n, 1].copy(), nodes[: self._n, 2].copy()
        lf, lv = self._lf[: self._m], self._lv[: self._m]
        if not solve:
            relax_sweeps(x, y, th, np.ascontiguousarray(lf[:, 0]), np.ascontiguousarray(lf[:, 1]),
                   np.ascontiguousarray(lv[:, 0]), np.ascontiguousarray(lv[:, 1]), np.ascontiguousarray(lv[:, 2]),
                   self.config.exp_loops, self.config.exp_correction, self.config.exp_robust_m)
        elif self.config.relaxation == "bias_walk" and self.bias_wander > 0:
            weights = bias_walk_weights(lv[:, 0], lv[:, 3], self.config.walk_position_rel,
                                        self.config.walk_heading_var, self.bias_wander)
            x, y, th, _ = relax_pose_graph(x, y, th, lf[:, 0], lf[:, 1], lv[:, 0], lv[:, 1], lv[:, 2], lv[:, 3],
                                           weights[0], weights[1], np.arange(self._m), weights[2])
        else:
            x, y, th = relax_least_squares(x, y, th, lf[:, 0], lf[:, 1], lv[:, 0], lv[:, 1], lv[:, 2])
        self._loop_linked = False  # solved (the sweeps never read it)
        nodes[: self._n, 0], nodes[: self._n, 1], nodes[: self._n, 2] = x, y, th
        self.relax_time_s = time.perf_counter() - t0
        self.solve_s_total += self.relax_time_s
        if self.config.prune_m > 0 and self._prune_due:
            self._prune_due = False
            self.prune()
            self.solve_s_total += self.prune_time_s

    # ---------------------------------------------------------------- poses and export
    def current_pose(self) -> tuple[float, float, float]:
        """The current experience's pose (what OpenRatSLAM publishes as RobotPose)."""
        if self._cur < 0:
            return (self.accum_dx, self.accum_dy, self.accum_facing)
        return tuple(float(v) for v in self._nodes[self._cur, :3])

    def robot_pose(self) -> tuple[float, float, float]:
        """Current experience plus the dead reckoning since it: a pose for every frame."""
        if self._cur < 0:
            return (self.accum_dx, self.accum_dy, self.accum_facing)
        x, y = self._nodes[self._cur, :2]
        return (float(x) + self.accum_dx, float(y) + self.accum_dy, self.accum_facing)

    def local_pose(self) -> tuple[int, float, float, float]:
        """(experience id, dx, dy, dtheta): :meth:`robot_pose` in the current experience's own frame
        (rotated by minus its heading), so that :func:`poses_on_map` can re-express it wherever
        relaxation later moves that experience. Before the first experience: (-1, robot pose)."""
        if self._cur < 0:
            return (-1, self.accum_dx, self.accum_dy, self.accum_facing)
        th = float(self._nodes[self._cur, 2])
        c, s = math.cos(th), math.sin(th)
        return (self.ids[self._cur], c * self.accum_dx + s * self.accum_dy, -s * self.accum_dx + c * self.accum_dy,
                clip_pi(self.accum_facing - th))

    def node_poses(self) -> dict[int, tuple[float, float, float]]:
        """Every experience's pose on the map now, id -> (x, y, theta): what :func:`poses_on_map`
        re-expresses the recorded :meth:`local_pose` rows on (the final map, once the run ends)."""
        return export_node_poses(self.export())

    @staticmethod
    def warm_up() -> None:
        """Compile (or load from numba's cache) the relaxation kernel before the first frame."""
        z = np.zeros(2)
        relax_sweeps(z.copy(), z.copy(), z.copy(), np.zeros(1, np.int64), np.ones(1, np.int64), z[:1].copy(),
               z[:1].copy(), z[:1].copy(), 1, 0.5, 0.0)

    def export(self) -> dict[str, Any]:
        """Nodes (id, x, y, theta, creation stamp) and links (from, to, d, heading, facing, dt);
        with pruning, ``merged``: each merged experience, the node it lies on and its pose in that
        node's frame (what re-expresses a frame recorded on it, :func:`poses_on_map`)."""
        out: dict[str, Any] = {
            "nodes": [{"id": self.ids[i], "x": float(x), "y": float(y), "theta": float(t), "stamp": float(s)}
                      for i, (x, y, t, s) in enumerate(self._nodes[: self._n].tolist())],
            "links": [{"from": a, "to": b, "d": d, "heading": h, "facing": f, "dt": t}
                      for a, b, d, h, f, t in self.links]}
        if self.merged:
            out["merged"] = []
            for e in sorted(self.merged):
                i, (dx, dy, dth) = self.resolve(e)
                out["merged"].append({"id": e, "into": self.ids[i], "dx": dx, "dy": dy, "dtheta": dth})
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"nodes": self._nodes[: self._n].copy(), "ids": np.array(self.ids, dtype=np.int64),
                "lf": self._lf[: self._m].copy(), "lv": self._lv[: self._m].copy(),
                "scalars": [self._cur, self.accum_dx, self.accum_dy, self.accum_t, self.accum_facing],
                "merged_ids": np.array([[e, v[0]] for e, v in self.merged.items()], dtype=np.int64).reshape(-1, 2),
                "merged_pose": np.array([v[1:] for v in self.merged.values()], dtype=np.float64).reshape(-1, 3),
                "prune_due": self._prune_due, "born": self._born[: self._n].copy(), "clock": self.clock}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self._nodes = np.array(st["nodes"], dtype=float).reshape(-1, 4)
        self._n = self._nodes.shape[0]
        self.ids = [int(v) for v in np.asarray(st["ids"]).reshape(-1)]
        self.index = {e: i for i, e in enumerate(self.ids)}
        self._lf = np.array(st["lf"], dtype=np.int64).reshape(-1, 2)
        self._lv = np.array(st["lv"], dtype=float).reshape(-1, 4)
        self._m = self._lf.shape[0]
        self.link_set = {(int(a), int(b)) for a, b in self._lf.tolist()}
        c, self.accum_dx, self.accum_dy, self.accum_t, self.accum_facing = (float(v) for v in st["scalars"])
        self._cur = int(c)
        # the parts follow from the links
        adjacency = sp.csr_matrix((np.ones(self._m), (self._lf[:, 0], self._lf[:, 1])), shape=(self._n, self._n))
        self.part = connected_components(adjacency, directed=False)[1].tolist() if self._n else []
        ids, pose = np.asarray(st["merged_ids"]), np.asarray(st["merged_pose"])
        self.merged = {int(e): (int(i), *map(float, o)) for (e, i), o in zip(ids.reshape(-1, 2).tolist(),
                                                                            pose.reshape(-1, 3).tolist(), strict=True)}
        self._prune_due = bool(st["prune_due"])
        self._born = np.array(st["born"], dtype=float).reshape(-1)
        self.clock = float(st["clock"])
