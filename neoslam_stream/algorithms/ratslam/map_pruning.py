"""The experience map at a bounded density (``ExperienceMapConfig.prune_m``): experiences that lie
closer than a spacing to an older one are merged into it, their links rewired to it.

Why (docs/long_runs.md). RatSLAM makes an experience whenever the pose cells' packet or the view
is not one an experience already holds, so a route driven all day keeps adding experiences at
places the map knows, and the map's solve, its memory and its saved size grow with the laps.
Milford and Wyeth kept RatSLAM's experience map for two weeks in an office by holding it at a
bounded density: an experience that lies close to another is removed and its transitions are
joined to the one kept ("Persistent navigation and mapping using a biologically inspired SLAM
system", IJRR 2010; implemented from that description). Here:

* **which**: after a solve, an experience e_j closer than ``prune_m`` (in the map's x, y) to a
  surviving experience e_i of an earlier visit (made at least ``prune_gap_s`` of driving before
  it) is merged into the nearest such e_i; the experiences are visited oldest first, so the first
  visit's experience of a place is the one kept and the survivors of different visits lie at least
  ``prune_m`` apart (one visit's experiences stay as the pose cells spaced them). Only *settled*
  experiences are merged: made at least ``prune_age_s`` of driving ago (the loop through them has
  closed since, and the solve has placed them by the closures on both sides; merged earlier, an
  offset still off by the drift would be frozen in), and on a cycle of links or at most ``prune_m``
  of links from one (an experience made during a turn on the spot hangs off the one it came back
  to; a longer stretch of dead reckoning since the last closure, the graph's bridges, may still be
  off by its drift). The current experience stays.
* **exactly**: the merged experience keeps its pose relative to the survivor, o_j = T_i^-1 T_j
  (dx, dy, dtheta in e_i's frame), so nothing moves at the merge. Each link l of e_j measuring
  Z = T_a^-1 T_b (d, heading, facing in a's frame) is rewired: as its source, o_j (+) Z; as its
  destination, Z (+) o_j^-1. A link that now joins e_i to itself (e_i's own link to e_j) is
  dropped: the merge makes that relation rigid; one that repeats a link between the same two
  experiences is dropped too (the older measurement stays), so links, like experiences, grow with
  the places and not with the laps. What is lost: the merged pair can no longer bend apart in
  later solves (by at most what a solve moves two experiences ``prune_m`` apart relative to each
  other).
* **later**: the pose cells still know e_j (they do not read the map), so an action naming it
  arrives at e_i (+) o_j: the link is rewired as above and dead reckoning starts from o_j
  (``ExperienceMap.resolve``). The map keeps o_j per merged experience: bounded by the experiences
  ever made, which with D's merged revisits grow with the places (revisit_merge.py).

The constants follow from the platform (derived_back_end): the spacing is ``exp_delta_pc_threshold``
cells of ``pc_cell_x_size`` metres, the distance at which the pose cells themselves tell two
experiences of one view apart; an earlier visit is one at least the earliest revisit ago (one
shortest loop at twice the typical speed, as D's candidates), and an experience has settled after
one shortest loop at the typical speed.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .angles import clip_pi


def relative(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """T_a^-1 T_b: pose b in a's frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, clip_pi(b[2] - a[2]))


def compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """T_a T_b: pose b, given in a's frame, in a's parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], clip_pi(a[2] + b[2]))


def inverse(a: tuple[float, float, float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], clip_pi(-a[2]))


def link_pose(d: float, heading: float, facing: float) -> tuple[float, float, float]:
    """A link's (d, heading, facing) as the pose of its destination in its source's frame."""
    return (d * math.cos(heading), d * math.sin(heading), facing)


def link_values(z: tuple[float, float, float]) -> tuple[float, float, float]:
    """The pose of a link's destination in its source's frame as (d, heading, facing)."""
    return (math.hypot(z[0], z[1]), math.atan2(z[1], z[0]), clip_pi(z[2]))


def on_cycles(n: int, lfrom: np.ndarray, lto: np.ndarray) -> np.ndarray:
    """Per experience, whether a cycle of links passes through it (it touches a link that is no
    bridge of the undirected graph): Tarjan's bridge search, iterative, O(n + m)."""
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for k, (a, b) in enumerate(zip(lfrom.tolist(), lto.tolist(), strict=True)):
        if a != b:
            adj[a].append((b, k))
            adj[b].append((a, k))
    disc = [-1] * n
    low = [0] * n
    bridge = np.zeros(lfrom.shape[0], dtype=bool)
    clock = 0
    for root in range(n):
        if disc[root] >= 0:
            continue
        disc[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, 0)]  # node, the link it was reached by, next neighbour to visit
        while stack:
            v, via, i = stack[-1]
            if i < len(adj[v]):
                stack[-1] = (v, via, i + 1)
                w, k = adj[v][i]
                if k == via:
                    continue
                if disc[w] < 0:
                    disc[w] = low[w] = clock
                    clock += 1
                    stack.append((w, k, 0))
                else:
                    low[v] = min(low[v], disc[w])
                continue
            stack.pop()
            if stack:
                u = stack[-1][0]
                low[u] = min(low[u], low[v])
                if low[v] > disc[u]:
                    bridge[via] = True
    out = np.zeros(n, dtype=bool)
    keep = ~bridge & (lfrom != lto)
    out[lfrom[keep]] = True
    out[lto[keep]] = True
    return out


