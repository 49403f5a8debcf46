"""Trajectory metrics on (t, x, y, yaw) rows: association by time, SE(2) alignment, APE, RPE and
the paper's metric (docs/evaluation.md). Our own implementations: evo is GPL-3.0, so it is used
only as an outside tool (docs/evaluation.md shows the equivalent ``evo_ape`` / ``evo_rpe``)."""

from __future__ import annotations

from typing import Any

import numpy as np

#: the distances of travel over which the relative pose error is measured (m)
RPE_DELTAS_M = (1.0, 5.0, 10.0)


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


def paper_metric(est_xy: np.ndarray, ref_xy: np.ndarray) -> dict[str, float]:
    """Subtract each sequence's first point, then per-point Euclidean error (mean, max)."""
    err = np.linalg.norm((est_xy - est_xy[0]) - (ref_xy - ref_xy[0]), axis=1)
    return {"mean_m": float(err.mean()), "max_m": float(err.max())}


def travelled(xy: np.ndarray) -> np.ndarray:
    """The distance travelled along a path of (n, 2) positions up to each of them (0 at the first)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not len(xy):
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])


def rpe_pairs(ref_xy: np.ndarray, delta_m: float) -> list[tuple[int, int]]:
    """The pairs (i, j) of poses ``delta_m`` of travel apart, as evo_rpe chooses them with
    ``--delta_unit m --pairs_from_reference`` (evo's ``filters.filter_pairs_by_path``, not
    ``--all_pairs``): the first pose, then each pose where the travel along the reference since
    the last one kept reaches ``delta_m``; consecutive kept poses are paired."""
    if not len(ref_xy):
        return []
    kept, since = [0], 0.0
    for i, step in enumerate(np.hypot(*np.diff(ref_xy, axis=0).T).tolist(), start=1):
        since += step
        if since >= delta_m:
            kept.append(i)
            since = 0.0
    return list(zip(kept, kept[1:], strict=False))


def rpe(est: np.ndarray, ref: np.ndarray, delta_m: float) -> dict[str, Any]:
    """The relative pose error over ``delta_m`` of travel: for each pair of poses that far apart
    along the reference (:func:`rpe_pairs`), the motion the estimate made between them, expressed
    in its first pose's frame, against the reference's: the translation error's mean, RMSE and max
    (m; evo_rpe's ``trans_part``), the heading error's mean (deg; its ``angle_deg``) and the number
    of pairs. ``est``, ``ref``: (n, 3) rows of x, y, yaw paired by index. None without a pair."""
    pairs = np.array(rpe_pairs(ref[:, :2], delta_m), dtype=np.int64).reshape(-1, 2)
    if not len(pairs):
        return {"delta_m": delta_m, "pairs": 0, "mean_m": None, "rmse_m": None, "max_m": None, "rot_mean_deg": None}
    i, j = pairs[:, 0], pairs[:, 1]

    def motion(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = p[j, :2] - p[i, :2]
        c, s = np.cos(p[i, 2]), np.sin(p[i, 2])
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]), p[j, 2] - p[i, 2]

    (te, re), (tr, rr) = motion(est), motion(ref)
    err = np.linalg.norm(te - tr, axis=1)
    rot = np.degrees(np.abs(np.angle(np.exp(1j * (re - rr)))))
    return {"delta_m": delta_m, "pairs": int(len(pairs)), "mean_m": float(err.mean()),
            "rmse_m": float(np.sqrt((err ** 2).mean())), "max_m": float(err.max()), "rot_mean_deg": float(rot.mean())}


def rpe_table(est: np.ndarray, ref: np.ndarray, deltas: tuple[float, ...] = RPE_DELTAS_M) -> dict[str, Any]:
    """:func:`rpe` over each distance of ``deltas``, keyed ``"1m"``, ``"5m"``, ``"10m"``."""
    return {f"{d:g}m": rpe(est, ref, d) for d in deltas}
