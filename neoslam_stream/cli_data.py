"""Data subcommands: ``neoslam evaluate`` and ``neoslam dataset synthetic``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .cli import print_evaluation
    from .evaluation import evaluate_run

    try:
        ev = evaluate_run(args.run_dir, args.gt, radius=args.radius)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_evaluation(ev)
    return 0


def cmd_dataset_synthetic(args: argparse.Namespace) -> int:
    import cv2

    from .evaluation import write_tum
    from .sources.synthetic import SyntheticWorldSource

    out = Path(args.out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    params = {k: getattr(args, k) for k in ("frames", "seed", "laps_cw", "laps_ccw", "width", "height")
              if getattr(args, k) is not None}
    try:
        src = SyntheticWorldSource(**params)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    gt, odo = [], []
    import math

    x = y = th = 0.0
    for sf in src:
        cv2.imwrite(str(out / "images" / f"{sf.frame:06d}.png"), sf.image[:, :, ::-1])
        gt.append((sf.stamp, *sf.groundtruth))
        v, w, dt = sf.odom
        th += w * dt
        x += v * dt * math.cos(th)
        y += v * dt * math.sin(th)
        odo.append((sf.stamp, x, y, th))
    write_tum(out / "groundtruth.tum", gt)
    write_tum(out / "odometry.tum", odo)
    print(f"wrote {len(gt)} frames, groundtruth.tum and odometry.tum to {out}")
    return 0


def cmd_map_export(args: argparse.Namespace) -> int:
    from .checkpoint import export_map

    out = Path(args.out) if args.out else Path(args.run_dir) / "map.neoslam"
    try:
        meta = export_map(args.run_dir, out)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MB): stages {', '.join(meta['stages'])} "
          f"from {meta['from_states']}")
    return 0


def cmd_map_info(args: argparse.Namespace) -> int:
    from .checkpoint import load_map_file

    try:
        data = load_map_file(args.map_file)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.map_file}: {data['format']} v{data['version']}, pipeline {data.get('pipeline')}, "
          f"{data.get('frames')} frames, from {data.get('from_run')}")
    for name, state in sorted(data["stages"].items()):
        print(f"  {name}: {', '.join(sorted(state))}")
    return 0


def register(sub: argparse._SubParsersAction, bench_sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("map", help="export / inspect maps for long-term deployment",
                       description="A map is every stage's learned state (templates, TM connections, "
                                   "intervals, pose cells, experience map) in one file; "
                                   "`neoslam run --map FILE` starts a new session on it.")
    msub = m.add_subparsers(dest="map_command", metavar="ACTION")
    me = msub.add_parser("export", help="pack a finished (or checkpointed) run's state into a map file")
    me.add_argument("run_dir")
    me.add_argument("--out", help="map file (default RUN_DIR/map.neoslam)")
    me.set_defaults(func=cmd_map_export)
    mi = msub.add_parser("info", help="what a map file holds")
    mi.add_argument("map_file")
    mi.set_defaults(func=cmd_map_info)
    m.set_defaults(func=lambda a: (m.print_help(), 2)[1])
    p = sub.add_parser("evaluate", help="trajectory / map error of a run folder against ground truth",
                       description="Recompute evaluation.json and map.png of a run folder.")
    p.add_argument("run_dir")
    p.add_argument("--gt", help="ground truth TUM file (default: RUN_DIR/groundtruth.tum)")
    p.add_argument("--radius", type=float, default=1.0, help="loop-closure correctness radius (m)")
    p.set_defaults(func=cmd_evaluate)
    d = sub.add_parser("dataset", help="write data sets", description="Write data sets to disk.")
    dsub = d.add_subparsers(dest="dataset", metavar="KIND")
    s = dsub.add_parser("synthetic", help="the synthetic world as PNG images + TUM files",
                        description="Render the synthetic world to DIR/images/*.png with groundtruth.tum "
                                    "and odometry.tum.")
    s.add_argument("--out", required=True)
    s.add_argument("--frames", type=int, default=None, help="number of frames (default: the whole route)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--laps-cw", type=int, default=None, help="laps one way (default 2)")
    s.add_argument("--laps-ccw", type=int, default=None, help="laps the other way afterwards (default 1)")
    s.add_argument("--width", type=int, default=None, help="image width (default 416)")
    s.add_argument("--height", type=int, default=None, help="image height (default 240)")
    s.set_defaults(func=cmd_dataset_synthetic)
    from .cli import add_run_options

    c = sub.add_parser("compare", help="NeoSLAM and RatSLAM on the same stream, side by side",
                       description="Run NeoSLAM and the RatSLAM baseline (local-view cells) in one run, the image "
                                   "topic fanned out to both; print a table and write compare.json and "
                                   "compare.png (RatSLAM's files in OUT/ratslam/).")
    add_run_options(c)
    c.set_defaults(func=cmd_compare)


def cmd_compare(args: argparse.Namespace) -> int:
    """NeoSLAM and RatSLAM on the same stream in one run, then a side-by-side table and one plot."""
    import json
    import shutil

    from .cli import _load, print_summary
    from .evaluation import evaluate_run
    from .topology import RunError, run

    args.pipeline = "compare"
    cfg = _load(args)
    out = Path(args.out or "runs/compare")
    try:
        res = run(cfg, out)
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print_summary(res.report)
    dirs = {"neoslam": out, "ratslam": out / "ratslam"}
    for name in ("groundtruth.tum", "odometry.tum"):
        if (out / name).exists():
            shutil.copy(out / name, dirs["ratslam"] / name)
    stages = res.report.get("stages", {})
    table = {}
    for pipeline, d in dirs.items():
        ev = evaluate_run(d) if (d / "groundtruth.tum").exists() else {}
        mine = {s: v for s, v in stages.items() if s.startswith("rs_") == (pipeline == "ratslam")}
        table[pipeline] = {
            "frames_processed": max((v.get("processed", 0) for s, v in mine.items()
                                     if s in ("A", "rs_local_view")), default=None),
            "trajectory_ape_mean_m": ev.get("trajectory_ape", {}).get("mean_m"),
            "trajectory_ape_max_m": ev.get("trajectory_ape", {}).get("max_m"),
            "map_paper_mean_m": ev.get("map_paper", {}).get("mean_m"),
            "map_paper_max_m": ev.get("map_paper", {}).get("max_m"),
            "loop_closures": ev.get("loop_closures", {}).get("closures"),
            "loop_precision": ev.get("loop_closures", {}).get("precision"),
            "stage_tau_p50_ms": {s: v.get("tau_p50_ms") for s, v in mine.items()},
        }
        if pipeline == "neoslam" and "odometry_ape" in ev:
            table["odometry"] = {"trajectory_ape_mean_m": ev["odometry_ape"]["mean_m"],
                                 "trajectory_ape_max_m": ev["odometry_ape"]["max_m"]}
    (out / "compare.json").write_text(json.dumps(table, indent=2))
    _print_compare(table)
    _plot_compare(dirs)
    print(f"compare.json and compare.png in {out}")
    return 0


def _print_compare(table: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title="NeoSLAM vs RatSLAM (same stream)")
    cols = ("frames_processed", "trajectory_ape_mean_m", "trajectory_ape_max_m", "map_paper_mean_m",
            "map_paper_max_m", "loop_closures", "loop_precision")
    t.add_column("")
    short = ("frames", "APE mean m", "APE max m", "paper mean m", "paper max m", "loops", "precision")
    for c in short:
        t.add_column(c, justify="right")
    for name, row in table.items():
        t.add_row(name, *[("" if row.get(c) is None else f"{row[c]:.3f}" if isinstance(row.get(c), float)
                           else str(row[c])) for c in cols])
    con = Console()
    con.print(t)
    lat = Table(title="per-stage latency (tau p50, ms)")
    lat.add_column("pipeline")
    lat.add_column("stages")
    for name, row in table.items():
        taus = row.get("stage_tau_p50_ms") or {}
        lat.add_row(name, ", ".join(f"{s}: {v:.1f}" for s, v in taus.items() if v is not None))
    con.print(lat)


def _plot_compare(dirs: dict[str, Path]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .evaluation import associate, read_tum, umeyama_se2

    fig, ax = plt.subplots(figsize=(7, 6))
    out = dirs["neoslam"]
    gt = read_tum(out / "groundtruth.tum") if (out / "groundtruth.tum").exists() else None
    if gt is not None:
        ax.plot(gt[:, 1], gt[:, 2], "k-", lw=1.5, label="ground truth")
    for name, colour in (("neoslam", "b"), ("ratslam", "m")):
        f = dirs[name] / "trajectory.tum"
        if not f.exists():
            continue
        tr = read_tum(f)
        xy = tr[:, 1:3]
        if gt is not None:
            ie, ig = associate(tr[:, 0], gt[:, 0])
            R, t = umeyama_se2(xy[ie], gt[ig, 1:3])
            xy = xy @ R.T + t
        ax.plot(xy[:, 0], xy[:, 1], f"{colour}-", lw=0.8, label=name)
    ax.set_aspect("equal")
    ax.legend()
    fig.savefig(out / "compare.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
