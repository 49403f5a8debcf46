"""Data subcommands: ``neoslam evaluate`` and ``neoslam dataset synthetic``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..evaluation import evaluate_run
    from . import print_evaluation

    try:
        ev = evaluate_run(args.run_dir, args.gt, radius=args.radius)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_evaluation(ev)
    return 0


def cmd_dataset_synthetic(args: argparse.Namespace) -> int:
    import cv2

    from ..sources.synthetic import SyntheticWorldSource
    from ..tum import integrate_odometry, write_tum

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
    for sf in src:
        cv2.imwrite(str(out / "images" / f"{sf.frame:06d}.png"), sf.image[:, :, ::-1])
        gt.append((sf.stamp, *sf.groundtruth))
        odo.append(sf.odom)
    write_tum(out / "groundtruth.tum", gt)
    write_tum(out / "odometry.tum", integrate_odometry([g[0] for g in gt], odo))
    print(f"wrote {len(gt)} frames, groundtruth.tum and odometry.tum to {out}")
    return 0


def cmd_map_export(args: argparse.Namespace) -> int:
    from ..runtime.checkpoint import export_map

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
    from ..runtime.checkpoint import load_map_file

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


def cmd_config_list(args: argparse.Namespace) -> int:
    from ..config import packaged_configs

    for name in packaged_configs():
        print(name)
    return 0


def cmd_config_show(args: argparse.Namespace) -> int:
    from ..config import ConfigError, packaged_config_text

    try:
        print(packaged_config_text(args.name), end="")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def register(sub: argparse._SubParsersAction, bench_sub: argparse._SubParsersAction) -> None:
    cf = sub.add_parser("config", help="the configs that ship with neoslam",
                        description="List the shipped configs (`-c NAME` uses one) or print one, "
                                    "to copy and edit: neoslam config show default > my.yaml")
    csub = cf.add_subparsers(dest="config_command", metavar="ACTION")
    cl = csub.add_parser("list", help="names of the shipped configs")
    cl.set_defaults(func=cmd_config_list)
    cs = csub.add_parser("show", help="print a shipped config's YAML")
    cs.add_argument("name")
    cs.set_defaults(func=cmd_config_show)
    cf.set_defaults(func=lambda a: (cf.print_help(), 2)[1])
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
    p.add_argument("--radius", type=float, default=1.0, help="a closure is correct when its matched place is within this true distance (m; default 1.0)")
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
    from . import add_run_options

    c = sub.add_parser("compare", help="NeoSLAM (default and paper profile) and RatSLAM on the same stream",
                       description="Run NeoSLAM with the config, NeoSLAM with the paper's profile (configs/paper.yaml; "
                                   "stages with the same parameters are shared) and the RatSLAM baseline (local-view "
                                   "cells) in one run, the image topic fanned out to all; print one table and write "
                                   "compare.json and compare.png (the paper profile's files in OUT/paper/, "
                                   "RatSLAM's in OUT/ratslam/).")
    add_run_options(c)
    c.add_argument("--radius", type=float, default=1.0,
                   help="a closure is correct when its matched place is within this true distance (m; default 1.0)")
    c.set_defaults(func=cmd_compare)


def cmd_compare(args: argparse.Namespace) -> int:
    """NeoSLAM (the config and the paper's profile) and RatSLAM on the same stream in one run, then
    one table and one figure."""
    from ..evaluation.compare import compare_runs
    from ..launch import RunError, run
    from . import _load, print_summary

    args.pipeline = "compare"
    cfg = _load(args)
    out = Path(args.out or "runs/compare")
    try:
        res = run(cfg, out)
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print_summary(res.report)
    table = compare_runs(out, res.report, radius=args.radius)
    _print_compare(table, args.radius)
    print(f"compare.json and compare.png in {out}")
    return 0


def _print_compare(table: dict, radius: float = 1.0) -> None:
    from rich.console import Console
    from rich.table import Table

    from ..evaluation.compare import COLUMNS

    t = Table(title=f"NeoSLAM (default, paper) vs RatSLAM, same stream; closures correct within {radius:g} m")
    t.add_column("")
    for _key, short in COLUMNS:
        t.add_column(short, justify="right")
    for name, row in table.items():
        label = row.get("label", name) + (" = default" if row.get("same_as_default") else "")
        t.add_row(label, *[("" if row.get(c) is None else f"{row[c]:.3f}" if isinstance(row.get(c), float)
                            else str(row[c])) for c, _short in COLUMNS])
    con = Console()
    con.print(t)
    lat = Table(title="per-stage latency (tau p50, ms)")
    lat.add_column("pipeline")
    lat.add_column("stages")
    for name, row in table.items():
        taus = row.get("stage_tau_p50_ms") or {}
        lat.add_row(row.get("label", name), ", ".join(f"{s}: {v:.1f}" for s, v in taus.items() if v is not None))
    con.print(lat)
