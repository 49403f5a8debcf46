"""``neoslam bench throughput``: live rate sweep, paper's loss table and scaling curve."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def _rates(text: str) -> list[float]:
    try:
        rates = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rates must be numbers separated by commas, got {text!r}") from None
    if any(r <= 0 for r in rates):
        raise argparse.ArgumentTypeError("rates must be > 0")
    return rates


def _json_object(text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON ({exc}): {text!r}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"must be a JSON object such as '{{\"A\": 1}}', got {text!r}")
    return value


def cmd_bench_throughput(args: argparse.Namespace) -> int:
    from ..config import ConfigError
    from ..throughput import run_bench

    topologies = ["pipeline", "monolithic"] if args.topology == "both" else [args.topology]
    overrides: dict[str, Any] = {}
    if args.projection:
        overrides["projector"] = {"projection": args.projection}
    if args.matrix_dtype:
        overrides.setdefault("projector", {})["matrix_dtype"] = args.matrix_dtype
    if args.feature_bits:
        overrides.setdefault("projector", {})["feature_bits"] = args.feature_bits
    if args.image_capacity:
        overrides["bus"] = {"capacity": {"image": args.image_capacity}}
    if args.tx_queue:
        overrides.setdefault("bus", {})["tx_queue"] = args.tx_queue
    if args.threads:
        overrides["run"] = {"threads": args.threads}
    if args.nice:
        overrides.setdefault("run", {})["nice"] = args.nice
    if args.cpus:
        overrides.setdefault("run", {})["cpus"] = args.cpus
    if args.max_batch:
        overrides.setdefault("run", {})["max_batch"] = args.max_batch
    try:
        res = run_bench(args.config, args.rates, args.duration, topologies, Path(args.out),
                        args.backbone, args.scaling, overrides, args.scaling_step)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"stopped: {exc}; results so far are in the run folders under {args.out}/runs", file=sys.stderr)
        return 130
    if res.get("paper_table"):
        print()
        print(res["paper_table"])
        print(f"sustainable rate (< 0.1 % loss): {res['sustainable_rate']}")
    if res.get("scaling"):
        sc = res["scaling"]
        print(f"scaling: {sc['frames']} frames, loss {100 * sc['loss']:.2f} %, RSS at end {sc['rss_total_mb_end']:.0f} MB, "
              f"extrapolated to 100k frames {sc['rss_total_mb_at_100k_extrapolated'] or float('nan'):.0f} MB")
    print(f"wrote {Path(args.out) / 'throughput.json'}")
    return 0


def register(sub: argparse._SubParsersAction, bench_sub: argparse._SubParsersAction) -> None:
    del sub
    p = bench_sub.add_parser(
        "throughput", help="live runs of the real NeoSLAM pipeline at several input rates",
        description="Real-time (drop-oldest) runs of NeoSLAM (A-D + pose cells + experience map) on the "
                    "looped synthetic world at each input rate and topology -> OUT/throughput.json, "
                    "OUT/throughput.png and the paper's table (Algorithm | Processed Frames | Data Loss). "
                    "--scaling N adds a long lossless run recording tau, RSS and state sizes every 1000 "
                    "frames.")
    p.add_argument("--config", "-c", help="base config (default: default)")
    p.add_argument("--rates", type=_rates, default=[10.0, 13.0, 20.0, 30.0, 45.0, 60.0],
                   help="input rates in FPS, comma-separated (default 10,13,20,30,45,60)")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of input per run (default 60)")
    p.add_argument("--topology", choices=["pipeline", "monolithic", "both"], default="both")
    p.add_argument("--backbone", default="random_alexnet",
                   help="feature backbone (default random_alexnet: AlexNet's cost without its weights; "
                        "alexnet with weights costs the same)")
    p.add_argument("--projection", choices=["gaussian", "sparse"], help="override stage B's projection")
    p.add_argument("--matrix-dtype", choices=["float32", "float16", "int8"],
                   help="override the storage of B's Gaussian matrix (projector.matrix_dtype)")
    p.add_argument("--feature-bits", type=int, choices=[16, 7],
                   help="with --matrix-dtype int8: features rounded to 16 bits (exact numba kernel) or "
                        "7 bits (torch's quantised int8 kernels; projector.feature_bits)")
    p.add_argument("--max-batch", type=int, help="override run.max_batch (1: every stage takes one frame at a time)")
    p.add_argument("--image-capacity", type=int, help="override the image ring capacity (bus.capacity.image)")
    p.add_argument("--tx-queue", type=int, help="zenoh's transmit queue per link for data, in 64 kB batches (bus.tx_queue)")
    p.add_argument("--threads", type=_json_object, help='per-stage thread budget as JSON, e.g. \'{"A": 2}\'')
    p.add_argument("--nice", type=_json_object, help='per-process niceness as JSON (run.nice), e.g. \'{"C": 10, "monitor": 10}\'')
    p.add_argument("--cpus", type=_json_object, help='per-process CPUs as JSON (run.cpus), e.g. \'{"A": [0], "B": [1]}\'')
    p.add_argument("--scaling", type=int, metavar="FRAMES", help="also run the lossless scaling curve")
    p.add_argument("--scaling-step", type=int, default=1000, help="frames between two points of the curve")
    p.add_argument("--out", default="bench/results/throughput", help="output folder")
    p.set_defaults(func=cmd_bench_throughput)
