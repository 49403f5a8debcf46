"""Commands on configs, maps, run folders and data sets: ``config``, ``map``, ``evaluate``,
``dataset synthetic``, and ``compare`` (three pipelines on one stream, then one table)."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import group
from .report import error, print_compare, print_evaluation, print_summary
from .run import add_run_options, load_run_config

RADIUS_HELP = "a closure is correct when its matched place is within this true distance (m; default 1.0)"


def register(sub: argparse._SubParsersAction) -> None:
    csub = group(sub, "config", "config_command", "ACTION", help="the configs that ship with neoslam",
                 description="List the shipped configs (`-c NAME` uses one) or print one, "
                             "to copy and edit: neoslam config show default > my.yaml")
    csub.add_parser("list", help="names of the shipped configs").set_defaults(func=cmd_config_list)
    p = csub.add_parser("show", help="print a shipped config's YAML, or a config file on top of its base",
                        description="A shipped config's YAML as it ships; a config file of your own merged "
                                    "onto its base (the shipped default unless it names another), as the run reads it.")
    p.add_argument("name", help="a shipped config's name, or a YAML file")
    p.set_defaults(func=cmd_config_show)

    msub = group(sub, "map", "map_command", "ACTION", help="export / inspect maps for long-term deployment",
                 description="A map is every stage's learned state (templates, TM connections, "
                             "intervals, pose cells, experience map) in one file; "
                             "`neoslam run --map FILE` starts a new session on it.")
    p = msub.add_parser("export", help="pack a finished (or checkpointed) run's state into a map file")
    p.add_argument("run_dir")
    p.add_argument("--out", help="map file (default RUN_DIR/map.neoslam)")
    p.set_defaults(func=cmd_map_export)
    p = msub.add_parser("info", help="what a map file holds")
    p.add_argument("map_file")
    p.set_defaults(func=cmd_map_info)

    p = sub.add_parser("evaluate", help="trajectory / map error of a run folder against ground truth",
                       description="Recompute evaluation.json and map.png of a run folder.")
    p.add_argument("run_dir")
    p.add_argument("--gt", help="ground truth TUM file (default: RUN_DIR/groundtruth.tum)")
    p.add_argument("--radius", type=float, default=1.0, help=RADIUS_HELP)
    shift = p.add_mutually_exclusive_group()
    shift.add_argument("--gt-offset", type=float, default=0.0, metavar="SECONDS",
                       help="add SECONDS to the ground truth's stamps (a ground truth on another clock)")
    shift.add_argument("--gt-align-start", action="store_true",
                       help="shift the ground truth's stamps so its first stamp is the run's first")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("dataset", help="write data sets", description="Write data sets to disk.")
    dsub = p.add_subparsers(dest="dataset", metavar="KIND")  # alone: neoslam's help, exit 2
    p = dsub.add_parser("synthetic", help="the synthetic world as PNG images + TUM files",
                        description="Render the synthetic world to DIR/images/*.png with groundtruth.tum "
                                    "and odometry.tum.")
    p.add_argument("--out", required=True)
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: the whole route)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--laps-cw", type=int, default=None, help="laps one way (default 2)")
    p.add_argument("--laps-ccw", type=int, default=None, help="laps the other way afterwards (default 1)")
    p.add_argument("--width", type=int, default=None, help="image width (default 416)")
    p.add_argument("--height", type=int, default=None, help="image height (default 240)")
    p.set_defaults(func=cmd_dataset_synthetic)

    p = sub.add_parser("compare", help="NeoSLAM (default and paper profile) and RatSLAM on the same stream",
                       description="Run NeoSLAM with the config, NeoSLAM with the paper's profile (configs/paper.yaml; "
                                   "stages with the same parameters are shared) and the RatSLAM baseline (local-view "
                                   "cells) in one run, the image topic fanned out to all; print one table and write "
                                   "compare.json and compare.png (the paper profile's files in OUT/paper/, "
                                   "RatSLAM's in OUT/ratslam/).")
    add_run_options(p)
    p.add_argument("--radius", type=float, default=1.0, help=RADIUS_HELP)
    p.set_defaults(func=cmd_compare)


def cmd_config_list(args: argparse.Namespace) -> int:
    from ..config import packaged_configs

    for name in packaged_configs():
        print(name)
    return 0


def cmd_config_show(args: argparse.Namespace) -> int:
    import yaml

    from ..config import ConfigError, config_data, load_config, packaged_config_text, packaged_configs

    try:
        if args.name in packaged_configs() and not Path(args.name).is_file():
            print(packaged_config_text(args.name), end="")
            return 0
        data, origin = config_data(args.name)
        load_config(args.name)  # a bad value: one line naming the field, as `neoslam run` would
    except ConfigError as exc:
        return error(exc, 2)
    print(f"# {origin}: merged, complete on its own")
    print(yaml.safe_dump({"base": "none", **data}, sort_keys=False), end="")
    return 0


def cmd_map_export(args: argparse.Namespace) -> int:
    from ..runtime.checkpoint import export_map

    out = Path(args.out) if args.out else Path(args.run_dir) / "map.neoslam"
    try:
        meta = export_map(args.run_dir, out)
    except (FileNotFoundError, ValueError) as exc:
        return error(exc, 1)
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MB): stages {', '.join(meta['stages'])} "
          f"from {meta['from_states']}")
    return 0


def cmd_map_info(args: argparse.Namespace) -> int:
    from ..runtime.checkpoint import load_map_file

    try:
        data = load_map_file(args.map_file)
    except (OSError, ValueError) as exc:
        return error(exc, 1)
    print(f"{args.map_file}: {data['format']} v{data['version']}, pipeline {data.get('pipeline')}, "
          f"{data.get('frames')} frames, from {data.get('from_run')}")
    for name, state in sorted(data["stages"].items()):
        print(f"  {name}: {', '.join(sorted(state))}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..evaluation import StampMismatch, evaluate_run

    try:
        ev = evaluate_run(args.run_dir, args.gt, radius=args.radius, gt_offset=args.gt_offset,
                          gt_align_start=args.gt_align_start)
    except (FileNotFoundError, StampMismatch) as exc:
        return error(exc, 2)
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
        return error(exc, 2)
    gt, odo = [], []
    for sf in src:
        cv2.imwrite(str(out / "images" / f"{sf.frame:06d}.png"), sf.image[:, :, ::-1])
        gt.append((sf.stamp, *sf.groundtruth))
        odo.append(sf.odom)
    write_tum(out / "groundtruth.tum", gt)
    write_tum(out / "odometry.tum", integrate_odometry([g[0] for g in gt], odo))
    print(f"wrote {len(gt)} frames, groundtruth.tum and odometry.tum to {out}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """NeoSLAM (the config and the paper's profile) and RatSLAM on the same stream in one run, then
    one table and one figure."""
    from ..evaluation.compare import compare_runs
    from ..launch import RunError, run

    cfg = load_run_config(args, {"run.pipeline": "compare"})
    out = Path(args.out or "runs/compare")
    try:
        res = run(cfg, out)
    except RunError as exc:
        return error(exc, 1)
    print_summary(res.report)
    table = compare_runs(out, res.report, radius=args.radius)
    print_compare(table, args.radius)
    rr = [f"{row['label']} {row['loop_re_recognitions']}" for row in table.values()
          if row.get("loop_re_recognitions") is not None and not row.get("same_as_default")]
    if rr:  # the matches the closures leave out (docs/evaluation.md, "Loop closures and re-recognitions")
        print(f"re-recognitions of a place just passed (not loop closures): {', '.join(rr)}")
    print(f"compare.json, compare.png and compare_pr.png in {out}")
    return 0
