"""The experience map as a pose graph with a wandering yaw-rate bias (``relaxation: bias_walk``).

The least-squares solve (graph_solve.py) takes the headings first and the positions after them, and
shares a loop's heading misclosure equally by its links, as a constant bias would have made it. A
yaw-rate bias that wanders (a random walk: a gyro's, a warming gearbox's) turns the headings by
more where it was larger, so one closure after a long stretch of dead reckoning should bend that
stretch as the bias bent it. Here every link k has its own unknown rate r_k, and Gauss-Newton on
SE(2), started from the least-squares solution, minimises

    sum_k w_pos |R(-th_from) (p_to - p_from) - d (cos, sin)(heading)|^2
        + w_head (wrap(th_to - th_from - facing) + r_k dt_k)^2
        + w_step (r_{k+1} - r_k)^2 + w_rate r_k^2

each step halved until the weighted sum of squares falls. :func:`bias_walk_weights` gives the
weights as inverse variances: a link's position error grows with its length, its heading error
with its duration, and the bias's step with the time between links times the wander the run's
own bias estimator measured (odometry_bias.py). Each connected part keeps its centroid and mean
heading, as the least-squares solve does. Why and how it was chosen: docs/mapping.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from .angles import wrap_pi
from .graph_solve import grounded_parts, relax_least_squares

#: weight of each rate's own prior, per (rad/s)^2: only keeps a rate no link constrains at 0
RATE_PRIOR = 1e-6
#: Gauss-Newton steps at most (each re-factorises the normal equations)
MAX_STEPS = 30
#: a link's length and duration are read as at least this fraction of the map's median, so that a
#: turn on the spot (d = 0) or two experiences in one odometry step do not get an infinite weight,
#: and never as less than 1 mm and 1 ms (a map of turns on the spot only: a median of 0)
FLOOR_OF_MEDIAN = 0.1
MIN_LENGTH_M, MIN_DURATION_S = 1e-3, 1e-3


def bias_walk_weights(ld: np.ndarray, ldt: np.ndarray, position_rel: float, heading_var: float,
                      wander: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse variances per link (position, heading) and per step between consecutive links:
    position sd ``position_rel`` x d, heading variance ``heading_var`` (rad^2/s) x dt, the bias's
    step ``wander`` (rad^2/s^3) x the steps' mean dt."""
    d = np.maximum(ld, max(FLOOR_OF_MEDIAN * float(np.median(ld)), MIN_LENGTH_M))
    t = np.maximum(ldt, max(FLOOR_OF_MEDIAN * float(np.median(ldt)), MIN_DURATION_S))
    return 1.0 / (position_rel * d) ** 2, 1.0 / (heading_var * t), 1.0 / (wander * 0.5 * (t[1:] + t[:-1]))


