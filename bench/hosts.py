"""Two hosts and a bad link -> bench/results/hosts.json.

Each scenario is one run of the LIGHT NeoSLAM on small synthetic frames split over two network
namespaces (tests/netlab/: 'robot' runs the source, A and B; 'base' the router and the rest),
through a relay adding 50 +- 20 ms (``--delay-ms`` / ``--jitter-ms``), with one fault: a 5 s link
outage, the relay stalling for 5 s, the router killed and started again, the base's supervisor
killed and started again with ``--resume``, or one host killed for good. Per scenario: exit codes, frames in and out, the loss
by cause, the rollbacks of a lossless run, whether its outputs equal a one-host run byte for byte,
the time from the end of the fault to the next pose (recovery), the outages the report names, the
relay's delays and the end-to-end latency. Needs root (network namespaces).

Run: ``.venv/bin/python bench/hosts.py [--frames 200] [--rate 10] [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
# the two test hosts and the relay live in tests/netlab
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from netlab.netns import netem_available, netns_unavailable  # noqa: E402
from netlab.scenario import Faults, run_split, split_config  # noqa: E402

#: name -> (mode, faults, the event recovery is measured from, host_timeout); the baseline without
#: the relay's delay gives the latency the link adds
SCENARIOS = {
    "lossless_latency": ("lossless", {}, None, 30.0),
    "lossless_outage_5s": ("lossless", {"outage_at": 40}, "link up", 30.0),
    "lossless_relay_stall_5s": ("lossless", {"stall_at": 40}, "relay released", 30.0),
    "lossless_router_restart": ("lossless", {"router_restart_at": 40}, "router started", 30.0),
    "lossless_base_restart_resume": ("lossless", {"base_restart_at": 40}, "base restarted", 30.0),
    "realtime_no_added_delay": ("realtime", {"delay_ms": 0.0, "jitter_ms": 0.0}, None, 30.0),
    "realtime_latency": ("realtime", {}, None, 30.0),
    "realtime_outage_5s": ("realtime", {"outage_at": 40}, "link up", 30.0),
    "realtime_relay_stall_5s": ("realtime", {"stall_at": 40}, "relay released", 30.0),
    "realtime_router_restart": ("realtime", {"router_restart_at": 40}, "router started", 30.0),
    "realtime_base_restart_resume": ("realtime", {"base_restart_at": 40}, "base restarted", 30.0),
    "realtime_robot_dies": ("realtime", {"robot_kill_at": 40}, None, 10.0),
    "realtime_base_dies": ("realtime", {"base_kill_at": 40}, None, 10.0),
}


def one_host(cfg: dict, out: Path) -> Path:
    """The same frames through the in-process API (equal to a one-host pipeline run)."""
    from neoslam_stream import NeoSLAM, load_config
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    out.mkdir(parents=True, exist_ok=True)
    (out / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    conf = load_config(str(out / "cfg.yaml"))
    slam = NeoSLAM(conf, run_dir=out)
    for sf in SyntheticWorldSource(**conf.source.params):
        slam.step(sf.image, odometry=sf.odom, stamp=sf.stamp, frame=sf.frame)
    slam.finish()
    return out


def last_line(log: str, needle: str) -> str | None:
    lines = [ln for ln in log.splitlines() if needle in ln]
    return lines[-1].strip() if lines else None


def scenario(name: str, args: argparse.Namespace, work: Path) -> dict:
    mode, fault, since, host_timeout = SCENARIOS[name]
    cfg = split_config(mode, args.frames, args.rate, checkpoint_every=args.checkpoint_every,
                       host_timeout=host_timeout)
    faults = Faults(**{"delay_ms": args.delay_ms, "jitter_ms": args.jitter_ms, "outage_s": args.outage_s, **fault})
    t0 = time.time()
    r = run_split(work / name, cfg, faults, timeout=args.timeout)
    out: dict = {"mode": mode, "fault": fault, "robot_exit": r.robot_rc, "base_exit": r.base_rc,
                 "wall_s": round(time.time() - t0, 1),
                 "events_s": [[round(t - r.rows[0][0], 2), e] for t, e in r.events] if r.rows else [],
                 "relay": r.relay, "leftover_processes": r.leftover}
    if since is not None:
        rec = r.resumed_after(since)
        out["recovery_s"] = None if rec is None else round(rec, 2)
        out["recovery_from"] = since
    for host, log in (("robot", r.robot_log), ("base", r.base_log)):
        line = last_line(log, "error:")
        if line:
            out[f"{host}_error_line"] = line
    try:
        rep = r.report()
    except (OSError, ValueError):
        rep = {}
    out.update({k: rep.get(k) for k in ("status", "frames_in", "frames_out", "frames_lost", "loss",
                                        "loss_by_cause", "rollbacks", "latency_p50_ms", "latency_p95_ms")})
    out["outages"] = [{k: o.get(k) for k in ("seen_by", "host", "start_s", "length_s", "host_restarted")}
                      for o in rep.get("outages") or []]
    if mode == "lossless" and rep:
        ref = one_host(cfg, work / f"{name}_one_host")
        out["identical_to_one_host"] = all(
            (r.base_dir / f).exists() and filecmp.cmp(r.base_dir / f, ref / f, shallow=False)
            for f in ("templates.csv", "trajectory.tum"))
    return out


def summary(scenarios: dict) -> dict:
    """The figures of the set in a few lines (docs/hosts.md and docs/reliability.md quote them)."""
    out: dict = {}
    base, slow = scenarios.get("realtime_no_added_delay"), scenarios.get("realtime_latency")
    if base and slow and base.get("latency_p50_ms") and slow.get("latency_p50_ms"):
        out["added_latency_p50_ms"] = round(slow["latency_p50_ms"] - base["latency_p50_ms"], 1)
        out["relay_delay_mean_ms"] = round(slow["relay"].get("delay_mean_ms") or 0.0, 1)
    for name, sc in scenarios.items():
        row = {k: sc.get(k) for k in ("frames_in", "frames_out", "loss_by_cause", "recovery_s",
                                      "identical_to_one_host")}
        row["rollback_s"] = [rb.get("took_s") for rb in sc.get("rollbacks") or []]
        row["outages_s"] = sorted({round(o["length_s"], 1) for o in sc.get("outages") or []})
        row["exit"] = [sc.get("robot_exit"), sc.get("base_exit")]
        row["error_line"] = sc.get("robot_error_line") or sc.get("base_error_line")
        out[name] = row
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--rate", type=float, default=10.0)
    p.add_argument("--checkpoint-every", type=int, default=10)
    p.add_argument("--delay-ms", type=float, default=50.0)
    p.add_argument("--jitter-ms", type=float, default=20.0)
    p.add_argument("--outage-s", type=float, default=5.0)
    p.add_argument("--timeout", type=float, default=400.0)
    p.add_argument("--only", nargs="*", choices=list(SCENARIOS))
    p.add_argument("--out", default=str(ROOT / "bench" / "results" / "hosts.json"))
    p.add_argument("--summary", action="store_true", help="only recompute the summary of --out")
    args = p.parse_args()
    path = Path(args.out)
    if args.summary:
        result = json.loads(path.read_text())
        result["summary"] = summary(result["scenarios"])
        path.write_text(json.dumps(result, indent=2, default=str) + "\n")
        return 0
    why = netns_unavailable()
    if why:
        print(f"cannot run: {why}", file=sys.stderr)
        return 2
    result = {"machine": {"cpus": os.cpu_count(), "kernel": platform.release(), "python": platform.python_version(),
                          "netem": netem_available(), "load_avg_at_start": os.getloadavg()},
              "method": {"frames": args.frames, "rate_fps": args.rate, "checkpoint_every": args.checkpoint_every,
                         "relay_delay_ms": args.delay_ms, "relay_jitter_ms": args.jitter_ms,
                         "outage_s": args.outage_s, "faults_at_pose_rows": 40,
                         "recovery": "seconds from the end of the fault to the next row of the base's trajectory"},
              "scenarios": {}}
    if path.exists() and args.only:
        result["scenarios"] = json.loads(path.read_text()).get("scenarios", {})
    work = Path(tempfile.mkdtemp(prefix="neoslam-hosts-"))
    try:
        for name in args.only or SCENARIOS:
            print(f"{name} ...", flush=True)
            result["scenarios"][name] = scenario(name, args, work)
            print(json.dumps(result["scenarios"][name], indent=1, default=str)[:2000], flush=True)
            result["summary"] = summary(result["scenarios"])
            path.write_text(json.dumps(result, indent=2, default=str) + "\n")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
