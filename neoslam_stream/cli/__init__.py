"""``neoslam`` command line: run, monitor, bench emulate; ``cli.data`` adds compare, evaluate,
dataset and map, ``cli.bench`` the throughput bench. Thin: each command parses, calls the library
(launch, evaluation, throughput) and prints."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

#: what `neoslam run` runs with no --config
DEFAULT_CONFIG = "default"


def _overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    over: dict[str, Any] = {"run": {}, "source": {}}
    if getattr(args, "topology", None):
        over["run"]["topology"] = args.topology
    if getattr(args, "mode", None):
        over["run"]["mode"] = args.mode
    if getattr(args, "pipeline", None):
        over["run"]["pipeline"] = args.pipeline
    if getattr(args, "oracle_templates", False):
        over["run"]["pipeline"] = "oracle"
    if getattr(args, "oracle_radius", None) is not None:
        over.setdefault("oracle", {})["radius_m"] = args.oracle_radius
    if getattr(args, "oracle_heading_tolerance", None) is not None:
        over.setdefault("oracle", {})["heading_tolerance_deg"] = args.oracle_heading_tolerance
    if getattr(args, "no_live", False):
        over["run"]["live"] = False
    if getattr(args, "checkpoint_every", None):
        over["run"]["checkpoint_every"] = args.checkpoint_every
    if getattr(args, "ros2_out", None) or getattr(args, "ros2_connect", None):
        over["ros2_out"] = {}
        if getattr(args, "ros2_out", None):
            over["ros2_out"]["format"] = args.ros2_out
        if getattr(args, "ros2_connect", None):
            over["ros2_out"]["connect"] = list(args.ros2_connect)
    if getattr(args, "stages", None):
        from ..runtime.parts import parse_stages

        try:
            over["run"]["stages"] = parse_stages(args.stages)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
    if getattr(args, "run_id", None):
        over["run"]["run_id"] = args.run_id
    bus: dict[str, Any] = {}
    if getattr(args, "connect", None):
        bus["connect"] = list(args.connect)
    if getattr(args, "router_listen", None):
        bus["router_listen"] = list(args.router_listen)
    if bus:
        over["bus"] = bus
    if getattr(args, "source", None):
        over["source"]["kind"] = args.source
    if getattr(args, "source_param", None):
        params = {}
        for kv in args.source_param:
            k, _, v = kv.partition("=")
            try:
                params[k] = json.loads(v)
            except json.JSONDecodeError:
                params[k] = v
        over["source"]["params"] = params
    if getattr(args, "rate", None):
        over["source"]["rate"] = args.rate
        over["source"]["pacing"] = "fixed"
    if getattr(args, "rate_multiplier", None):
        over["source"]["rate_multiplier"] = args.rate_multiplier
        over["source"]["pacing"] = "recorded"
    if getattr(args, "max_frames", None):
        over["source"]["max_frames"] = args.max_frames
    if getattr(args, "duration", None):
        over["source"]["duration"] = args.duration
    return {k: v for k, v in over.items() if v}


def _load(args: argparse.Namespace) -> Any:
    from ..config import ConfigError, load_config

    try:
        return load_config(args.config or DEFAULT_CONFIG, _overrides_from_args(args))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", help=f"YAML config file, or the name of a shipped config: default, paper datasets... "
                        f"(`neoslam config list`; default: {DEFAULT_CONFIG})")
    p.add_argument("--source", help="source kind (synthetic, folder, video, bag, zenoh-ros2, zenoh, emulated)")
    p.add_argument("--source-param", "-p", action="append", metavar="KEY=VALUE",
                   help="source parameter, e.g. -p path=data/run1 (repeatable; values parsed as JSON)")
    p.add_argument("--topology", choices=["pipeline", "monolithic"], help="one process per stage, or one")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lossless", dest="mode", action="store_const", const="lossless",
                      help="process every frame; the source is back-pressured (default for recorded data)")
    mode.add_argument("--realtime", dest="mode", action="store_const", const="realtime",
                      help="bounded drop-oldest queues; a slow stage never blocks its upstream")
    p.add_argument("--rate", type=float, help="publish frames at this fixed rate (Hz)")
    p.add_argument("--rate-multiplier", type=float, help="replay recorded timing sped up by this factor")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--out", help="run folder (default: runs/<name>)")
    p.add_argument("--no-live", action="store_true", help="no live table / progress bar")


def _start_viewer(cfg: Any, args: argparse.Namespace) -> tuple[Any, str]:
    """``run --view``: the viewer as a child process (``neoslam view RUN_DIR``) that attaches as
    soon as the run's router is up; the run folder is fixed here so that both know it."""
    import subprocess

    from ..runtime.topology import make_run_dir

    _, run_dir = make_run_dir(cfg, args.out)
    return subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "view", str(run_dir),
                             "--wait", "120"]), str(run_dir)


