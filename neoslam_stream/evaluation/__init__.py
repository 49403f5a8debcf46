"""Trajectory and map evaluation against ground truth, and the map plot (docs/evaluation.md).

* The paper's metric (as the NeoSLAM / OpenRatSLAM2 scripts compute it): each sequence minus its
  first point (no rotation or scale alignment), per-point Euclidean error; mean and max.
* APE: per-frame error after a least-squares SE(2) alignment (Umeyama, no scale) of the estimate
  onto the ground truth; mean, RMSE and max; RPE: the error of the motion over 1, 5 and 10 m of
  travel (poses.py; our own implementations, evo is GPL-3.0).
* Loop closures (closures.py): a match is a loop closure only when the robot left the matched
  place (travelled more than 5 closure radii since), else a re-recognition; precision, recall and
  the precision-recall curve over the decisions' confidence, a closure being correct when the true
  position of the place it matched lies within ``radius`` metres of the current true position.
* Online floor: until the robot first returns to a place, no recognition can correct its pose;
  :func:`online_floor` is the APE of the odometry until that first return, exact from then on.

``evaluate_run(run_dir)`` (``neoslam evaluate RUN_DIR``) reads a run folder and writes
``evaluation.json``, ``map.png`` (experience map, ground truth and odometry, closures marked) and
``pr_curve.png``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..tum import read_tum, write_tum
from .closures import (
    closure_figures,
    closures_by_odometry,
    closures_line,
    left_distance,
    loop_closure_quality,
    read_closures,
)
from .poses import ape, associate, best_rotation_2d, paper_metric, rpe, rpe_table, travelled, umeyama_se2

__all__ = ["METRICS", "StampMismatch", "ape", "associate", "best_rotation_2d", "closure_figures",
           "closures_by_odometry", "closures_line", "evaluate_run", "left_distance", "loop_closure_quality",
           "online_floor", "paper_metric", "read_closures", "read_tum", "rpe", "rpe_table", "travelled",
           "umeyama_se2", "write_tum"]


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
    """Evaluate a run folder against ground truth; write ``evaluation.json`` (and ``map.png``,
    ``pr_curve.png``: the loop closures' precision-recall curve, when there are revisits).

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
        """(estimate x, y, yaw; ground truth x, y, yaw) of the rows with a ground-truth sample near in time."""
        ie, ig = associate(rows[:, 0], gt[:, 0])
        return rows[ie, 1:4], gt[ig, 1:4]

    est, ref = matched(traj)
    result["trajectory_ape"] = ape(est[:, :2], ref[:, :2])
    result["trajectory_rpe"] = rpe_table(est, ref)
    result["trajectory_paper"] = paper_metric(est[:, :2], ref[:, :2])
    on_map = run_dir / "trajectory_map.tum"
    est, ref = matched(read_tum(on_map)) if on_map.exists() else (est[:0], ref[:0])
    if len(est):  # every frame re-expressed on the final, relaxed map (docs/evaluation.md)
        result["map_trajectory_ape"] = ape(est[:, :2], ref[:, :2])
        result["map_trajectory_rpe"] = rpe_table(est, ref)
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
        result["odometry_ape"] = ape(est[:, :2], ref[:, :2])
        result["odometry_rpe"] = rpe_table(est, ref)
        result["odometry_paper"] = paper_metric(est[:, :2], ref[:, :2])
        result["online_floor"] = online_floor(gt, odo, radius)
    if (run_dir / "templates.csv").exists():
        result["loop_closures"] = loop_closure_quality(run_dir / "templates.csv", gt, radius,
                                                       closures_csv=run_dir / "closures.csv")
    (run_dir / "evaluation.json").write_text(json.dumps(result, indent=2))
    if plot:
        from .plots import plot_map, plot_pr, synthetic_walls

        if walls is None and gt_path is None:
            walls = synthetic_walls(run_dir)
        plot_map(run_dir, gt, traj, mp, result, walls)
        pr = result.get("loop_closures", {}).get("precision_recall")
        if pr is not None:
            plot_pr({run_dir.name: result["loop_closures"]}, run_dir / "pr_curve.png")
    return result
