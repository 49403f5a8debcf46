"""Trajectory and map evaluation against ground truth, and the map plot (docs/evaluation.md).

* The paper's metric (as the NeoSLAM / OpenRatSLAM2 scripts compute it): each sequence minus its
  first point (no rotation or scale alignment), per-point Euclidean error; mean and max.
* APE: per-frame error after a least-squares SE(2) alignment (Umeyama, no scale) of the estimate
  onto the ground truth; mean, RMSE and max. Our own implementation (evo is GPL-3.0).
* Loop closures: precision/recall, a closure being correct when the true position of the place it
  matched lies within ``radius`` metres of the current true position.
* Online floor: until the robot first returns to a place, no recognition can correct its pose;
  :func:`online_floor` is the APE of the odometry until that first return, exact from then on.

``evaluate_run(run_dir)`` (``neoslam evaluate RUN_DIR``) reads a run folder and writes
``evaluation.json`` and ``map.png`` (experience map, ground truth and odometry, closures marked).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..tum import read_tum, write_tum

__all__ = ["METRICS", "StampMismatch", "ape", "associate", "best_rotation_2d", "closures_line", "evaluate_run", "loop_closure_quality", "online_floor",
           "paper_metric", "read_closures", "read_tum",
           "umeyama_se2", "write_tum"]


def associate(t_est: np.ndarray, t_ref: np.ndarray, max_dt: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Indices pairing each estimate time with the nearest reference time within ``max_dt``."""
    j = np.clip(np.searchsorted(t_ref, t_est), 1, max(1, len(t_ref) - 1))
    prev = np.clip(j - 1, 0, len(t_ref) - 1)
    j = np.clip(j, 0, len(t_ref) - 1)
    best = np.where(np.abs(t_ref[prev] - t_est) <= np.abs(t_ref[j] - t_est), prev, j)
    ok = np.abs(t_ref[best] - t_est) <= max_dt
    return np.flatnonzero(ok), best[ok]