def cmd_run(args: argparse.Namespace) -> int:
    import subprocess

    from ..launch import RunError, run

    if getattr(args, "oracle_templates", False) and getattr(args, "pipeline", None) not in (None, "oracle"):
        print(f"error: --oracle-templates replaces the front end of the neoslam pipeline; it cannot run "
              f"with --pipeline {args.pipeline}", file=sys.stderr)
        return 2
    cfg = _load(args)
    viewer = None
    if getattr(args, "view", False):
        viewer, args.out = _start_viewer(cfg, args)
    try:
        result = run(cfg, args.out, getattr(args, "resume", None), getattr(args, "map", None))
    except BaseException as exc:
        if viewer is not None:  # the run did not end normally: no report.json will end the viewer
            viewer.terminate()
            viewer.wait(10)
        if isinstance(exc, RunError):
            print(f"error: {exc}", file=sys.stderr)
            return 1
        raise
    if viewer is not None:  # it ends by itself once report.json is there and the map is logged
        try:
            viewer.wait(60)
        except subprocess.TimeoutExpired:
            viewer.terminate()
    if "part" in result.report:  # one host's share of a split run: the report is the other host's
        print(f"run {result.report['run']}: stages {', '.join(result.report['part'])} done here "
              f"(restarts {result.report['restarts']}); the report is in the run folder of the host "
              f"with the source (part.json: {result.run_dir / 'part.json'})")
        return 128 + (result.signal or 2) if result.interrupted else 0
    print_summary(result.report)
    run_dir = result.run_dir
    if cfg.run.pipeline == "oracle" and not (run_dir / "groundtruth.tum").exists():
        print("error: --oracle-templates needs a source with ground truth (this one published none, so "
              "no template was made)", file=sys.stderr)
        return 1
    if (run_dir / "groundtruth.tum").exists() and (run_dir / "trajectory.tum").exists():
        from ..evaluation import evaluate_run

        ev = evaluate_run(run_dir)
        print_evaluation(ev)
    if result.interrupted:  # the shell convention: 128 + the signal (130 for Ctrl-C, 143 for SIGTERM)
        return 128 + (result.signal or 2)
    return 0


def print_evaluation(ev: dict[str, Any]) -> None:
    from ..evaluation import closures_line

    t, o = ev.get("trajectory_ape", {}), ev.get("odometry_ape", {})
    m = ev.get("map_paper", {})
    print(f"trajectory APE mean {t.get('mean_m', float('nan')):.3f} m (max {t.get('max_m', float('nan')):.3f}); "
          f"odometry APE mean {o.get('mean_m', float('nan')):.3f} m; "
          f"map nodes {ev.get('map_nodes', 0)}, paper metric mean {m.get('mean_m', float('nan')):.3f} m")
    if "map_trajectory_ape" in ev:
        print(f"trajectory on the final map (trajectory_map.tum) APE mean {ev['map_trajectory_ape']['mean_m']:.3f} m "
              f"(max {ev['map_trajectory_ape']['max_m']:.3f})")
    if "loop_closures" in ev:
        print(closures_line(ev["loop_closures"]))
    print("evaluation.json and map.png written")


