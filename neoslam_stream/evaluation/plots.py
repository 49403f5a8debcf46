"""Plots of runs: the map against ground truth and odometry (map.png), the loop closures'
precision-recall curve (pr_curve.png), and NeoSLAM vs RatSLAM on the same stream (compare.png,
compare_pr.png)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..tum import read_tum
from .poses import associate, umeyama_se2


def synthetic_walls(run_dir: Path) -> np.ndarray | None:
    try:
        kind = json.loads((run_dir / "report.json").read_text()).get("source", {}).get("kind")
    except (OSError, ValueError, AttributeError):
        return None
    if kind != "synthetic":
        return None
    from ..sources.synthetic import WALLS

    return WALLS[:, :4].reshape(-1, 2, 2)


def plot_map(run_dir: Path, gt: np.ndarray, traj: np.ndarray, mp: dict, result: dict,
             walls: np.ndarray | None = None) -> None:
    """``map.png``: ground truth (black, on top), odometry (red) and the final experience map (blue
    nodes and links, placed by the online trajectory's fit), each aligned onto the ground truth by
    SE(2) Umeyama, loop closures as hollow green rings at their true positions (the ground truth
    shows through), the world's walls (grey) when known; the title gives both trajectory errors,
    online (trajectory.tum) and on the final map (trajectory_map.tum)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ie, ig = associate(traj[:, 0], gt[:, 0])
    R, t = umeyama_se2(traj[ie, 1:3], gt[ig, 1:3])
    fig, ax = plt.subplots(figsize=(7, 6))
    if walls is not None:
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(np.asarray(walls), colors="0.6", linewidths=2.0, zorder=0))
    tpl = run_dir / "templates.csv"
    if tpl.exists():  # first, so that the paths stay visible on top of them
        rows = np.loadtxt(tpl, delimiter=",", skiprows=1, ndmin=2)
        if rows.size:
            lc = rows[rows[:, 3] > 0]
            _, gi = associate(lc[:, 1], gt[:, 0], max_dt=1.0)
            ax.plot(gt[gi, 1], gt[gi, 2], "o", ms=7, mfc="none", mec="limegreen", mew=0.8, alpha=0.6,
                    label="loop closure (true position)", zorder=1)
    ax.plot(gt[:, 1], gt[:, 2], "k-", lw=1.2, label="ground truth", zorder=4)
    odo_file = run_dir / "odometry.tum"
    if odo_file.exists():
        odo = read_tum(odo_file)
        oe, og = associate(odo[:, 0], gt[:, 0])
        Ro, to = umeyama_se2(odo[oe, 1:3], gt[og, 1:3])
        o = odo[:, 1:3] @ Ro.T + to
        ax.plot(o[:, 0], o[:, 1], "r-", lw=0.8, alpha=0.7, label="odometry")
    nodes = {n["id"]: np.array([n["x"], n["y"]]) @ R.T + t for n in mp.get("nodes", [])}
    for lk in mp.get("links", []):
        a, b = nodes.get(lk["from"]), nodes.get(lk["to"])
        if a is not None and b is not None:
            ax.plot([a[0], b[0]], [a[1], b[1]], "b-", lw=0.6)
    if nodes:
        pts = np.array(list(nodes.values()))
        ax.plot(pts[:, 0], pts[:, 1], "b.", ms=3, label="experience map (final)")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    online = result.get("trajectory_ape", {}).get("mean_m")
    final = (result.get("map_trajectory_ape") or {}).get("mean_m")
    parts = [f"online {online:.2f} m" if online is not None else "online n/a"]
    if final is not None:
        parts.append(f"on the final map {final:.2f} m")
    ax.set_title(f"{run_dir.name}: trajectory APE mean, {', '.join(parts)}", fontsize=10)
    fig.savefig(run_dir / "map.png", dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_compare(dirs: dict[str, Path], out: Path, ape: dict[str, float | None] | None = None) -> None:
    """``compare.png``: one panel per pipeline (``dirs``: label -> run folder) with its experience
    map (nodes and links) and its trajectory, the ground truth and the odometry, each aligned onto
    the ground truth by SE(2) Umeyama (the map with its trajectory's transform); the world's walls
    when the run's source was synthetic; ``ape``: label -> APE mean (m) for the panel titles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(dirs.values()))
    gt = read_tum(first / "groundtruth.tum") if (first / "groundtruth.tum").exists() else None
    odo = read_tum(first / "odometry.tum") if (first / "odometry.tum").exists() else None
    walls = synthetic_walls(first)
    fig, axes = plt.subplots(1, len(dirs), figsize=(5.5 * len(dirs), 5.2), sharex=True, sharey=True,
                             squeeze=False)
    colours = iter(("b", "m", "g", "c", "y"))
    for ax, (name, d) in zip(axes[0], dirs.items(), strict=True):
        colour = next(colours, "k")
        if walls is not None:
            from matplotlib.collections import LineCollection

            ax.add_collection(LineCollection(np.asarray(walls), colors="0.75", linewidths=1.5, zorder=0))
        if gt is not None:
            ax.plot(gt[:, 1], gt[:, 2], "k-", lw=1.2, label="ground truth")
            if odo is not None:
                oe, og = associate(odo[:, 0], gt[:, 0])
                Ro, to = umeyama_se2(odo[oe, 1:3], gt[og, 1:3])
                o = odo[:, 1:3] @ Ro.T + to
                ax.plot(o[:, 0], o[:, 1], "r-", lw=0.7, alpha=0.6, label="odometry")
        f = d / "trajectory.tum"
        if f.exists():
            tr = read_tum(f)
            R, t = np.eye(2), np.zeros(2)
            if gt is not None:
                ie, ig = associate(tr[:, 0], gt[:, 0])
                R, t = umeyama_se2(tr[ie, 1:3], gt[ig, 1:3])
            xy = tr[:, 1:3] @ R.T + t
            ax.plot(xy[:, 0], xy[:, 1], f"{colour}-", lw=0.5, alpha=0.5, label=f"{name} trajectory")
            mp_file = d / "map.json"
            mp = json.loads(mp_file.read_text()) if mp_file.exists() else {}
            nodes = {n["id"]: np.array([n["x"], n["y"]]) @ R.T + t for n in mp.get("nodes", [])}
            for lk in mp.get("links", []):
                a, b = nodes.get(lk["from"]), nodes.get(lk["to"])
                if a is not None and b is not None:
                    ax.plot([a[0], b[0]], [a[1], b[1]], f"{colour}-", lw=0.6)
            if nodes:
                pts = np.array(list(nodes.values()))
                ax.plot(pts[:, 0], pts[:, 1], f"{colour}.", ms=3, label=f"{name} map")
        a = (ape or {}).get(name)
        ax.set_title(name if a is None else f"{name}: APE mean {a:.2f} m", fontsize=10)
        ax.set_aspect("equal")
        ax.legend(loc="best", fontsize=7)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_pr(closures: dict[str, dict], out: Path) -> None:
    """The loop closures' precision-recall curves (``pr_curve.png``; ``compare_pr.png`` with one
    curve per pipeline): ``closures``: label -> evaluation.json's ``loop_closures``. Each curve runs
    from the most confident closure to the run's own decision (marked), recall over the revisiting
    frames; the legend gives its area (average precision)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    drawn = 0
    for (name, lc), colour in zip(closures.items(), ("b", "m", "g", "c", "y"), strict=False):
        pr = (lc or {}).get("precision_recall")
        if not pr or not pr["curve"]["recall"]:
            continue
        drawn += 1
        r, p = [0.0, *pr["curve"]["recall"]], [pr["curve"]["precision"][0], *pr["curve"]["precision"]]
        ax.step(r, p, where="post", color=colour, label=f"{name}: area {pr['area']:.2f}, "
                f"{lc['closures']} closures, {lc['re_recognitions']['count']} re-recognitions")
        ax.plot(r[-1:], p[-1:], "o", color=colour)
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("recall (revisiting frames closed correctly)")
    ax.set_ylabel("precision (loop closures correct)")
    radius = next((lc.get("radius_m") for lc in closures.values() if lc), None)
    ax.set_title(f"loop closures within {radius:g} m, ranked by confidence (dot: the run's decision)"
                 if radius is not None else "loop closures", fontsize=9)
    if drawn:
        ax.legend(loc="lower left", fontsize=7)
    else:
        ax.text(0.5, 0.5, "no loop closure, or no revisiting frame: no curve", ha="center", fontsize=9)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
