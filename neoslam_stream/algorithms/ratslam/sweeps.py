"""OpenRatSLAM's relaxation of the experience map: ``exp_loops`` Gauss-Seidel sweeps over the links.

Each sweep visits the experiences in index order and each one's outgoing links in insertion order,
and moves both ends of a link towards agreement with what the link says (a fraction ``corr`` of the
disagreement, ``exp_correction``), positions and facings alike, as the C++ does; the experience map
(``experience_map.py``) calls :func:`relax_sweeps` with ``relaxation: sweeps``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _clip(a):  # pragma: no cover - compiled
    while a > math.pi:
        a -= 2 * math.pi
    while a <= -math.pi:
        a += 2 * math.pi
    return a


@njit(cache=True)
def relax_sweeps(x, y, th, lfrom, lto, ld, lhead, lface, loops, corr, robust=0.0):  # pragma: no cover - compiled
    """exp_loops Gauss-Seidel sweeps: experiences in index order, each one's outgoing links in
    insertion order (a counting sort of the link list by source keeps that order). ``robust`` > 0:
    each link's correction is scaled by the Cauchy weight robust^2 / (robust^2 + r^2) of its
    current position error r (ExperienceMapConfig.exp_robust_m). A sweep that changes nothing
    ends the relaxation: the next would start from the same state and change nothing either (a map
    without a loop closure is such a fixed point, whose sweeps were all wasted)."""
    n = x.shape[0]
    m = lfrom.shape[0]
    ptr = np.zeros(n + 1, np.int64)
    for li in range(m):
        ptr[lfrom[li] + 1] += 1
    for i in range(n):
        ptr[i + 1] += ptr[i]
    fill = ptr[:n].copy()
    order = np.empty(m, np.int64)
    for li in range(m):
        order[fill[lfrom[li]]] = li
        fill[lfrom[li]] += 1
    for _ in range(loops):
        changed = False
        for e0 in range(n):
            for p in range(ptr[e0], ptr[e0 + 1]):
                li = order[p]
                e1 = lto[li]
                lx = x[e0] + ld[li] * math.cos(th[e0] + lhead[li])
                ly = y[e0] + ld[li] * math.sin(th[e0] + lhead[li])
                c = corr
                if robust > 0.0:
                    r2 = (x[e1] - lx) ** 2 + (y[e1] - ly) ** 2
                    c = corr * robust * robust / (robust * robust + r2)
                dx = (x[e1] - lx) * c
                dy = (y[e1] - ly) * c
                before = (x[e0], y[e0], x[e1], y[e1], th[e0], th[e1])
                x[e0] += dx
                y[e0] += dy
                x[e1] -= dx
                y[e1] -= dy
                df = _clip(th[e1] - (th[e0] + lface[li]))
                th[e0] = _clip(th[e0] + df * c)
                th[e1] = _clip(th[e1] - df * c)
                if not changed and before != (x[e0], y[e0], x[e1], y[e1], th[e0], th[e1]):
                    changed = True
        if not changed:
            break
