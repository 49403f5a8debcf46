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
    src = SyntheticWorldSource(frames=args.frames, seed=args.seed)
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


def register(sub: argparse._SubParsersAction, bench_sub: argparse._SubParsersAction) -> None:
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
    s.set_defaults(func=cmd_dataset_synthetic)
