"""``neoslam run`` and what watches or links runs: ``view``, ``monitor``, ``router``.

The run options are config flags (flags.py): each names the config value it sets, and the
config file with those values on top is validated as one."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..config import FullRunConfig
from .flags import ConfigFlags
from .report import error, platform_lines, print_evaluation, print_summary

#: what `neoslam run` runs with no --config
DEFAULT_CONFIG = "default"
#: where --foxglove serves when it names no address: this machine only
FOXGLOVE_DEFAULT = "127.0.0.1:8765"


def _source_params(pairs: list[str]) -> dict[str, Any]:
    """``-p KEY=VALUE`` pairs; a value is JSON when it parses as JSON, else the text."""
    params = {}
    for kv in pairs:
        k, _, v = kv.partition("=")
        try:
            params[k] = json.loads(v)
        except json.JSONDecodeError:
            params[k] = v
    return params


def _stages(text: str) -> list[str]:
    from ..runtime.share import parse_stages

    return parse_stages(text)


def add_run_options(p: argparse.ArgumentParser) -> ConfigFlags:
    """The options of every command that runs a pipeline (run, compare)."""
    p.add_argument("--config", "-c", help=f"YAML config file, or the name of a shipped config: default, paper datasets... "
                        f"(`neoslam config list`; default: {DEFAULT_CONFIG})")
    flags = ConfigFlags(p)
    flags.add("--source", path="source.kind",
              help="source kind (synthetic, folder, video, camera, bag, zenoh-ros2, zenoh, rmw-zenoh, "
                   "emulated)")
    flags.add("--source-param", "-p", path="source.params", convert=_source_params, action="append",
              metavar="KEY=VALUE",
              help="source parameter, e.g. -p path=data/run1 (repeatable; values parsed as JSON)")
    flags.add("--topology", path="run.topology", help="one process per stage, or one")
    mode = p.add_mutually_exclusive_group()
    flags.add("--lossless", path="run.mode", sets="lossless", dest="mode", to=mode,
              help="process every frame; the source is back-pressured (default for recorded data)")
    flags.add("--realtime", path="run.mode", sets="realtime", dest="mode", to=mode,
              help="bounded drop-oldest queues; a slow stage never blocks its upstream")
    flags.add("--rate", path="source.rate", also={"source.pacing": "fixed"},
              help="publish frames at this fixed rate (Hz)")
    flags.add("--rate-multiplier", path="source.rate_multiplier", also={"source.pacing": "recorded"},
              help="replay recorded timing sped up by this factor")
    flags.add("--max-frames", path="source.max_frames", help="stop after this many frames")
    flags.add("--duration", path="source.duration", help="stop after this many seconds")
    p.add_argument("--out", help="run folder (default: runs/<name>)")
    flags.add("--no-live", path="run.live", sets=False, help="no live table / progress bar")
    return flags


def load_run_config(args: argparse.Namespace, fixed: dict[str, Any] | None = None) -> Any:
    """The config of ``--config`` with the flags given on top (and ``fixed``: dotted paths), as it
    will run (``launch.prepare``: the source's parameters checked, the odometry rule applied); a bad
    value ends the command with one line naming the field or parameter (exit 2) before anything
    starts. Prints what the run assumes: the platform, and visual odometry where the source gives
    no odometry."""
    from ..config import load_config
    from ..launch import prepare

    try:
        cfg, notes = prepare(load_config(args.config or DEFAULT_CONFIG, args.config_flags.overrides(args, fixed)))
    except ValueError as exc:  # ConfigError, SourceParamError
        raise SystemExit(error(exc, 2)) from None
    if cfg.run.pipeline != "emulated":
        for line in [*platform_lines(cfg), *notes]:
            print(line, flush=True)
    return cfg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run a pipeline (default: NeoSLAM on the synthetic world)",
                       description="Run a pipeline to the end of its source; writes report.json, "
                                   "timeline.csv and the stage outputs into the run folder.")
    flags = add_run_options(p)
    flags.add("--checkpoint-every", path="run.checkpoint_every",
              help="save every stage's state every N frames")
    flags.add("--trace", path="run.trace", metavar="FILE",
              help="write every frame's path through the stages (received, started, finished per stage "
                   "and process) to FILE as a Chrome / Perfetto trace: open it in ui.perfetto.dev")
    p.add_argument("--resume", metavar="RUN_DIR", help="resume from the last checkpoint of RUN_DIR")
    p.add_argument("--map", metavar="MAP_FILE", help="start from a map exported by `neoslam map export` "
                   "(long-term deployment)")
    flags.add("--pipeline", path="run.pipeline", help="pipeline name (neoslam, ratslam, oracle, emulated)")
    flags.add("--oracle-templates", path="run.pipeline", sets="oracle",
              help="template ids from ground truth instead of the front end (A-D): the back end's "
                   "best map (the `oracle` pipeline; docs/end_to_end.md)")
    flags.add("--oracle-radius", path="oracle.radius_m", metavar="M",
              help="the oracle's template radius in metres (default: exp_delta_pc_threshold x "
                   "pc_cell_x_size, the experience spacing)")
    flags.add("--oracle-heading-tolerance", path="oracle.heading_tolerance_deg", metavar="DEG",
              help="the oracle matches a template only within this heading difference (default 45; "
                   "180 ignores the heading: closures a forward camera cannot make)")
    flags.add("--ros2-out", path="ros2_out.format", nargs="?", const="bridge",
              help="publish the outputs as ROS 2 messages: keys of zenoh-bridge-ros2dds (default), "
                   "of rmw_zenoh, or both (docs/ros2.md)")
    flags.add("--ros2-connect", path="ros2_out.connect", metavar="ENDPOINT",
              help="zenoh endpoint of the ROS 2 side's router, e.g. tcp/localhost:7447 (repeatable)")
    flags.add("--stages", path="run.stages", convert=_stages, metavar="A,B|rest",
              help="run only these stages here (the rest on other hosts, same --run-id), "
                   "or 'rest': those no other host runs")
    flags.add("--run-id", path="run.run_id",
              help="the run's id (key expressions neoslam/<id>/...), shared by its hosts")
    flags.add("--connect", path="bus.connect", metavar="ENDPOINT",
              help="zenoh endpoint (a router) linking this run to other hosts, e.g. "
                   "tcp/10.0.0.2:7447 (repeatable; bus.connect)")
    flags.add("--router-listen", path="bus.router_listen", metavar="ENDPOINT",
              help="the supervisor's router also listens here, for the other hosts of the run "
                   "(repeatable; bus.router_listen)")
    p.add_argument("--view", action="store_true",
                   help="show the run live in a rerun viewer (recorded to RUN_DIR/view.rrd)")
    flags.add("--foxglove", path="foxglove.listen", nargs="?", const=FOXGLOVE_DEFAULT, metavar="HOST:PORT",
              help=f"serve the run live to Foxglove / Lichtblick over the Foxglove WebSocket protocol on "
                   f"HOST:PORT (default {FOXGLOVE_DEFAULT}: this machine only; docs/foxglove.md)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("view", help="show a run (live or finished) in a rerun viewer",
                       description="Camera frame, template ids and loop closures, the experience "
                                   "map with ground truth and odometry, and each stage's rate, "
                                   "recorded to a rerun file (RUN_DIR/view.rrd unless --save). "
                                   "Attaches to a running run; shows a finished run's files.")
    p.add_argument("run_dir", help="run folder (a running run's has endpoints.json)")
    p.add_argument("--save", metavar="FILE", help="record to FILE (.rrd) without opening a window")
    p.add_argument("--no-window", action="store_true", help="record to RUN_DIR/view.rrd only")
    p.add_argument("--duration", type=float, help="stop watching a live run after this many seconds")
    p.add_argument("--wait", type=float, default=0.0,
                   help="wait this many seconds for the run to start (endpoints.json)")
    p.add_argument("--foxglove", nargs="?", const=FOXGLOVE_DEFAULT, metavar="HOST:PORT",
                   help=f"serve the run to Foxglove / Lichtblick instead (Foxglove WebSocket protocol, default "
                        f"{FOXGLOVE_DEFAULT}): live while it runs, else its files played again once a "
                        f"client subscribed, then kept until Ctrl-C or --duration (docs/foxglove.md)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="with --foxglove, a finished run plays at this many times its source time (0: at once)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("monitor", help="attach a live table to a running pipeline",
                       description="Show the live stats of a running pipeline.")
    p.add_argument("run_dir", nargs="?", help="run folder of the running pipeline (has endpoints.json)")
    p.add_argument("--run", help="run id (instead of RUN_DIR)")
    p.add_argument("--connect", action="append", help="zenoh endpoint to connect to (repeatable)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.set_defaults(func=cmd_monitor)

    p = sub.add_parser("router", help="a zenoh router linking the hosts of a split run",
                       description="A zenoh router (scouting off) that the supervisors of a run "
                                   "split over hosts connect to (neoslam run --connect).")
    p.add_argument("--listen", action="append", required=True, metavar="ENDPOINT",
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="another router (repeatable)")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="zenoh json5 file for TLS and access control (as bus.zenoh_config)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.set_defaults(func=cmd_router)


def _start_viewer(cfg: FullRunConfig, args: argparse.Namespace, *extra: str) -> tuple[Any, str]:
    """``run --view`` / ``run --foxglove``: a viewer as a child process (``neoslam view RUN_DIR
    [extra]``) that attaches as soon as the run's router is up; the run folder is fixed here so
    that both know it."""
    import subprocess

    from ..runtime.topology import make_run_dir

    _, run_dir = make_run_dir(cfg, args.out)
    return subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "view", str(run_dir),
                             "--wait", "120", *extra]), str(run_dir)


def _foxglove_served(run_dir: Path, report: dict[str, Any]) -> str:
    """What the run's Foxglove server served (foxglove.json), into report.json as ``foxglove``;
    one line for the summary."""
    from ..runtime.report import write_report
    from ..viewer import FOXGLOVE_FILE

    try:
        served = json.loads((run_dir / FOXGLOVE_FILE).read_text())
    except (OSError, ValueError):
        return "foxglove: the server wrote no foxglove.json (it did not start?)"
    report["foxglove"] = served
    write_report(run_dir / "report.json", report)
    return (f"foxglove: {served.get('url')}, {served.get('clients', 0)} clients; camera {served.get('images', 0)} "
            f"frames sent, {served.get('images_thinned', 0)} thinned, {served.get('images_dropped', 0)} dropped; "
            f"{served.get('poses', 0)} poses, {served.get('loop_closures', 0)} loop closures, "
            f"{served.get('messages_dropped', 0)} other messages dropped")


def cmd_run(args: argparse.Namespace) -> int:
    import subprocess

    from ..launch import RunError, run

    if args.oracle_templates and args.pipeline not in (None, "oracle"):
        return error(f"--oracle-templates replaces the front end of the neoslam pipeline; it cannot run "
                     f"with --pipeline {args.pipeline}", 2)
    cfg = load_run_config(args)
    if cfg.foxglove.listen:
        from ..viewer.foxglove import NEEDS, parse_listen, sdk_available

        if not sdk_available():
            return error(NEEDS, 2)
        try:
            parse_listen(cfg.foxglove.listen)
        except ValueError as exc:
            return error(exc, 2)
    viewers = []
    if args.view:
        viewer, args.out = _start_viewer(cfg, args)
        viewers.append(viewer)
    if cfg.foxglove.listen:  # the first frame waits for the server (and its first client) to attach
        cfg.run.wait_for = [*cfg.run.wait_for, "foxglove"]
        cfg.run.wait_for_s = max(cfg.run.wait_for_s, cfg.foxglove.wait_for_client_s + 30.0)
        viewer, args.out = _start_viewer(cfg, args, "--foxglove", cfg.foxglove.listen)
        viewers.append(viewer)
    try:
        result = run(cfg, args.out, args.resume, args.map)
    except BaseException as exc:
        for viewer in viewers:  # the run did not end normally: no report.json will end the viewer
            viewer.terminate()
            viewer.wait(10)
        if isinstance(exc, RunError):
            return error(exc, 1)
        raise
    for viewer in viewers:  # each ends by itself once report.json is there and the map is shown
        try:
            viewer.wait(60)
        except subprocess.TimeoutExpired:
            viewer.terminate()
    served = _foxglove_served(result.run_dir, result.report) if cfg.foxglove.listen else ""
    if "part" in result.report:  # one host's share of a split run: the report is the other host's
        here = [*result.report["part"], *(["the source"] if result.report.get("source_here") else [])]
        print(f"run {result.report['run']}: {', '.join(here)} done here "
              f"(restarts {result.report['restarts']}); the report is in the run folder of the host "
              f"with the last stage and the monitor (part.json: {result.run_dir / 'part.json'})")
        return 128 + (result.signal or 2) if result.interrupted else 0
    print_summary(result.report)
    if served:
        print(served)
    run_dir = result.run_dir
    if cfg.run.pipeline == "oracle" and not (run_dir / "groundtruth.tum").exists():
        return error("--oracle-templates needs a source with ground truth (this one published none, so "
                     "no template was made)", 1)
    if (run_dir / "groundtruth.tum").exists() and (run_dir / "trajectory.tum").exists():
        from ..evaluation import StampMismatch, evaluate_run

        try:
            print_evaluation(evaluate_run(run_dir))
        except StampMismatch as exc:  # e.g. no pose came out: the run's files say what there is
            print(f"no evaluation: {exc}")
    elif not (run_dir / "groundtruth.tum").exists():  # no judgement, but which matches were returns
        from ..evaluation import closures_by_odometry

        split = closures_by_odometry(run_dir)
        if split is not None:
            print(f"closures (no ground truth, not judged): {split['closures']} loop closures and "
                  f"{split['re_recognitions']} re-recognitions of a place just passed (left after "
                  f"{split['left_m']:g} m of travel by odometry.tum)")
    if result.interrupted:  # the shell convention: 128 + the signal (130 for Ctrl-C, 143 for SIGTERM)
        return 128 + (result.signal or 2)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from ..viewer import serve_foxglove, view

    if args.foxglove:
        import signal

        def _stop(*_: Any) -> None:  # SIGTERM ends the server as Ctrl-C does: foxglove.json says what it served
            raise KeyboardInterrupt

        signal.signal(signal.SIGTERM, _stop)
        try:
            st = serve_foxglove(args.run_dir, args.foxglove, args.speed, args.duration, args.wait)
        except (FileNotFoundError, ValueError) as exc:
            return error(exc, 2)
        except RuntimeError as exc:  # the SDK could not bind: the port is taken, the address unknown
            return error(f"cannot serve on {args.foxglove}: {exc}", 1)
        print(f"served {args.run_dir}: {st.poses} poses, {st.templates} templates ({st.loop_closures} loop "
              f"closures), {st.images} camera frames ({st.images_thinned} thinned, {st.images_dropped} dropped), "
              f"{st.log_lines} log lines, stats of {len(st.stages)} stages")
        return 0
    try:
        st = view(args.run_dir, save=args.save, window=False if (args.save or args.no_window) else None,
                  duration=args.duration, wait_s=args.wait)
    except FileNotFoundError as exc:
        return error(exc, 2)
    out = args.save or str(Path(args.run_dir) / "view.rrd")
    camera = f"{st.images} camera frames ({st.images_dropped} skipped)"
    if not st.images and not (Path(args.run_dir) / "camera.zip").exists():
        camera += " (the run folder has no camera.zip: runs keep one unless source.camera_log_s is 0)"
    print(f"viewed {args.run_dir}: {st.templates} templates ({st.loop_closures} loop closures), "
          f"{st.poses} poses, {camera}, {st.log_lines} log lines, rates of {len(st.stages)} stages; "
          f"recording: {out} (open it with `rerun {out}`)")
    return 0


def cmd_monitor(args: argparse.Namespace) -> int:
    from ..runtime.monitor import attach

    run, connect = args.run, args.connect or []
    if args.run_dir:
        ep = json.loads((Path(args.run_dir) / "endpoints.json").read_text())
        run, connect = ep["run"], ep["connect"] + connect
    if not run or not connect:
        return error("give a RUN_DIR (with endpoints.json) or --run and --connect", 2)
    attach(run, connect, duration=args.duration)
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    import os

    from ..runtime.bus import ZENOH_CONFIG_ENV
    from ..runtime.share import serve_router

    if args.zenoh_config:
        if not Path(args.zenoh_config).is_file():
            return error(f"no zenoh config file {args.zenoh_config}", 2)
        os.environ[ZENOH_CONFIG_ENV] = args.zenoh_config
    print(f"zenoh router listening on {', '.join(args.listen)} (Ctrl-C to stop)", flush=True)
    serve_router(args.listen, args.connect, args.duration)
    return 0
