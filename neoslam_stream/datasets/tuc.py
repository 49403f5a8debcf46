"""The TU Chemnitz corridor run through pose cells + experience map (used by bench/ratslam.py and tests).

Wheel odometry (10 Hz: forward speed vx and turn rate wz, as RatSLAM uses them) drives the pose
cells and the experience map. Visual templates come from the run's loop-closure candidates: every
time stamp that appears in a candidate is a camera frame; a frame whose best candidate with an
earlier frame (at least ``min_gap_s`` earlier, similarity >= ``threshold``) exists reuses that
frame's template id (a place recognised), otherwise it gets a new id. The error of the
experience-map trajectory and of odometry alone is measured against the 2-D ground truth after
the same rigid 2-D alignment (rotation + translation, least squares) of each.
"""

from __future__ import annotations

import math

import numpy as np

from ..evaluation import best_rotation_2d
from . import data_root

DATA = data_root() / "tuc_slam_odom_loops"

#: the corridor's settings before issue #14's levers (OpenRatSLAM's back end on the candidates):
#: the "paper" column of the TUC figures
TUC_PAPER_SETTINGS = dict(pc=dict(pc_dim_xy=30, pc_cell_x_size=1.0, exp_delta_pc_threshold=2.0),
                          em=dict(exp_loops=20, exp_initial_em_deg=0), threshold=0.6, min_gap_s=30.0)

#: the settings of the TUC figures (bench/ratslam.py, tests/test_ratslam_tuc.py): the paper
#: settings plus the yaw-rate bias estimated from every recognition, modulo half a turn (this
#: front end recognises the corridor in both directions), and the odometry gate that the
#: bias-corrected odometry makes reliable (20 m + 0.1 m per metre driven: the look-alikes lie
#: ~86 m away); each is needed (docs/mapping.md, "TUC corridor")
TUC_SETTINGS = dict(
    TUC_PAPER_SETTINGS,
    pc=dict(TUC_PAPER_SETTINGS["pc"],
            odometry_bias=dict(enabled=True, samples_from="templates", bidirectional=True),
            odometry_gate=dict(radius_m=20.0, drift=0.1)))


def load_ground_truth(path=None) -> np.ndarray:
    """(n, 3) rows (t, x, y) of the ``point2`` records only.

    The GT file interleaves ``point2 t x y ...`` (positions, metres) with ``angle t heading 0``
    records; reading every row as a position mixed (t, heading, 0) into the trajectory, so the
    figures were not trajectory errors (issue #14). Rows are sorted by time.
    """
    rows = []
    for line in open(path or DATA / "Corridor_GT.txt"):
        p = line.split()
        if p and p[0] == "point2":
            rows.append((float(p[1]), float(p[2]), float(p[3])))
    gt = np.array(rows, dtype=np.float64)
    return gt[np.argsort(gt[:, 0], kind="stable")]


def load(limit_s: float | None = None):
    odom, loops = [], []
    for line in open(DATA / "Corridor_Input.txt"):
        p = line.split()
        if not p:
            continue
        if p[0] == "odom2":
            odom.append((float(p[1]), float(p[2]), float(p[4])))
        elif p[0] == "loop":
            loops.append((float(p[1]), float(p[2]), float(p[3])))
    gt = load_ground_truth()
    odom = np.array(odom)
    loops = np.array(loops)
    if limit_s is not None:
        odom = odom[odom[:, 0] <= limit_s]
        loops = loops[loops[:, 0] <= limit_s]
        gt = gt[gt[:, 0] <= limit_s]
    return odom, loops, gt


def templates_from_loops(loops: np.ndarray, threshold: float, min_gap_s: float,
                         sequence: dict | None = None) -> dict[float, int]:
    """time -> template id, in time order. ``sequence``: the parameters of a
    :class:`~neoslam_stream.algorithms.sequence.SequenceFilter` over frame indices (a recognised
    frame must continue a run of consistent recognitions), as stage D's ``sequence`` setting."""
    from ..algorithms.sequence import SequenceFilter

    seq = SequenceFilter(**(sequence or {}))
    frames = np.unique(np.concatenate([loops[:, 0], loops[:, 1]]))
    best: dict[float, tuple[float, float]] = {}
    for t1, t2, s in loops:
        later, earlier = max(t1, t2), min(t1, t2)
        if later - earlier >= min_gap_s and s >= threshold and s > best.get(later, (0, -1))[1]:
            best[later] = (earlier, s)
    ids: dict[float, int] = {}
    pos = {t: i for i, t in enumerate(frames)}
    n = 0
    for i, t in enumerate(frames):
        ref = pos[best[t][0]] if t in best and best[t][0] in ids else -1
        if seq.check(i, ref):
            ids[t] = ids[best[t][0]]
        else:
            ids[t] = n
            n += 1
    return ids


