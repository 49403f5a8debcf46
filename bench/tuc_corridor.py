"""The TU Chemnitz corridor run through the back end's pose cells and experience map.

Wheel odometry (10 Hz: forward speed vx and turn rate wz, as RatSLAM uses them) drives the
:class:`~neoslam_stream.algorithms.backend.PoseCellStage` (yaw-rate bias, odometry gate, pose
cells) and the experience map. Visual templates come from the run's loop-closure candidates: every
time stamp that appears in a candidate is a camera frame; a frame whose best candidate with an
earlier frame (at least ``min_gap_s`` earlier, similarity >= ``threshold``) exists reuses that
frame's template id (a place recognised), otherwise it gets a new id. The error of the
experience-map trajectory and of odometry alone is measured against the 2-D ground truth after
the same rigid 2-D alignment (rotation + translation, least squares) of each. Settings:
bench/settings/tuc.yaml and tuc_paper.yaml. Used by bench/ratslam.py, studies/maps.py and
tests/test_ratslam_tuc.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from bench_settings import data_root, load_settings

from neoslam_stream.algorithms.backend import PoseCellStage, integrate
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.map_poses import poses_on_map
from neoslam_stream.algorithms.sequence import SequenceFilter
from neoslam_stream.evaluation import best_rotation_2d

DATA = data_root() / "tuc_slam_odom_loops"


def load_ground_truth(path=None) -> np.ndarray:
    """(n, 3) rows (t, x, y) of the ``point2`` records only, sorted by time.

    The GT file interleaves ``point2 t x y ...`` (positions, metres) with ``angle t heading 0``
    records (headings, not positions).
    """
    rows = []
    for line in open(path or DATA / "Corridor_GT.txt"):
        p = line.split()
        if p and p[0] == "point2":
            rows.append((float(p[1]), float(p[2]), float(p[3])))
    gt = np.array(rows, dtype=np.float64)
    return gt[np.argsort(gt[:, 0], kind="stable")]


def load(limit_s: float | None = None, start_s: float | None = None):
    """Odometry rows (t, vx, wz), loop candidates (t1, t2, similarity) and ground truth (t, x, y),
    from ``start_s`` (a run that starts there: candidates whose both frames are that late) to
    ``limit_s``."""
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
    if start_s is not None:
        odom = odom[odom[:, 0] >= start_s]
        loops = loops[np.minimum(loops[:, 0], loops[:, 1]) >= start_s]
        gt = gt[gt[:, 0] >= start_s]
    return odom, loops, gt


@functools.lru_cache(maxsize=1)
def halfway_s() -> float:
    """The middle of the recording's time span: the back end's constants were chosen on the run up
    to it, and the run from it on is the held-out half."""
    odom = load()[0]
    return float(odom[0, 0] + odom[-1, 0]) / 2


def run_half(half: str, pose_cells: dict, experience_map: dict, map_cls: type = ExperienceMap) -> dict:
    """:func:`run` on one half of the recording alone, under bench/settings/tuc.yaml's protocol:
    ``first`` (up to :func:`halfway_s`, the half on which the back end's constants are chosen) or
    ``second`` (from it on, held out)."""
    if half not in ("first", "second"):
        raise ValueError(f"half must be 'first' or 'second', got {half!r}")
    proto = load_settings("tuc")["protocol"]
    part = {"limit_s": halfway_s()} if half == "first" else {"start_s": halfway_s()}
    return run(pose_cells, experience_map, proto["threshold"], proto["min_gap_s"], map_cls=map_cls, **part)


def templates_from_loops(loops: np.ndarray, threshold: float, min_gap_s: float,
                         sequence: dict | None = None) -> dict[float, int]:
    """time -> template id, in time order. ``sequence``: the parameters of a
    :class:`~neoslam_stream.algorithms.sequence.SequenceFilter` over frame indices (a recognised
    frame must continue a run of consistent recognitions), as stage D's ``sequence`` setting."""
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


def run(pose_cells: dict, experience_map: dict, threshold: float = 0.8, min_gap_s: float = 60.0,
        limit_s: float | None = None, sequence: dict | None = None, start_s: float | None = None,
        map_cls: type = ExperienceMap) -> dict:
    """The corridor run through the pose-cell stage (``pose_cells``: that config section, with its
    ``odometry_gate`` and ``odometry_bias``) and an experience map (``experience_map``); the
    templates that arrive between two odometry steps reach the stage first, as in a run.
    ``sequence``: see :func:`templates_from_loops`. ``map_on_final_mean_m``: the error of every
    step re-expressed on the final map (as trajectory_map.tum). ``start_s`` / ``limit_s``: a run
    of that part of the recording alone (:func:`load`), e.g. the half that chose no constant.
    ``map_cls``: the experience map's class (studies/relaxation_models.py measures others)."""
    odom, loops, gt = load(limit_s, start_s)
    ids = templates_from_loops(loops, threshold, min_gap_s, sequence)
    frame_times = np.array(sorted(ids))
    stage = PoseCellStage(pose_cells)
    em = map_cls(experience_map)
    fi = 0
    est, dr, local = [], [], []
    x = y = 0.0
    th = math.radians(em.config.exp_initial_em_deg)
    prev_t = odom[0, 0]
    recognised = 0
    for t, vx, wz in odom:
        dt = t - prev_t
        prev_t = t
        while fi < len(frame_times) and frame_times[fi] <= t:
            vt = ids[frame_times[fi]]
            known = vt in stage.network.templates
            if stage.on_template(vt, 0.0):  # it reached the pose cells: a place recognised if known
                recognised += int(known)
            fi += 1
        p = integrate(em, stage.on_odometry(vx, wz, dt, t), t)
        est.append((t, p.pose[0], p.pose[1]))
        local.append((p.exp_id, *p.local))
        th += wz * dt
        x += vx * dt * math.cos(th)
        y += vx * dt * math.sin(th)
        dr.append((t, x, y))
    est, dr = np.array(est), np.array(dr)
    idx = np.clip(np.searchsorted(gt[:, 0], est[:, 0]), 0, len(gt) - 1)
    ref = gt[idx, 1:3]
    err_map = np.linalg.norm(align_rigid_2d(est[:, 1:], ref) - ref, axis=1)
    err_odo = np.linalg.norm(align_rigid_2d(dr[:, 1:], ref) - ref, axis=1)
    loc = np.array(local, dtype=np.float64).reshape(-1, 4)
    on_map = poses_on_map(em.node_poses(), loc[:, 0].astype(np.int64), loc[:, 1:])[:, :2]
    err_on_map = np.linalg.norm(align_rigid_2d(on_map, ref) - ref, axis=1)
    bias = stage.bias
    return {"steps": len(odom), "frames": len(frame_times), "templates": len(set(ids.values())),
            "recognised_frames": recognised, "gate_refused": stage.gate.refused,
            "experiences": em.n_experiences, "links": len(em.links),
            "map_mean_m": float(err_map.mean()), "map_max_m": float(err_map.max()),
            "map_on_final_mean_m": float(err_on_map.mean()), "yaw_bias_rad_s": float(bias.bias),
            "yaw_bias_samples": bias.samples,
            "odometry_mean_m": float(err_odo.mean()), "odometry_max_m": float(err_odo.max()),
            "threshold": threshold, "min_gap_s": min_gap_s, "est": est, "odo": dr, "gt": ref}
