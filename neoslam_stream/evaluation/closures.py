"""Which matches are loop closures, how good they are, and their precision-recall curve.

A front end's match of frame t to what it saw at frame m (closures.csv's ``matched_frame``) is a
**loop closure** only when the robot left that place in between: it travelled more than
``left_m`` along its path from m to t. ``left_m`` defaults to :data:`LEFT_RADII` times the
closure radius (5 m at 1 m): a path that long which ends within the radius of its start went at
least (left_m - radius) / 2 = 2 radii away from it, so a pause, a turn on the spot or a stretch of
corridor never counts as having left. The other matches recognise a place just passed again: they
are **re-recognitions**, counted beside the closures and never in their precision or recall.
:func:`closure_figures` is the one definition, used by ``neoslam evaluate`` (the run folder's files,
:func:`loop_closure_quality`) and by the benches (bench/streams.py), docs/evaluation.md.

Each decided closure keeps the confidence it was decided on (closures.csv's ``confidence``); sweeping
a threshold over it gives the precision-recall curve below the run's own decision (recall over the
revisiting frames, as the single figure).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .poses import associate, travelled

#: a match is a loop closure when the robot travelled more than this many closure radii since
#: the matched frame (see the module docstring)
LEFT_RADII = 5.0
#: the precisions at which the curve's best recall is reported
PRECISIONS = (1.0, 0.99, 0.95)
#: evaluation.json keeps at most this many points of the curve (its area uses them all)
CURVE_POINTS = 200


def left_distance(radius: float) -> float:
    """D: the travel (m) after which the robot has left a place, at closure radius ``radius``."""
    return LEFT_RADII * radius


def precision_recall(confidence: np.ndarray, correct: np.ndarray, hit: np.ndarray,
                     n_revisit: int) -> dict[str, Any] | None:
    """The loop closures' precision-recall curve as a threshold on ``confidence`` falls from the
    highest to the run's own decision: at each distinct confidence, precision over the closures at
    or above it and recall = their ``hit`` (correct, at a revisiting frame) / ``n_revisit``. A
    closure without a confidence (NaN) ranks below every other. ``area``: average precision, the
    sum of precision x recall gained over the thresholds (scikit-learn's), at most the run's
    recall; ``recall_at_precision``: the best recall where precision is at least each of
    :data:`PRECISIONS` (0 where none reaches it). None without revisiting frames."""
    if n_revisit <= 0:
        return None
    if not len(confidence):
        return {"ranked_by": "confidence", "unranked": 0, "area": 0.0,
                "recall_at_precision": {str(p): 0.0 for p in PRECISIONS},
                "curve": {"confidence": [], "precision": [], "recall": []}}
    conf = np.where(np.isnan(confidence), -np.inf, np.asarray(confidence, dtype=np.float64))
    order = np.argsort(-conf, kind="stable")
    conf, correct, hit = conf[order], np.asarray(correct, bool)[order], np.asarray(hit, bool)[order]
    last = np.flatnonzero(np.append(conf[1:] != conf[:-1], True))  # the end of each distinct confidence
    n = last + 1
    precision = np.cumsum(correct)[last] / n
    recall = np.cumsum(hit)[last] / n_revisit
    area = float(np.sum(np.diff(np.concatenate([[0.0], recall])) * precision))
    best = {str(p): float(recall[precision >= p - 1e-12].max(initial=0.0)) for p in PRECISIONS}
    keep = np.unique(np.linspace(0, len(last) - 1, min(len(last), CURVE_POINTS)).round().astype(int))
    return {"ranked_by": "confidence", "unranked": int(np.isinf(conf).sum()), "area": area,
            "recall_at_precision": best,
            "curve": {"confidence": [None if np.isinf(c) else float(c) for c in conf[last][keep]],
                      "precision": precision[keep].tolist(), "recall": recall[keep].tolist()}}


def closure_figures(at: np.ndarray, place: np.ndarray, travel: np.ndarray, revisit: np.ndarray,
                    n_revisit: int, radius: float, left_m: float | None = None,
                    confidence: np.ndarray | None = None) -> dict[str, Any]:
    """The figures of a run's matches, one row each: ``at`` the frame's true (x, y), ``place`` the
    matched frame's, ``travel`` the distance travelled from the matched frame to the frame,
    ``revisit`` whether the frame revisits a place (recall's numerator counts those); ``n_revisit``
    the revisiting frames (recall's denominator). A match is a loop closure when ``travel`` >
    ``left_m`` (default :func:`left_distance`), correct when ``place`` lies within ``radius`` of
    ``at``. ``confidence``: each match's decision confidence, for the precision-recall curve."""
    left = left_distance(radius) if left_m is None else float(left_m)
    at, place = np.asarray(at, np.float64).reshape(-1, 2), np.asarray(place, np.float64).reshape(-1, 2)
    near = np.hypot(*(at - place).T) <= radius
    loop = np.asarray(travel, np.float64) > left
    hit = loop & near & np.asarray(revisit, bool)
    n_loop, n_correct = int(loop.sum()), int((loop & near).sum())
    out: dict[str, Any] = {
        "closures": n_loop, "correct": n_correct, "precision": n_correct / n_loop if n_loop else None,
        "recall": int(hit.sum()) / n_revisit if n_revisit else None, "revisit_frames": int(n_revisit),
        "radius_m": radius, "left_m": left,
        "re_recognitions": {"count": int((~loop).sum()), "correct": int((~loop & near).sum())}}
    if confidence is not None:
        conf = np.asarray(confidence, np.float64)
        out["precision_recall"] = precision_recall(conf[loop], near[loop], hit[loop], n_revisit)
    return out


def read_closures(path: str | Path) -> dict[int, tuple[int, float]]:
    """closures.csv (written by the recorder): closure frame -> (matched frame, confidence; NaN
    where the row has none, or the file has no such column)."""
    out: dict[int, tuple[int, float]] = {}
    lines = Path(path).read_text().splitlines()
    col = lines[0].split(",").index("confidence") if lines and "confidence" in lines[0].split(",") else -1
    for line in lines[1:]:
        parts = line.split(",")
        if len(parts) >= 4 and parts[0].isdigit():
            conf = parts[col] if 0 <= col < len(parts) else ""
            out[int(parts[0])] = (int(parts[3]), float(conf) if conf else float("nan"))
    return out


def loop_closure_quality(templates_csv: str | Path, gt: np.ndarray, radius: float = 1.0,
                         min_gap_s: float = 30.0, closures_csv: str | Path | None = None,
                         left_m: float | None = None) -> dict[str, Any]:
    """Loop closures and re-recognitions of a run folder's ``templates.csv`` against ground truth
    (``gt``: (t, x, y, yaw) rows), by :func:`closure_figures`.

    A match's matched frame is the one ``closures_csv`` names (the frame that opened D's matched
    interval, or created the matched template) or, without that file or row, the first frame that
    produced its template; its place and travel are the ground truth's there, the travel measured
    along the ground truth's path. A frame is a revisit when the robot was within ``radius`` of its
    true position more than ``min_gap_s`` seconds earlier. Frames without a ground-truth sample
    within 1 s are left out.
    """
    from scipy.spatial import cKDTree

    rows = np.loadtxt(templates_csv, delimiter=",", skiprows=1, ndmin=2)
    left = left_distance(radius) if left_m is None else left_m
    empty = {"closures": 0, "correct": 0, "precision": None, "recall": None, "revisit_frames": 0,
             "radius_m": radius, "left_m": left, "re_recognitions": {"count": 0, "correct": 0}}
    if rows.size == 0:
        return empty
    ie, gi = associate(rows[:, 1], gt[:, 0], max_dt=1.0)
    frames = rows[ie, 0].astype(int)
    stamps, ids, loops = rows[ie, 1], rows[ie, 2].astype(int), rows[ie, 3].astype(bool)
    pos, path = gt[gi, 1:3], travelled(gt[:, 1:3])[gi]
    _, first = np.unique(ids, return_index=True)
    first_row = dict(zip(ids[first].tolist(), first.tolist(), strict=True))
    matched_row = np.array([first_row[t] for t in ids.tolist()], dtype=np.int64).reshape(-1)
    confidence = np.full(len(frames), np.nan)
    matched_by = "template"
    if closures_csv is not None and Path(closures_csv).exists():
        # the matched frame where the recorder knew it (and it has ground truth)
        matched = read_closures(closures_csv)
        row_of = {f: i for i, f in enumerate(frames.tolist())}
        for i in np.flatnonzero(loops):
            m, conf = matched.get(int(frames[i]), (None, np.nan))
            confidence[i] = conf
            if m is not None and m in row_of:
                matched_row[i] = row_of[m]
        matched_by = "closures.csv"
    earliest = np.array([stamps[nb].min() for nb in cKDTree(pos).query_ball_point(pos, radius)])
    revisit = earliest < stamps - min_gap_s
    idx = np.flatnonzero(loops)
    m = matched_row[idx]
    out = closure_figures(pos[idx], pos[m], path[idx] - path[m], revisit[idx], int(revisit.sum()), radius, left,
                          confidence[idx])
    return {**out, "min_gap_s": min_gap_s, "matched_by": matched_by, "travelled_from": "ground truth"}


def closures_by_odometry(run_dir: str | Path, radius: float = 1.0) -> dict[str, Any] | None:
    """Without ground truth: the decided matches of closures.csv split into loop closures and
    re-recognitions by the travel of the wheel odometry (odometry.tum: its path length, which drifts
    far less than its position) between each matched frame and its frame, at the travel
    :func:`left_distance` of ``radius``. None without closures.csv, templates.csv or odometry.tum
    (nothing says how far the robot went); frames without an odometry sample within 0.5 s are left out."""
    from ..tum import read_tum

    run_dir = Path(run_dir)
    files = [run_dir / n for n in ("closures.csv", "templates.csv", "odometry.tum")]
    if not all(f.exists() for f in files):
        return None
    matched = read_closures(files[0])
    rows = np.loadtxt(files[1], delimiter=",", skiprows=1, ndmin=2)
    odo = read_tum(files[2])
    if not matched or rows.size == 0 or not len(odo):
        return None
    stamp = dict(zip(rows[:, 0].astype(int).tolist(), rows[:, 1].tolist(), strict=True))
    pairs = [(stamp[f], stamp[m]) for f, (m, _c) in matched.items() if f in stamp and m in stamp]
    t = np.array(pairs, dtype=np.float64).reshape(-1, 2)
    path = travelled(odo[:, 1:3])
    ia, oa = associate(t[:, 0], odo[:, 0])
    ib, ob = associate(t[:, 1], odo[:, 0])
    both = np.intersect1d(ia, ib)
    travel = path[oa[np.searchsorted(ia, both)]] - path[ob[np.searchsorted(ib, both)]]
    left = left_distance(radius)
    n_loop = int((travel > left).sum())
    return {"closures": n_loop, "re_recognitions": int(len(travel) - n_loop), "left_m": left,
            "travelled_from": "odometry.tum"}


def closures_line(lc: dict[str, Any]) -> str:
    """The closures' precision and recall at the stated radius and the re-recognitions beside them,
    as ``neoslam evaluate`` prints them: ``closures: precision 0.85, recall 0.40 at 1.0 m (41 of 48
    correct); 76 re-recognitions of a place just passed (left after 5 m of travel)``."""
    def f(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"

    r = f"{lc.get('radius_m', float('nan')):g}"
    r = r if "." in r or "e" in r or "n" in r else r + ".0"  # 1.0 m, 0.25 m
    line = (f"closures: precision {f(lc.get('precision'))}, recall {f(lc.get('recall'))} at "
            f"{r} m ({lc.get('correct', 0)} of {lc.get('closures', 0)} correct)")
    rr = lc.get("re_recognitions")
    if rr is not None:
        line += f"; {rr['count']} re-recognitions of a place just passed (left after {lc['left_m']:g} m of travel)"
    return line