def relax_pose_graph(x: np.ndarray, y: np.ndarray, th: np.ndarray, lfrom: np.ndarray, lto: np.ndarray,
                     ld: np.ndarray, lhead: np.ndarray, lface: np.ndarray, ldt: np.ndarray, w_pos: np.ndarray,
                     w_head: np.ndarray, rate_of: np.ndarray | None = None, w_step: np.ndarray | None = None,
                     w_rate: float = RATE_PRIOR) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """New (x, y, th) of n experiences from m links (from, to, d, heading, facing, dt) and the
    solve's figures (steps, cost before and after, largest rate). ``rate_of``: each link's rate
    (None: no rates, a plain pose graph); ``w_step``: the weight of each step between consecutive
    rates (None: rates independent). The inputs are not modified."""
    x, y, th = relax_least_squares(x, y, th, lfrom, lto, ld, lhead, lface)
    n, m = x.shape[0], lfrom.shape[0]
    if m == 0:
        return x, y, th, {"steps": 0, "cost_before": 0.0, "cost": 0.0, "max_rate": 0.0}
    rate_of = np.zeros(0, np.int64) if rate_of is None else np.asarray(rate_of, np.int64)
    n_rates = int(rate_of.max()) + 1 if rate_of.size else 0
    w_step = np.zeros(0) if w_step is None else np.asarray(w_step, float)
    n_steps = w_step.shape[0]
    inc = sp.csr_matrix((np.ones(2 * m), (np.r_[np.arange(m), np.arange(m)], np.r_[lfrom, lto])), shape=(m, n))
    n_parts, part, grounded = grounded_parts((inc.T @ inc).tocsr())
    free = np.r_[np.repeat(~grounded, 3), np.ones(n_rates, dtype=bool)]
    w = np.r_[np.ravel(np.c_[w_pos, w_pos, w_head]), w_step, np.full(n_rates, w_rate)]
    meas_x, meas_y = ld * np.cos(lhead), ld * np.sin(lhead)

    def residual(x, y, th, r):
        dx, dy = x[lto] - x[lfrom], y[lto] - y[lfrom]
        c, s = np.cos(th[lfrom]), np.sin(th[lfrom])
        qx, qy = c * dx + s * dy, -s * dx + c * dy
        turn = wrap_pi(th[lto] - th[lfrom] - lface) + (r[rate_of] * ldt if n_rates else 0.0)
        e = np.r_[np.ravel(np.c_[qx - meas_x, qy - meas_y, turn]), np.diff(r)[:n_steps], r]
        return e, (c, s, qx, qy)

    rows, a3, b3 = 3 * np.arange(m), 3 * lfrom, 3 * lto
    ks = np.arange(n_steps)

    def jacobian(c, s, qx, qy):
        R = [rows, rows, rows, rows, rows, rows + 1, rows + 1, rows + 1, rows + 1, rows + 1, rows + 2, rows + 2]
        C = [a3, a3 + 1, b3, b3 + 1, a3 + 2, a3, a3 + 1, b3, b3 + 1, a3 + 2, a3 + 2, b3 + 2]
        V = [-c, -s, c, s, qy, s, -c, -s, c, -qx, -np.ones(m), np.ones(m)]
        if n_rates:
            R += [rows + 2, 3 * m + n_steps + np.arange(n_rates)]
            C += [3 * n + rate_of, 3 * n + np.arange(n_rates)]
            V += [ldt, np.ones(n_rates)]
        if n_steps:
            R += [3 * m + ks, 3 * m + ks]
            C += [3 * n + ks + 1, 3 * n + ks]
            V += [np.ones(n_steps), -np.ones(n_steps)]
        shape = (3 * m + n_steps + n_rates, 3 * n + n_rates)
        return sp.csr_matrix((np.concatenate(V), (np.concatenate(R), np.concatenate(C))), shape=shape)

    th0 = th.copy()
    cx0 = [x[part == k].mean() for k in range(n_parts)]
    cy0 = [y[part == k].mean() for k in range(n_parts)]
    r = np.zeros(n_rates)
    e, lin = residual(x, y, th, r)
    cost0 = cost = float(e @ (w * e))
    steps = 0
    while steps < MAX_STEPS and cost > 0:
        steps += 1
        J = jacobian(*lin)[:, free]
        d = np.zeros(3 * n + n_rates)
        d[free] = -splu((J.T @ sp.diags(w) @ J).tocsc()).solve(J.T @ (w * e))
        for _ in range(30):  # halve the step until the sum of squares falls
            trial = (x + d[0:3 * n:3], y + d[1:3 * n:3], th + d[2:3 * n:3], r + d[3 * n:])
            e_new, lin_new = residual(*trial)
            cost_new = float(e_new @ (w * e_new))
            if cost_new <= cost:
                break
            d *= 0.5
        if cost_new > cost:
            break
        (x, y, th, r), e, lin = trial, e_new, lin_new
        done = (cost - cost_new) < 1e-9 * cost
        cost = cost_new
        if done:
            break
    for k in range(n_parts):  # the part's mean heading and centroid stay: one rigid motion
        sel = part == k
        turn = wrap_pi(th0[sel] - th[sel])
        t = np.arctan2(np.sin(turn).sum(), np.cos(turn).sum())
        ct, st = np.cos(t), np.sin(t)
        xs, ys = x[sel] - x[sel].mean(), y[sel] - y[sel].mean()
        x[sel], y[sel], th[sel] = ct * xs - st * ys + cx0[k], st * xs + ct * ys + cy0[k], th[sel] + t
    return x, y, wrap_pi(th), {"steps": steps, "cost_before": cost0, "cost": cost,
                               "max_rate": float(np.abs(r).max()) if n_rates else 0.0}