def settled(n: int, lfrom: np.ndarray, lto: np.ndarray, ld: np.ndarray, within: float) -> np.ndarray:
    """Per experience, whether the solve has fixed its place: it lies on a cycle of links
    (:func:`on_cycles`), or at most ``within`` metres of links from one (a turn on the spot that
    came back to the experience it left hangs off it by one short link; a stretch of dead
    reckoning since the last closure is settled only for its first ``within`` metres)."""
    import heapq

    dist = np.where(on_cycles(n, lfrom, lto), 0.0, np.inf)
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for a, b, d in zip(lfrom.tolist(), lto.tolist(), ld.tolist(), strict=True):
        adj[a].append((b, d))
        adj[b].append((a, d))
    heap = [(0.0, int(v)) for v in np.flatnonzero(dist == 0.0)]
    while heap:
        d, v = heapq.heappop(heap)
        if d > dist[v]:
            continue
        for w, length in adj[v]:
            if d + length < dist[w] and d + length <= within:
                dist[w] = d + length
                heapq.heappush(heap, (d + length, w))
    return dist <= within


def merges(x: np.ndarray, y: np.ndarray, born: np.ndarray, settled: np.ndarray, current: int, spacing: float,
           gap_s: float = 0.0, before: float = math.inf) -> list[tuple[int, int]]:
    """(j, i): settled experience j made no later than ``before`` into the nearest surviving
    experience i within ``spacing`` made at least ``gap_s`` before it (``born``: each one's making,
    in seconds of driving), visiting the experiences oldest first (index order) so that the
    survivors lie at least ``spacing`` apart, except those made within ``gap_s`` of each other (one
    visit's, which the pose cells spaced); ``current`` is never merged. A grid of ``spacing`` cells
    finds the neighbours."""
    out: list[tuple[int, int]] = []
    grid: dict[tuple[int, int], list[int]] = {}
    r2 = spacing * spacing
    for j in np.flatnonzero(settled).tolist():
        cx, cy = int(math.floor(x[j] / spacing)), int(math.floor(y[j] / spacing))
        best, best_d2 = -1, r2
        if j != current and born[j] <= before:
            for gx in (cx - 1, cx, cx + 1):
                for gy in (cy - 1, cy, cy + 1):
                    for i in grid.get((gx, gy), ()):
                        d2 = (x[j] - x[i]) ** 2 + (y[j] - y[i]) ** 2
                        if d2 < best_d2 and born[j] - born[i] >= gap_s:
                            best, best_d2 = i, d2
        if best >= 0:
            out.append((j, best))
        else:
            grid.setdefault((cx, cy), []).append(j)
    return out


def prune(em: Any) -> int:
    """Merge each settled experience of the experience map ``em`` closer than its ``prune_m`` to
    an older surviving one into it (the module docstring): the merged experience's pose relative
    to the survivor goes to ``em.merged``, its links are rewired (those that join the survivor to
    itself, or repeat a link, dropped), the map's arrays compacted. Returns how many were merged."""
    n, m = em._n, em._m
    lf, lv = em._lf[:m], em._lv[:m]
    spacing = em.config.prune_m
    pairs = merges(em.x, em.y, em._born[:n], settled(n, lf[:, 0], lf[:, 1], lv[:, 0], spacing), em._cur, spacing,
                   em.config.prune_gap_s, em.clock - em.config.prune_age_s)
    if not pairs:
        return 0
    into = np.arange(n)
    off: dict[int, tuple[float, float, float]] = {}
    pose = em._nodes[:n, :3].tolist()
    for j, i in pairs:
        off[j] = relative(tuple(pose[i]), tuple(pose[j]))
        into[j] = i
        em.merged[em.ids[j]] = (em.ids[i], *off[j])
    ident = (0.0, 0.0, 0.0)
    links, seen = [], set()
    for (a, b), (d, h, f, dt) in zip(lf.tolist(), lv.tolist(), strict=True):
        a2, b2 = int(into[a]), int(into[b])
        if a2 == b2 or (a2, b2) in seen or (b2, a2) in seen:
            continue
        seen.add((a2, b2))
        if a2 != a or b2 != b:  # T_i^-1 T_b = o_a (+) Z, T_a^-1 T_i = Z (+) o_b^-1
            d, h, f = link_values(compose(compose(off.get(a, ident), link_pose(d, h, f)), inverse(off.get(b, ident))))
        links.append((a2, b2, d, h, f, dt))
    keep = np.flatnonzero(into == np.arange(n))
    new = np.full(n, -1, dtype=np.int64)
    new[keep] = np.arange(keep.shape[0])
    em._nodes = np.ascontiguousarray(em._nodes[keep])
    em._born = np.ascontiguousarray(em._born[keep])
    em._n = keep.shape[0]
    em.ids = [em.ids[k] for k in keep.tolist()]
    em.index = {e: k for k, e in enumerate(em.ids)}
    em._m = len(links)
    arr = np.array(links, dtype=np.float64).reshape(-1, 6)
    em._lf = new[arr[:, :2].astype(np.int64)].reshape(-1, 2)
    em._lv = np.ascontiguousarray(arr[:, 2:])
    em.link_set = {(int(a), int(b)) for a, b in em._lf.tolist()}
    em._cur = int(new[em._cur]) if em._cur >= 0 else -1
    return len(pairs)
