"""Beyond two cores: the rate each topology sustains on c cores, predicted and measured.

For each topology: one uncontended reference run (real time at ``--ref-rate`` FPS on every core
of this machine) measures each worker's service time per frame (report.json) and its CPU per frame
(the whole process tree's CPU). Load runs: lossless, as fast as the pipeline goes (``pacing:
asap``), the whole process tree pinned to 1 and to 2 cores with ``sched_setaffinity``; their steady
frame rate is the rate the topology sustains there, and their CPU time per frame C is what a frame
costs when the stages share cores. ``runtime.capacity.sustainable_rate`` predicts each core count
from the reference and the *other* load run (each worker's least service time, their C), and 4,
8, 16 cores from all three runs (the mean C). Writes bench/results/cores.json; the shipped default config unless ``--config``.

On a machine with more cores, ``--cores 1,2,4,8,16`` also runs the load at those counts and
checks the 4-, 8- and 16-core predictions made from what a 2-core machine measures (the reference
and the 1- and 2-core runs alone) against the rates measured there. Every stage runs on the CPU,
also where torch sees a GPU (the model counts cores; the GPU path is bench/gpu.py).

Run: ``.venv/bin/python bench/cores.py [--config default] [--frames 900] [--cores 1,2]
[--topologies pipeline,monolithic] [--out bench/results/cores.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neoslam_stream.runtime.capacity import (  # noqa: E402
    least_service_ms,
    sustainable_rate,
    worker_service_ms,
)
from neoslam_stream.throughput import bench_config  # noqa: E402

CLI = [sys.executable, "-m", "neoslam_stream.cli"]
#: the model counts CPU cores: every stage on the CPU, also where torch sees a GPU (bench/gpu.py)
ON_CPU = {"features": {"device": "cpu"}, "projector": {"device": "cpu"}}
PREDICT_CORES = (1, 2, 4, 8, 16)
#: frames past the measured ones, so that the run is still going when the last mark is taken
MARGIN = 300


def _tree_cpu_s(proc: psutil.Process) -> float:
    """CPU seconds (user + system) of a process and every live descendant."""
    total = 0.0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


def _done(run_dir: Path) -> tuple[float, int] | None:
    """(monitor time, frames through the last stage) of the newest line of stats.jsonl."""
    try:
        lines = (run_dir / "stats.jsonl").read_text().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        try:
            snap = json.loads(line)
        except json.JSONDecodeError:
            continue
        return snap["t_s"], int(snap["stages"].get("experience_map", {}).get("processed", 0))
    return None


def measured_run(cfg: Any, run_dir: Path, cpus: set[int] | None, skip: int, frames: int) -> dict[str, Any]:
    """One run as a child process tree (pinned to ``cpus``); CPU and frames between the moment
    ``skip`` frames were done and the moment ``skip + frames`` were (start-up and drain left out)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg_path = run_dir.parent / f"{run_dir.name}.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    pre = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
    proc = subprocess.Popen([*CLI, "run", "-c", str(cfg_path), "--out", str(run_dir), "--no-live"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=pre, cwd=ROOT)
    ps = psutil.Process(proc.pid)
    marks: list[tuple[float, float, int]] = []  # (wall, tree CPU, frames done)
    try:
        for target in (skip, skip + frames):
            while proc.poll() is None:
                d = _done(run_dir)
                if d is not None and d[1] >= target:
                    marks.append((time.monotonic(), _tree_cpu_s(ps), d[1]))
                    break
                time.sleep(0.2)
        rc = proc.wait(timeout=900)
    finally:
        if proc.poll() is None:
            proc.kill()
    if rc != 0 or len(marks) < 2:
        raise RuntimeError(f"run {run_dir} failed (rc {rc}): {proc.stderr.read().decode()[-2000:]}")
    (w0, c0, f0), (w1, c1, f1) = marks
    if f1 <= f0:
        raise RuntimeError(f"run {run_dir}: no frame between the two marks (raise --frames)")
    report = json.loads((run_dir / "report.json").read_text())
    return {"report": report, "frames": f1 - f0, "wall_s": w1 - w0, "rate_hz": (f1 - f0) / (w1 - w0),
            "cpu_ms_per_frame": 1e3 * (c1 - c0) / (f1 - f0)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="default")
    ap.add_argument("--ref-rate", type=float, default=10.0, help="FPS of the uncontended reference runs")
    ap.add_argument("--frames", type=int, default=900, help="frames measured per run, after --skip")
    ap.add_argument("--skip", type=int, default=150, help="frames left out at the start of each run")
    ap.add_argument("--cores", default="1,2",
                    help="core counts of the load runs (comma-separated; 1 and 2 always among them)")
    ap.add_argument("--topologies", default="pipeline,monolithic")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "cores.json"))
    args = ap.parse_args()
    n_cpu = len(os.sched_getaffinity(0))
    counts = sorted({1, 2, *(int(c) for c in args.cores.split(",") if c.strip())})
    if n_cpu < counts[-1]:
        raise SystemExit(f"bench/cores.py measures at {counts[-1]} cores: this process may use only {n_cpu}")
    cpus = sorted(os.sched_getaffinity(0))
    res: dict[str, Any] = {"config": args.config, "machine_cores": n_cpu, "load_cores": counts, "topologies": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for topo in args.topologies.split(","):
            print(f"{topo}: reference run at {args.ref_rate:g} FPS on {n_cpu} cores ...", flush=True)
            cfg = bench_config(args.config, topo, "realtime", None, ON_CPU)
            cfg.source.rate, cfg.source.pacing = args.ref_rate, "fixed"
            cfg.source.max_frames = args.skip + args.frames + MARGIN
            ref = measured_run(cfg, Path(tmp) / f"{topo}-ref", None, args.skip, args.frames)
            workers = worker_service_ms(ref["report"])
            load = {}
            for cores in counts:
                print(f"{topo}: lossless, as fast as it goes, on {cores} core(s) ...", flush=True)
                cfg = bench_config(args.config, topo, "lossless", None, ON_CPU)
                cfg.source.pacing = "asap"
                cfg.source.max_frames = args.skip + args.frames + MARGIN
                m = measured_run(cfg, Path(tmp) / f"{topo}-{cores}", set(cpus[:cores]), args.skip, args.frames)
                load[cores] = {"rate_hz": m["rate_hz"], "frames": m["frames"],
                               "cpu_ms_per_frame": m["cpu_ms_per_frame"],
                               "worker_ms": worker_service_ms(m["report"])}
            row: dict[str, Any] = {
                "reference": {"rate_hz": args.ref_rate, "worker_ms": workers,
                              "cpu_ms_per_frame": ref["cpu_ms_per_frame"], "loss": ref["report"]["loss"]},
                "load": {str(c): v for c, v in load.items()}, "validation": {}}
            # each core count predicted from the reference and load runs a 2-core machine can make,
            # never its own: 1 from 2, 2 from 1, more cores from both
            for cores in counts:
                others = [c for c in (1, 2) if c != cores]
                tau = least_service_ms(workers, *(load[o]["worker_ms"] for o in others))
                cpu = sum(load[o]["cpu_ms_per_frame"] for o in others) / len(others)
                pred = sustainable_rate(tau, cpu, cores)
                meas = load[cores]["rate_hz"]
                row["validation"][str(cores)] = {**pred, "cpu_ms_per_frame_from": " and ".join(f"{o} core(s)" for o in others),
                                                 "measured_hz": meas, "error": pred["rate_hz"] / meas - 1.0}
                print(f"      {cores} core(s): measured {meas:.1f} Hz, predicted {pred['rate_hz']:.1f} Hz "
                      f"({100 * (pred['rate_hz'] / meas - 1):+.1f} %, {pred['bound']} bound)", flush=True)
            small = [load[c] for c in (1, 2)]
            cpu = sum(v["cpu_ms_per_frame"] for v in small) / len(small)
            tau = least_service_ms(workers, *(v["worker_ms"] for v in small))
            row["predicted"] = {str(c): sustainable_rate(tau, cpu, c) for c in PREDICT_CORES}
            res["topologies"][topo] = row
            Path(args.out).write_text(json.dumps(res, indent=2))  # what is done so far, if a later run fails
    topos = res["topologies"]
    if {"pipeline", "monolithic"} <= topos.keys():
        p, m = topos["pipeline"]["predicted"], topos["monolithic"]["predicted"]
        res["pipeline_over_monolithic_predicted"] = {c: p[c]["rate_hz"] / m[c]["rate_hz"] for c in p}
    Path(args.out).write_text(json.dumps(res, indent=2))
    print(f"wrote {args.out}")
    for c in map(str, PREDICT_CORES):
        print(f"{c:>2} cores: " + ", ".join(f"{t} {r['predicted'][c]['rate_hz']:.1f} Hz ({r['predicted'][c]['bound']})"
                                           for t, r in topos.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