def first_point_error(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The NeoSLAM authors' metric (show_em_irat.m): subtract each trajectory's first point, no rotation."""
    return np.linalg.norm((est - est[0]) - (ref - ref[0]), axis=1)


def first_point_rotated_error(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """As :func:`first_point_error`, with the rotation about the first point fitted (least
    squares): the authors' metric compares headings in two unrelated frames (the robot's start
    heading is not the ground truth's x axis), so without the rotation it mostly measures that
    angle."""
    e, r = est - est[0], ref - ref[0]
    return np.linalg.norm(e @ best_rotation_2d(e, r).T - r, axis=1)


def align_rigid_2d(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Least-squares rotation + translation of est (n,2) onto ref (n,2) (Umeyama without scale)."""
    mu_e, mu_r = est.mean(0), ref.mean(0)
    return (est - mu_e) @ best_rotation_2d(est - mu_e, ref - mu_r).T + mu_r


def run(pc_params: dict, em_params: dict, threshold: float = 0.8, min_gap_s: float = 60.0,
        limit_s: float | None = None, sequence: dict | None = None) -> dict:
    """The corridor run through pose cells + experience map. ``pc_params`` may hold an
    ``odometry_gate`` (OdometryGate's parameters: recognitions odometry cannot explain do not
    reach the pose cells, as in the pose-cell node) and an ``odometry_bias`` (the yaw-rate bias
    estimated from loop closures and subtracted, as in the pose-cell node); ``sequence``: see
    templates_from_loops. ``map_on_final_mean_m``: the error of every step re-expressed on the
    final map (as trajectory_map.tum)."""
    from ..algorithms.ratslam.experience_map import ExperienceMap, poses_on_map
    from ..algorithms.ratslam.odometry_bias import YawBiasEstimator
    from ..algorithms.ratslam.odometry_gate import OdometryGate
    from ..algorithms.ratslam.pose_cells import PoseCellNetwork

    odom, loops, gt = load(limit_s)
    ids = templates_from_loops(loops, threshold, min_gap_s, sequence)
    frame_times = np.array(sorted(ids))
    pc = PoseCellNetwork(**pc_params)
    em = ExperienceMap(**em_params)
    gate = OdometryGate(pc.cfg.odometry_gate)
    bias = YawBiasEstimator(pc.cfg.odometry_bias)
    fi = 0
    est, dr, local = [], [], []
    x = y = 0.0
    th = math.radians(em.cfg.exp_initial_em_deg)
    prev_t = odom[0, 0]
    recognised = 0
    for t, vx, wz in odom:
        dt = t - prev_t
        prev_t = t
        while fi < len(frame_times) and frame_times[fi] <= t:
            vt = ids[frame_times[fi]]
            bias.on_template(vt)
            if gate.check(vt):
                recognised += int(vt in pc.templates)
                pc.on_view_template(vt, 0.0)
            fi += 1
        wc = bias.correct(wz, dt)
        pc.on_odo(vx, wc, dt)
        gate.on_odo(vx, wc, dt)
        em.on_odo(vx, wc, dt)
        a, s, d, rr = pc.get_action()
        bias.on_action(a, d, rr)
        if a:
            em.on_action(a, s, d, rr, t)
        px, py, _ = em.robot_pose()
        est.append((t, px, py))
        local.append(em.local_pose())
        th += wz * dt
        x += vx * dt * math.cos(th)
        y += vx * dt * math.sin(th)
        dr.append((t, x, y))
    est, dr = np.array(est), np.array(dr)
    idx = np.clip(np.searchsorted(gt[:, 0], est[:, 0]), 0, len(gt) - 1)
    ref = gt[idx, 1:3]
    err_map = np.linalg.norm(align_rigid_2d(est[:, 1:], ref) - ref, axis=1)
    err_odo = np.linalg.norm(align_rigid_2d(dr[:, 1:], ref) - ref, axis=1)
    nodes = {em.ids[k]: (em.x[k], em.y[k], em.th[k]) for k in range(em.n_experiences)}
    loc = np.array(local, dtype=np.float64).reshape(-1, 4)
    on_map = poses_on_map(nodes, loc[:, 0].astype(np.int64), loc[:, 1:])[:, :2]
    err_on_map = np.linalg.norm(align_rigid_2d(on_map, ref) - ref, axis=1)
    return {"steps": len(odom), "frames": len(frame_times), "templates": len(set(ids.values())),
            "recognised_frames": recognised, "gate_refused": gate.refused, "experiences": em.n_experiences, "links": len(em.links),
            "map_mean_m": float(err_map.mean()), "map_max_m": float(err_map.max()),
            "map_on_final_mean_m": float(err_on_map.mean()), "yaw_bias_rad_s": float(bias.bias),
            "yaw_bias_samples": bias.samples,
            "odometry_mean_m": float(err_odo.mean()), "odometry_max_m": float(err_odo.max()),
            "threshold": threshold, "min_gap_s": min_gap_s, "est": est, "odo": dr, "gt": ref}
