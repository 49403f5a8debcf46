"""``neoslam bench emulate`` (the paper's worked example with emulated stages) and ``neoslam bench
throughput`` (live runs of the NeoSLAM pipeline at several input rates, and the scaling curve)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .flags import ConfigFlags
from .report import error, print_summary


def _rates(text: str) -> list[float]:
    try:
        rates = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rates must be numbers separated by commas, got {text!r}") from None
    if any(r <= 0 for r in rates):
        raise argparse.ArgumentTypeError("rates must be > 0")
    return rates


def _tau(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--tau must be numbers separated by commas, got {text!r}") from None


def _topologies(name: str) -> list[str]:
    return ["pipeline", "monolithic"] if name == "both" else [name]


def register(bsub: argparse._SubParsersAction) -> None:
    p = bsub.add_parser("emulate", help="the paper's worked example with emulated stages",
                        description="Stages with fixed service times through real zenoh processes.")
    flags = ConfigFlags(p)
    flags.add("--tau", path="emulated.tau_ms", convert=_tau, default="50,280,20,350",
              help="service times in ms, comma-separated")
    flags.add("--rate", path="source.rate", default=10.0, help="input rate (Hz)")
    flags.add("--duration", path="source.duration", default=30.0, help="seconds of input")
    p.add_argument("--topology", choices=["pipeline", "monolithic", "both"], default="both")
    flags.add("--busy", path="emulated.busy", sets=True,
              help="spin instead of sleeping (CPU-bound emulation)")
    p.add_argument("--out", default="bench/results/emulate", help="output folder")
    flags.add("--no-live", path="run.live", sets=False, help="no live table")
    p.set_defaults(func=cmd_bench_emulate)

    p = bsub.add_parser(
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
    p.add_argument("--backbone", default=None,
                   help="feature backbone (default: the config's, as a user runs it; random_alexnet: "
                        "AlexNet's cost without its weights, the paper's comparison; alexnet with "
                        "weights costs the same)")
    flags = ConfigFlags(p)
    flags.add("--projection", path="projector.projection", help="override stage B's projection")
    flags.add("--matrix-dtype", path="projector.matrix_dtype",
              help="override the storage of B's Gaussian matrix (projector.matrix_dtype)")
    flags.add("--feature-bits", path="projector.feature_bits",
              help="with --matrix-dtype int8: features rounded to 16 bits (exact numba kernel) or "
                   "7 bits (torch's quantised int8 kernels; projector.feature_bits)")
    flags.add("--max-batch", path="run.max_batch",
              help="override run.max_batch (1: every stage takes one frame at a time)")
    flags.add("--image-capacity", path="bus.capacity.image",
              help="override the image ring capacity (bus.capacity.image)")
    flags.add("--tx-queue", path="bus.tx_queue",
              help="zenoh's transmit queue per link for data, in 64 kB batches (bus.tx_queue)")
    flags.add("--threads", path="run.threads", help='per-stage thread budget as JSON, e.g. \'{"A": 2}\'')
    flags.add("--batch-wait", path="run.batch_wait_ms",
              help='per-stage ms a batchable stage may wait for a second frame, as JSON (run.batch_wait_ms), '
                   'e.g. \'{"B": 20}\'')
    flags.add("--nice", path="run.nice",
              help='per-process niceness as JSON (run.nice), e.g. \'{"C": 10, "monitor": 10}\'')
    flags.add("--cpus", path="run.cpus",
              help='per-process CPUs as JSON (run.cpus), e.g. \'{"A": [0], "B": [1]}\'')
    p.add_argument("--scaling", type=int, metavar="FRAMES", help="also run the lossless scaling curve")
    p.add_argument("--scaling-step", type=int, default=1000, help="frames between two points of the curve")
    p.add_argument("--out", default="bench/results/throughput", help="output folder")
    p.set_defaults(func=cmd_bench_throughput)


def cmd_bench_emulate(args: argparse.Namespace) -> int:
    from ..config import ConfigError, load_config
    from ..launch import run

    topologies = _topologies(args.topology)
    out = Path(args.out)
    results = []
    for topo in topologies:
        try:
            cfg = load_config(None, args.config_flags.overrides(args, {
                "run.pipeline": "emulated", "run.topology": topo, "run.mode": "realtime", "run.drain_s": 0.0,
                "run.name": f"emulate-{topo}", "source.kind": "emulated", "source.params": {"frames": None},
                "source.pacing": "fixed",
                # the worked example: a busy stage keeps only the newest frame
                "bus.capacity": {"image": 1}}))
        except ConfigError as exc:
            return error(exc, 2)
        res = run(cfg, out if len(topologies) == 1 else out / topo)
        print_summary(res.report)
        results.append(res.report)
    if len(results) > 1:
        (out / "report.json").write_text(json.dumps({"runs": results}, indent=2))
    return 0


def cmd_bench_throughput(args: argparse.Namespace) -> int:
    from ..config import ConfigError
    from ..throughput import run_bench

    try:
        res = run_bench(args.config, args.rates, args.duration, _topologies(args.topology), Path(args.out),
                        args.backbone, args.scaling, args.config_flags.overrides(args), args.scaling_step)
    except ConfigError as exc:
        return error(exc, 2)
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
