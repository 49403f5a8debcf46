"""Recorded poses on a (relaxed) experience map: a frame recorded as its experience and its offset in
that experience's frame (:meth:`ExperienceMap.local_pose`) is re-expressed wherever the map has
since moved the experience, or the one it merged into (map_pruning.py). The run folder's
``trajectory_map.tum`` and the benches' final-map APE read frames so."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .angles import clip_pi
from .map_pruning import compose


def poses_on_map(nodes: dict[int, tuple[float, float, float]], exp_ids: np.ndarray,
                 local: np.ndarray) -> np.ndarray:
    """Poses (k, 3) re-expressed on a (relaxed) map: each pose's offset ``local`` (dx, dy, dtheta) in
    the frame of its experience (:meth:`ExperienceMap.local_pose`) applied to that experience's
    pose in ``nodes`` (id -> x, y, theta): x_e + R(theta_e) (dx, dy), theta_e + dtheta. Rows whose
    experience is -1 or not in ``nodes`` keep ``local`` as it is (a pose before the first
    experience is already absolute)."""
    local = np.asarray(local, dtype=np.float64).reshape(-1, 3)
    out = local.copy()
    for i, e in enumerate(np.asarray(exp_ids).reshape(-1).tolist()):
        node = nodes.get(int(e))
        if node is None:
            continue
        x, y, th = node
        c, s = math.cos(th), math.sin(th)
        dx, dy, dth = local[i]
        out[i] = (x + c * dx - s * dy, y + s * dx + c * dy, clip_pi(th + dth))
    return out


def export_node_poses(export: dict[str, Any]) -> dict[int, tuple[float, float, float]]:
    """Every experience's pose on an exported map (:meth:`ExperienceMap.export`, map.json), id ->
    (x, y, theta): the nodes, and each merged experience at its pose in the frame of the node it
    merged into: what :func:`poses_on_map` re-expresses recorded poses on."""
    nodes = {int(n["id"]): (float(n["x"]), float(n["y"]), float(n["theta"])) for n in export.get("nodes", [])}
    for e in export.get("merged", []):
        into = nodes.get(int(e["into"]))
        if into is not None:
            nodes[int(e["id"])] = compose(into, (float(e["dx"]), float(e["dy"]), float(e["dtheta"])))
    return nodes
