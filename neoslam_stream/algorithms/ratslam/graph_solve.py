"""The experience map's least-squares relaxation: the headings, then the positions, that agree best
with every link (``ExperienceMapConfig.relaxation: least_squares``).

OpenRatSLAM relaxes by Gauss-Seidel sweeps that each pull both ends of a link half-way to what it
says. Around a loop whose links disagree (every loop closure with drifted odometry), each pull
undoes part of the last, so the sweeps never settle, and a correction crosses a chain of N
experiences in ~N^2 sweeps: the map keeps improving with the sweep count while its cost grows with
sweeps x links on every action. Solved directly instead, as two linear least-squares problems on
the graph's Laplacian (one sparse factorisation, three right-hand sides):

* headings: theta_to - theta_from = facing (+ the whole turns that make the current residual
  smallest, so a link is read as the current map reads it);
* positions, with those headings: p_to - p_from = d (cos, sin)(theta_from + heading).

Relative values only are determined; as the sweeps do (each pull moves both ends by opposite
amounts), each connected part keeps the centroid of its positions, and its mean heading.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from .angles import wrap_pi


def grounded_parts(lap: sp.spmatrix) -> tuple[int, np.ndarray, np.ndarray]:
    """The graph's connected parts (``lap``: its Laplacian or any matrix with its links' pattern):
    their number, each experience's part, and one experience per part that holds still in a solve
    (its value is fixed afterwards by the part's centroid)."""
    n_parts, part = connected_components(lap, directed=False)
    grounded = np.zeros(lap.shape[0], dtype=bool)
    grounded[np.unique(part, return_index=True)[1]] = True
    return n_parts, part, grounded


def relax_least_squares(x: np.ndarray, y: np.ndarray, th: np.ndarray, lfrom: np.ndarray, lto: np.ndarray,
                        ld: np.ndarray, lhead: np.ndarray, lface: np.ndarray) -> tuple[np.ndarray, ...]:
    """New (x, y, th) of n experiences from m links (from, to, d, heading, facing), as the module
    docstring says. The inputs are not modified."""
    n, m = x.shape[0], lfrom.shape[0]
    if m == 0:
        return x.copy(), y.copy(), th.copy()
    rows = np.concatenate([np.arange(m), np.arange(m)])
    inc = sp.csr_matrix((np.concatenate([-np.ones(m), np.ones(m)]), (rows, np.concatenate([lfrom, lto]))),
                        shape=(m, n))
    lap = (inc.T @ inc).tocsr()
    n_parts, part, grounded = grounded_parts(lap)
    free = ~grounded
    lu = splu(lap[free][:, free].tocsc()) if free.any() else None

    def solve(link_values: np.ndarray) -> np.ndarray:
        out = np.zeros(n)
        if lu is not None:
            out[free] = lu.solve((inc.T @ link_values)[free])
        return out

    residual = th[lto] - th[lfrom] - lface
    th_new = solve(lface + (residual - wrap_pi(residual)))
    # each part's mean heading stays (circular mean of the change)
    turn = wrap_pi(th - th_new)
    for k in range(n_parts):
        sel = part == k
        th_new[sel] += np.arctan2(np.sin(turn[sel]).sum(), np.cos(turn[sel]).sum())
    ang = th_new[lfrom] + lhead
    x_new, y_new = solve(ld * np.cos(ang)), solve(ld * np.sin(ang))
    for k in range(n_parts):
        sel = part == k
        x_new[sel] += x[sel].mean() - x_new[sel].mean()
        y_new[sel] += y[sel].mean() - y_new[sel].mean()
    return x_new, y_new, wrap_pi(th_new)