def print_summary(report: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    t = Table(title=f"run {report.get('run')} ({report.get('topology')}, {report.get('mode')})")
    for col in ("stage", "processed", "tau p50 ms", "tau p95 ms", "dropped", "errors"):
        t.add_column(col, justify="right" if col != "stage" else "left")
    for name, st in report.get("stages", {}).items():
        if st.get("missing"):
            t.add_row(name, "missing", "", "", "", "")
            continue
        t.add_row(name, str(st["processed"]), f"{st['tau_p50_ms']:.1f}", f"{st['tau_p95_ms']:.1f}",
                  str(st["dropped"]), str(st["errors"]))
    con.print(t)
    fp = report.get("f_pipeline_predicted")
    loss = report.get("loss")
    # a loss that was not measured is said so: never a 0 that nobody counted
    loss_text = "loss unknown" if loss is None else (
        f"loss {100 * loss:.1f} % ({report.get('frames_lost', '?')} of {report.get('frames_expected', '?')} frames)")
    con.print(f"frames in {report.get('frames_in')}, out {report.get('frames_out')} "
              f"(strided {report.get('frames_strided')}), {loss_text}, "
              f"f_in {report.get('f_in', 0):.2f} Hz, f_out {report.get('f_out', 0):.2f} Hz, "
              f"f_pipeline {fp if fp is None else round(fp, 2)} Hz (bottleneck {report.get('bottleneck')})")
    causes = _loss_causes(report.get("loss_breakdown"))
    if causes:
        con.print(f"loss by cause: {causes}")
    src = report.get("source") or {}
    if src.get("lost_before_source"):  # a live ROS 2 camera's gaps in its sequence numbers
        con.print(f"lost before the source: {src['lost_before_source']} frames (publishers' sequence numbers)")
    con.print(f"run folder: {report.get('run_dir')}")


def _loss_causes(breakdown: dict[str, Any] | None) -> str:
    """One line of report.json's ``loss_breakdown``: the source's losses, each stage's refused /
    dropped messages, and what no counter explains."""
    if not breakdown:
        return ""
    parts = [f"source: {cause} {n}" for cause, n in (breakdown.get("source") or {}).items() if n]
    for stage, b in (breakdown.get("stages") or {}).items():
        parts += [f"{stage} {what.replace('_', ' ')} {n}" for what, n in b.items() if n]
    if breakdown.get("unattributed"):
        parts.append(f"in flight or lost while restarting {breakdown['unattributed']}")
    return "; ".join(parts)


def cmd_monitor(args: argparse.Namespace) -> int:
    from ..runtime.monitor import attach

    run, connect = args.run, args.connect or []
    if args.run_dir:
        ep = json.loads((Path(args.run_dir) / "endpoints.json").read_text())
        run, connect = ep["run"], ep["connect"] + connect
    if not run or not connect:
        print("error: give a RUN_DIR (with endpoints.json) or --run and --connect", file=sys.stderr)
        return 2
    attach(run, connect, duration=args.duration)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from ..viewer import view

    try:
        st = view(args.run_dir, save=args.save, window=False if (args.save or args.no_window) else None,
                  duration=args.duration, wait_s=args.wait)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = args.save or str(Path(args.run_dir) / "view.rrd")
    print(f"viewed {args.run_dir}: {st.templates} templates ({st.loop_closures} loop closures), "
          f"{st.poses} poses, {st.images} camera frames ({st.images_dropped} skipped), "
          f"rates of {len(st.stages)} stages; recording: {out} (open it with `rerun {out}`)")
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    import os

    from ..runtime.bus import ZENOH_CONFIG_ENV
    from ..runtime.parts import serve_router

    if args.zenoh_config:
        if not Path(args.zenoh_config).is_file():
            print(f"error: no zenoh config file {args.zenoh_config}", file=sys.stderr)
            return 2
        os.environ[ZENOH_CONFIG_ENV] = args.zenoh_config
    print(f"zenoh router listening on {', '.join(args.listen)} (Ctrl-C to stop)", flush=True)
    serve_router(args.listen, args.connect, args.duration)
    return 0


def cmd_bench_emulate(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..launch import run

    taus = [float(x) for x in args.tau.split(",") if x.strip()]
    topologies = ["pipeline", "monolithic"] if args.topology == "both" else [args.topology]
    out = Path(args.out)
    results = []
    for topo in topologies:
        cfg = load_config(None, {
            "run": {"pipeline": "emulated", "topology": topo, "mode": "realtime", "live": not args.no_live,
                    "drain_s": 0.0, "name": f"emulate-{topo}"},
            "source": {"kind": "emulated", "params": {"frames": None}, "rate": args.rate,
                       "pacing": "fixed", "duration": args.duration},
            "emulated": {"tau_ms": taus, "busy": args.busy},
            # the worked example: a busy stage keeps only the newest frame
            "bus": {"capacity": {"image": 1}}})
        run_dir = out if len(topologies) == 1 else out / topo
        res = run(cfg, run_dir)
        print_summary(res.report)
        results.append(res.report)
    if len(results) > 1:
        (out / "report.json").write_text(json.dumps({"runs": results}, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="neoslam", description="NeoSLAM / RatSLAM as a multiprocess zenoh pipeline.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  neoslam run                        # full NeoSLAM on the synthetic world\n"
               "  neoslam run -c irat2011 -p path=data/irat_aus_28112011.bag\n"
               "  neoslam bench emulate --tau 50,280,20,350 --rate 10 --duration 30 --topology both --out bench/results/emulate")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p_run = sub.add_parser("run", help="run a pipeline (default: NeoSLAM on the synthetic world)",
                           description="Run a pipeline to the end of its source; writes report.json, "
                                       "timeline.csv and the stage outputs into the run folder.")
    add_run_options(p_run)
    p_run.add_argument("--checkpoint-every", type=int, help="save every stage's state every N frames")
    p_run.add_argument("--resume", metavar="RUN_DIR", help="resume from the last checkpoint of RUN_DIR")
    p_run.add_argument("--map", metavar="MAP_FILE",
                       help="start from a map exported by `neoslam map export` (long-term deployment)")
    p_run.add_argument("--pipeline", help="pipeline name (neoslam, ratslam, oracle, emulated)")
    p_run.add_argument("--oracle-templates", action="store_true",
                       help="template ids from ground truth instead of the front end (A-D): the back end's "
                            "best map (the `oracle` pipeline; docs/evaluation.md)")
    p_run.add_argument("--oracle-radius", type=float, metavar="M",
                       help="the oracle's template radius in metres (default: exp_delta_pc_threshold x "
                            "pc_cell_x_size, the experience spacing)")
    p_run.add_argument("--oracle-heading-tolerance", type=float, metavar="DEG",
                       help="the oracle matches a template only within this heading difference (default 45; "
                            "180 ignores the heading: closures a forward camera cannot make)")
    p_run.add_argument("--ros2-out", nargs="?", const="bridge", choices=["bridge", "rmw", "both"],
                       help="publish the outputs as ROS 2 messages: keys of zenoh-bridge-ros2dds (default), "
                            "of rmw_zenoh, or both (docs/ros2.md)")
    p_run.add_argument("--ros2-connect", action="append", metavar="ENDPOINT",
                       help="zenoh endpoint of the ROS 2 side's router, e.g. tcp/localhost:7447 (repeatable)")
    p_run.add_argument("--stages", metavar="A,B|rest",
                       help="run only these stages here (the rest on other hosts, same --run-id), "
                            "or 'rest': those no other host runs")
    p_run.add_argument("--run-id", help="the run's id (key expressions neoslam/<id>/...), shared by its hosts")
    p_run.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="zenoh endpoint (a router) linking this run to other hosts, e.g. "
                            "tcp/10.0.0.2:7447 (repeatable; bus.connect)")
    p_run.add_argument("--router-listen", action="append", metavar="ENDPOINT",
                       help="the supervisor's router also listens here, for the other hosts of the run "
                            "(repeatable; bus.router_listen)")
    p_run.add_argument("--view", action="store_true",
                       help="show the run live in a rerun viewer (recorded to RUN_DIR/view.rrd)")
    p_run.set_defaults(func=cmd_run)

    p_view = sub.add_parser("view", help="show a run (live or finished) in a rerun viewer",
                            description="Camera frame, template ids and loop closures, the experience "
                                        "map with ground truth and odometry, and each stage's rate, "
                                        "recorded to a rerun file (RUN_DIR/view.rrd unless --save). "
                                        "Attaches to a running run; shows a finished run's files.")
    p_view.add_argument("run_dir", help="run folder (a running run's has endpoints.json)")
    p_view.add_argument("--save", metavar="FILE", help="record to FILE (.rrd) without opening a window")
    p_view.add_argument("--no-window", action="store_true", help="record to RUN_DIR/view.rrd only")
    p_view.add_argument("--duration", type=float, help="stop watching a live run after this many seconds")
    p_view.add_argument("--wait", type=float, default=0.0,
                        help="wait this many seconds for the run to start (endpoints.json)")
    p_view.set_defaults(func=cmd_view)

    p_mon = sub.add_parser("monitor", help="attach a live table to a running pipeline",
                           description="Show the live stats of a running pipeline.")
    p_mon.add_argument("run_dir", nargs="?", help="run folder of the running pipeline (has endpoints.json)")
    p_mon.add_argument("--run", help="run id (instead of RUN_DIR)")
    p_mon.add_argument("--connect", action="append", help="zenoh endpoint to connect to (repeatable)")
    p_mon.add_argument("--duration", type=float, help="stop after this many seconds")
    p_mon.set_defaults(func=cmd_monitor)

    p_router = sub.add_parser("router", help="a zenoh router linking the hosts of a split run",
                              description="A zenoh router (scouting off) that the supervisors of a run "
                                          "split over hosts connect to (neoslam run --connect).")
    p_router.add_argument("--listen", action="append", required=True, metavar="ENDPOINT",
                          help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p_router.add_argument("--connect", action="append", metavar="ENDPOINT", help="another router (repeatable)")
    p_router.add_argument("--zenoh-config", metavar="FILE",
                          help="zenoh json5 file for TLS and access control (as bus.zenoh_config)")
    p_router.add_argument("--duration", type=float, help="stop after this many seconds")
    p_router.set_defaults(func=cmd_router)

    p_bench = sub.add_parser("bench", help="benchmarks", description="Benchmarks writing JSON reports.")
    bsub = p_bench.add_subparsers(dest="bench", metavar="BENCH")
    p_em = bsub.add_parser("emulate", help="the paper's worked example with emulated stages",
                           description="Stages with fixed service times through real zenoh processes.")
    p_em.add_argument("--tau", default="50,280,20,350", help="service times in ms, comma-separated")
    p_em.add_argument("--rate", type=float, default=10.0, help="input rate (Hz)")
    p_em.add_argument("--duration", type=float, default=30.0, help="seconds of input")
    p_em.add_argument("--topology", choices=["pipeline", "monolithic", "both"], default="both")
    p_em.add_argument("--busy", action="store_true", help="spin instead of sleeping (CPU-bound emulation)")
    p_em.add_argument("--out", default="bench/results/emulate", help="output folder")
    p_em.add_argument("--no-live", action="store_true", help="no live table")
    p_em.set_defaults(func=cmd_bench_emulate)
    p_bench.set_defaults(func=lambda a: (p_bench.print_help(), 2)[1])

    from . import bench, data

    data.register(sub, bsub)
    bench.register(sub, bsub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if not getattr(args, "func", None):
        if args.command is None:
            args = parser.parse_args(["run", *(argv or [])])
        else:
            parser.print_help()
            return 2
    return int(args.func(args) or 0)