def best_rotation_2d(e: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The 2x2 rotation R minimising sum |R e_i - r_i|^2 about the origin (Kabsch, no reflection)."""
    U, _, Vt = np.linalg.svd(e.T @ r)
    return Vt.T @ np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T


def umeyama_se2(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (2x2) and translation t minimising sum |R est + t - ref|^2."""
    if len(est) < 2:
        return np.eye(2), (ref.mean(0) - est.mean(0)) if len(est) else np.zeros(2)
    mu_e, mu_r = est.mean(0), ref.mean(0)
    R = best_rotation_2d(est - mu_e, ref - mu_r)
    return R, mu_r - R @ mu_e


def ape(est_xy: np.ndarray, ref_xy: np.ndarray) -> dict[str, float]:
    R, t = umeyama_se2(est_xy, ref_xy)
    err = np.linalg.norm(est_xy @ R.T + t - ref_xy, axis=1)
    return {"mean_m": float(err.mean()), "rmse_m": float(np.sqrt((err ** 2).mean())), "max_m": float(err.max())}


def _first_return(t: np.ndarray, p: np.ndarray, radius: float, min_gap_s: float) -> int:
    """The first row k whose position p[k] lies within ``radius`` of a row at least ``min_gap_s``
    older (t sorted), or len(t). Older rows enter a grid of ``radius`` cells as their time passes,
    so each row looks at the 3 x 3 cells around it: linear in the rows, as ``neoslam evaluate``
    runs it on every run, however long."""
    cell = max(radius, 1e-9)
    keys = np.floor(p / cell).astype(np.int64)
    grid: dict[tuple[int, int], list[int]] = {}
    entered = 0
    for k in range(len(t)):
        while entered < k and t[entered] <= t[k] - min_gap_s:
            grid.setdefault((int(keys[entered, 0]), int(keys[entered, 1])), []).append(entered)
            entered += 1
        cx, cy = int(keys[k, 0]), int(keys[k, 1])
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                near = grid.get((cx + dx, cy + dy))
                if near and (np.linalg.norm(p[near] - p[k], axis=1) <= radius).any():
                    return k
    return len(t)


def online_floor(gt: np.ndarray, odometry: np.ndarray, radius: float = 1.0, min_gap_s: float = 30.0) -> dict[str, Any]:
    """The APE (after SE(2) alignment, as ``trajectory_ape``) of the best online pose a SLAM
    system can have from odometry alone before its first return: the odometry, moved rigidly so
    its first pose is the true first pose, until the first frame whose true position lies within
    ``radius`` of a true position at least ``min_gap_s`` earlier, and the ground truth from that
    frame on. ``gt`` and ``odometry``: (t, x, y, yaw) rows as :func:`read_tum` gives them, paired by
    time (:func:`associate`)."""
    ie, ig = associate(odometry[:, 0], gt[:, 0])
    odo, ref = odometry[ie], gt[ig]
    t, p = ref[:, 0], ref[:, 1:3]
    first = _first_return(t, p, radius, min_gap_s)
    turn = ref[0, 3] - odo[0, 3]
    c, s = np.cos(turn), np.sin(turn)
    start = (odo[:, 1:3] - odo[0, 1:3]) @ np.array([[c, s], [-s, c]]) + p[0]
    est = np.where((np.arange(len(ref)) < first)[:, None], start, p)
    return {"radius_m": radius, "min_gap_s": min_gap_s, "first_return_frame": int(first),
            "first_return_s": float(t[first] - t[0]) if first < len(ref) else None,
            "frames_before_first_return": round(first / max(len(ref), 1), 4),
            "ape_mean_m": ape(est, p)["mean_m"] if len(ref) else None}


def paper_metric(est_xy: np.ndarray, ref_xy: np.ndarray) -> dict[str, float]:
    """Subtract each sequence's first point, then per-point Euclidean error (mean, max)."""
    err = np.linalg.norm((est_xy - est_xy[0]) - (ref_xy - ref_xy[0]), axis=1)
    return {"mean_m": float(err.mean()), "max_m": float(err.max())}


def read_closures(path: str | Path) -> dict[int, int]:
    """closures.csv (written by the recorder): closure frame -> matched frame."""
    out: dict[int, int] = {}
    lines = Path(path).read_text().splitlines()
    for line in lines[1:]:
        parts = line.split(",")
        if len(parts) >= 4 and parts[0].isdigit():
            out[int(parts[0])] = int(parts[3])
    return out


def loop_closure_quality(templates_csv: str | Path, gt: np.ndarray, radius: float = 1.0,
                         min_gap_s: float = 30.0, closures_csv: str | Path | None = None) -> dict[str, Any]:
    """Precision and recall of the loop closures in ``templates.csv`` against ground truth.

    A closure's place is the true position of its matched frame as ``closures_csv`` gives it (the
    frame that opened D's matched interval, or created the matched template), or, without that
    file or row, the true position at the first frame that produced its template. A closure (a
    frame with ``is_loop_closure``) is correct when its place is within ``radius`` metres of the
    frame's true position. A frame is a revisit when the robot was within ``radius`` of its true
    position more than ``min_gap_s`` seconds earlier; recall = revisit frames with a correct closure
    / revisit frames. Frames without a ground-truth sample within 1 s are left out.
    """
    from scipy.spatial import cKDTree

    rows = np.loadtxt(templates_csv, delimiter=",", skiprows=1, ndmin=2)
    if rows.size == 0:
        return {"closures": 0, "correct": 0, "precision": None, "recall": None, "revisit_frames": 0,
                "radius_m": radius}
    ie, gi = associate(rows[:, 1], gt[:, 0], max_dt=1.0)
    frames = rows[ie, 0].astype(int)
    stamps, ids, loops = rows[ie, 1], rows[ie, 2].astype(int), rows[ie, 3].astype(bool)
    pos = gt[gi, 1:3]
    _, first = np.unique(ids, return_index=True)
    place = dict(zip(ids[first].tolist(), pos[first], strict=True))
    tpl_pos = np.array([place[t] for t in ids.tolist()]).reshape(-1, 2)
    matched_by = "template"
    if closures_csv is not None and Path(closures_csv).exists():
        # the matched frame's true position where the recorder knew it (and it has ground truth)
        matched = read_closures(closures_csv)
        at = dict(zip(frames.tolist(), pos, strict=True))
        for i in np.flatnonzero(loops):
            m = matched.get(int(frames[i]))
            if m is not None and m in at:
                tpl_pos[i] = at[m]
        matched_by = "closures.csv"
    correct = loops & (np.linalg.norm(tpl_pos - pos, axis=1) <= radius)
    earliest = np.array([stamps[nb].min() for nb in cKDTree(pos).query_ball_point(pos, radius)])
    revisit = earliest < stamps - min_gap_s
    n_loops, n_rev = int(loops.sum()), int(revisit.sum())
    return {"closures": n_loops, "correct": int(correct.sum()),
            "precision": float(correct.sum() / n_loops) if n_loops else None,
            "recall": float((correct & revisit).sum() / n_rev) if n_rev else None,
            "revisit_frames": n_rev, "radius_m": radius, "min_gap_s": min_gap_s, "matched_by": matched_by}


def closures_line(lc: dict[str, Any]) -> str:
    """The closures' precision and recall at the stated radius, as ``neoslam evaluate`` prints them:
    ``closures: precision 0.85, recall 0.40 at 1.0 m (41 of 48 correct)``."""
    def f(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"

    r = f"{lc.get('radius_m', float('nan')):g}"
    r = r if "." in r or "e" in r or "n" in r else r + ".0"  # 1.0 m, 0.25 m
    return (f"closures: precision {f(lc.get('precision'))}, recall {f(lc.get('recall'))} at "
            f"{r} m ({lc.get('correct', 0)} of {lc.get('closures', 0)} correct)")


#: the two errors ``neoslam evaluate`` prints, each with the line that says what it measures
#: (docs/evaluation.md, "Which figure to quote")
METRICS = {
    "ape": "APE (SE(2)-aligned): each pose's distance to the ground truth after the one rotation and "
           "translation that fit the whole trajectory best (no scale); the accuracy figure to quote",
    "paper": "paper metric (the NeoSLAM authors' per-node error): each experience-map node's distance to "
             "the ground truth after subtracting both first points only (no rotation), so a heading error "
             "at the start grows with the distance; quote it only next to NeoSLAM's published results",
}


class StampMismatch(ValueError):
    """The run's stamps and the ground truth's do not overlap (or one of them has none)."""


def _span(t: np.ndarray) -> str:
    return f"{t.min():.3f} .. {t.max():.3f} s" if len(t) else "no stamps"


def gt_time_shift(traj_t: np.ndarray, gt_t: np.ndarray, offset: float = 0.0, align_start: bool = False,
                  gt_file: str | Path = "the ground truth") -> float:
    """The seconds to add to the ground truth's stamps: ``offset``, or with ``align_start`` the
    difference of the first stamps. Raises :class:`StampMismatch` naming both time ranges and the
    fix when, so shifted, no pose of the run has a ground-truth sample within 0.5 s."""
    if not len(traj_t):
        raise StampMismatch("the run's trajectory.tum holds no pose (did the run fail? its report.json says)")
    if not len(gt_t):
        raise StampMismatch(f"{gt_file} holds no pose")
    shift = float(traj_t.min() - gt_t.min()) if align_start else float(offset)
    if len(associate(np.sort(traj_t), np.sort(gt_t) + shift)[0]):
        return shift
    shifted = f" shifted by {shift:.3f} s" if shift else ""
    raise StampMismatch(
        f"the run's stamps ({_span(traj_t)}) and the ground truth's{shifted} ({_span(gt_t + shift)}, "
        f"{gt_file}) do not overlap: add --gt-offset SECONDS to shift the ground truth's stamps "
        f"(--gt-offset {traj_t.min() - gt_t.min():.3f} if both started together), or --gt-align-start "
        "to align the first stamps")


def evaluate_run(run_dir: str | Path, gt_path: str | Path | None = None, radius: float = 1.0,
                 plot: bool = True, walls: np.ndarray | None = None, gt_offset: float = 0.0,
                 gt_align_start: bool = False) -> dict[str, Any]:
    """Evaluate a run folder against ground truth; write ``evaluation.json`` (and ``map.png``).

    ``gt_path`` defaults to ``RUN_DIR/groundtruth.tum``; ``radius`` is the loop-closure correctness
    radius (m); ``walls`` (n, 2, 2) segments drawn under the plot in ground-truth coordinates, by
    default the synthetic world's when ``report.json`` says the run's source was ``synthetic``.
    ``gt_offset`` (s) is added to the ground truth's stamps; ``gt_align_start`` shifts them so the
    first stamps agree instead. Raises :class:`StampMismatch` when the stamps do not overlap.
    Returns the dict written to ``evaluation.json`` (keys in docs/evaluation.md).
    """
    run_dir = Path(run_dir)
    gt_file = Path(gt_path) if gt_path else run_dir / "groundtruth.tum"
    if not gt_file.exists():
        raise FileNotFoundError(f"no ground truth: {gt_file} (give --gt FILE)")
    gt = read_tum(gt_file)
    traj = read_tum(run_dir / "trajectory.tum")
    shift = gt_time_shift(traj[:, 0], gt[:, 0], gt_offset, gt_align_start, gt_file)
    gt[:, 0] += shift
    result: dict[str, Any] = {"ground_truth": str(gt_file), "ground_truth_offset_s": shift}

    def matched(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(estimate xy, ground truth xy) of the rows with a ground-truth sample near in time."""
        ie, ig = associate(rows[:, 0], gt[:, 0])
        return rows[ie, 1:3], gt[ig, 1:3]

    est, ref = matched(traj)
    result["trajectory_ape"] = ape(est, ref)
    result["trajectory_paper"] = paper_metric(est, ref)
    on_map = run_dir / "trajectory_map.tum"
    est, ref = matched(read_tum(on_map)) if on_map.exists() else (est[:0], ref[:0])
    if len(est):  # every frame re-expressed on the final, relaxed map (docs/evaluation.md)
        result["map_trajectory_ape"] = ape(est, ref)
    mp = json.loads((run_dir / "map.json").read_text()) if (run_dir / "map.json").exists() else {"nodes": []}
    nodes = np.array([[n["stamp"], n["x"], n["y"]] for n in mp["nodes"]]).reshape(-1, 3)
    ne, ng = associate(nodes[:, 0], gt[:, 0], max_dt=1.0) if len(nodes) else ([], [])
    if len(ne):
        result["map_paper"] = paper_metric(nodes[ne, 1:3], gt[ng, 1:3])
        result["map_nodes"] = int(len(nodes))
    odo_file = run_dir / "odometry.tum"
    odo = read_tum(odo_file) if odo_file.exists() else np.empty((0, 4))
    est, ref = matched(odo)
    if len(est):
        result["odometry_ape"] = ape(est, ref)
        result["odometry_paper"] = paper_metric(est, ref)
        result["online_floor"] = online_floor(gt, odo, radius)
    if (run_dir / "templates.csv").exists():
        result["loop_closures"] = loop_closure_quality(run_dir / "templates.csv", gt, radius,
                                                       closures_csv=run_dir / "closures.csv")
    (run_dir / "evaluation.json").write_text(json.dumps(result, indent=2))
    if plot:
        from .plots import plot_map, synthetic_walls

        if walls is None and gt_path is None:
            walls = synthetic_walls(run_dir)
        plot_map(run_dir, gt, traj, mp, result, walls)
    return result
