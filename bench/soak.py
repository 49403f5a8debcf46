"""Soak: NeoSLAM for a long time at camera rate on the looped synthetic world -> bench/results/soak.json.

One real-time (drop-oldest) pipeline run at ``--rate`` FPS for ``--duration`` seconds (default one
hour), then the monitor's stats.jsonl sampled every ``--every`` seconds: frames in, frames done,
the frames lost in that interval, RSS of every worker and in total, and the CPU time the
hypervisor took from this machine in it (``steal_s``, from /proc/stat beside the run: a minute in
which the host took the cores loses frames that are not the pipeline's doing). Memory is bounded
when the RSS curve flattens: the report gives the growth rate over the second half of the run
(MB per hour) next to the state the stages keep (TM segments/synapses, spatial-view intervals,
experiences), which must grow with new places only, and ``memory_flat_after_warmup``: the range
(max - min) of the summed RSS after ``--flat-after`` seconds (600: the first ten minutes) until
the stream's end against ``--flat-within`` MB (50), as bench/memory_flat.py defines it for both
soaks, with the frames lost, and whether both hold (``reached``).

Run: ``.venv/bin/python bench/soak.py [--duration 3600] [--rate 30] [--backbone random_alexnet] [--matrix-dtype int8] [--out bench/results/soak.json]``;
a short check of the same: ``--duration 240 --every 10 --flat-after 60``
(the default config with its own backbone unless ``--backbone`` or ``--config`` say otherwise).
Also writes soak.png next to the JSON.
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import sys
import threading
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from memory_flat import FLAT_AFTER_S, FLAT_WITHIN_MB, memory_flat  # noqa: E402

from neoslam_stream.runtime.host import steal_ticks  # noqa: E402
from neoslam_stream.throughput import rate_sweep, summarise  # noqa: E402


def minutes(stats_path: Path, every_s: float) -> list[dict]:
    rows: list[dict] = []
    next_t = every_s
    for line in stats_path.read_text().splitlines():
        try:
            snap = json.loads(line)
        except json.JSONDecodeError:
            continue
        if snap["t_s"] < next_t:
            continue
        next_t = (snap["t_s"] // every_s + 1) * every_s
        st = snap["stages"]
        done = st.get("experience_map", {}).get("processed", 0)
        fin = snap.get("frames_in", 0)
        rss = {n: s.get("rss_mb") for n, s in st.items()}
        by_worker = {s.get("worker", n): s.get("rss_mb") or 0.0 for n, s in st.items()}
        rows.append({"t_s": snap["t_s"], "frames_in": fin, "frames_done": done,
                     # frames published but not through yet: bounded while the pipeline keeps up
                     # (a sample is taken while frames are in flight, so this is not a loss)
                     "in_flight": fin - done,
                     "rss_mb": rss, "rss_total_mb": sum(by_worker.values()),
                     "tm_segments": (st.get("C", {}).get("info") or {}).get("segments"),
                     "tm_synapses": (st.get("C", {}).get("info") or {}).get("synapses"),
                     "svc_intervals": (st.get("D", {}).get("info") or {}).get("intervals"),
                     # the intervals in D's index (revisits stay out of it in the default)
                     "svc_indexed": (st.get("D", {}).get("info") or {}).get("indexed_intervals"),
                     # D's query over its recent frames: how the spatial-view search scales
                     "d_query_recent_p50_ms": st.get("D", {}).get("tau_recent_p50_ms"),
                     "d_query_recent_p95_ms": st.get("D", {}).get("tau_recent_p95_ms"),
                     "experiences": (st.get("experience_map", {}).get("info") or {}).get("experiences")})
    return rows


class StealLog(threading.Thread):
    """Appends ``<epoch s> <the cpu line of /proc/stat>`` to ``path`` every ``every_s`` seconds
    while the run goes on (no /proc/stat: nothing)."""

    def __init__(self, path: Path, every_s: float) -> None:
        super().__init__(daemon=True)
        self.path, self.every_s, self.stop = path, every_s, threading.Event()

    def run(self) -> None:
        try:
            with open(self.path, "w") as out:
                while True:
                    out.write(f"{time.time():.0f} {Path('/proc/stat').read_text().splitlines()[0]}\n")
                    out.flush()
                    if self.stop.wait(self.every_s):
                        return
        except OSError:
            return


def steal_by_row(log: Path, rows: list[dict]) -> None:
    """Each row's ``steal_s``: the steal (``steal_ticks`` of the logged cpu line) since the previous
    row, the counter read linearly between the log's samples; the log's first sample is the run's
    start, to within a second (the run folder is made then)."""
    if not log.exists():
        return
    tick = os.sysconf("SC_CLK_TCK")
    samples = []
    for line in log.read_text().splitlines():
        stamp, _, cpu_line = line.partition(" ")
        ticks = steal_ticks(cpu_line)
        if ticks is not None:
            samples.append((float(stamp), ticks / tick))
    if len(samples) < 2:
        return
    t0 = samples[0][0]
    ts = [t - t0 for t, _ in samples]

    def at(t: float) -> float:  # the steal counter at run time t, linear between two samples
        k = max(1, min(len(samples) - 1, bisect.bisect_right(ts, t)))
        (ta, a), (tb, b) = (ts[k - 1], samples[k - 1][1]), (ts[k], samples[k][1])
        return a + (b - a) * min(1.0, max(0.0, (t - ta) / (tb - ta))) if tb > ta else b

    prev = 0.0
    for r in rows:
        r["steal_s"] = round(at(r["t_s"]) - at(prev), 2)
        prev = r["t_s"]


def lost_by_row(lost: list[int], rows: list[dict]) -> None:
    """Each row's ``lost``: the lost frames published since the previous row (frame f was published
    when ``frames_in`` passed f)."""
    ins = [r["frames_in"] for r in rows]
    for r in rows:
        r["lost"] = 0
    for f in lost:
        k = bisect.bisect_right(ins, f)
        if k < len(rows):
            rows[k]["lost"] += 1


def passes(run_dir: Path) -> list[dict]:
    """Frames, loop closures (all, and in the stretch every pass revisits: bench/streams.py's
    STRETCH), new templates and the frames lost (``lost_frames``: missing from templates.csv; what
    ``studies/passes.py --lost-from`` replays) in each pass of the looped synthetic route."""
    from streams import STRETCH

    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    if cfg["source"]["kind"] != "synthetic" or not (run_dir / "templates.csv").exists():
        return []
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    route = SyntheticWorldSource(**cfg["source"]["params"]).route_len
    rows: dict[int, dict] = {}
    seen: set[int] = set()
    got: set[int] = set()
    with open(run_dir / "templates.csv") as f:
        next(f)
        for line in f:
            frame, _, template, closure = line.split(",")[:4]
            r = rows.setdefault(int(frame) // route, {"frames": 0, "loop_closures": 0, "new_templates": 0,
                                                      "loop_closures_800_2400": 0})
            r["frames"] += 1
            got.add(int(frame))
            r["loop_closures"] += int(closure)
            r["loop_closures_800_2400"] += int(closure) * (STRETCH[0] <= int(frame) % route < STRETCH[1])
            if int(template) not in seen:
                seen.add(int(template))
                r["new_templates"] += 1
    last = max(got, default=-1)
    return [{"pass": k + 1, **rows[k],
             "lost_frames": [f for f in range(k * route, min((k + 1) * route, last + 1)) if f not in got]}
            for k in sorted(rows)]


def memory_after_warmup(rows: list[dict], after_s: float, within_mb: float, frames_lost: int,
                        until_s: float | None = None) -> dict:
    """The live hour's target: memory flat after the warm-up (:func:`memory_flat.memory_flat`, the
    verdict both soaks use) and no frame lost over the whole run; ``reached`` when both hold."""
    flat = memory_flat(rows, after_s, within_mb, until_s)
    reached = None if flat["flat"] is None else bool(flat["flat"] and frames_lost == 0)
    return {**flat, "frames_lost": frames_lost, "no_frame_lost": frames_lost == 0, "reached": reached}


def growth_per_hour(rows: list[dict]) -> float | None:
    pts = [(r["t_s"], r["rss_total_mb"]) for r in rows[len(rows) // 2:]]
    if len(pts) < 2:
        return None
    n = len(pts)
    mx, my = sum(p[0] for p in pts) / n, sum(p[1] for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    return 3600.0 * sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx if sxx else None


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = res["minutes"]
    t = [r["t_s"] / 60 for r in rows]
    fig, ax = plt.subplots(1, 3 if res.get("passes") else 2, figsize=(16 if res.get("passes") else 11, 4))
    ax[0].plot(t, [r["rss_total_mb"] for r in rows], "k-", label="all workers")
    for name in sorted(rows[-1]["rss_mb"]) if rows else []:
        ax[0].plot(t, [r["rss_mb"].get(name) for r in rows], lw=0.8, label=name)
    ax[0].set(xlabel="minutes", ylabel="RSS (MB)", title="Memory")
    ax[0].legend(fontsize=7)
    ax[1].bar(t, [r.get("lost", 0) for r in rows], width=0.8, color="tab:red", label="frames lost in the minute")
    ax[1].plot(t, [r.get("steal_s", float("nan")) for r in rows], "k.-", ms=3,
               label="CPU seconds the hypervisor took (steal)")
    ax[1].set(xlabel="minutes", ylabel="per sample interval",
              title=f"{res['frames_out']} of {res['frames_in']} frames at {res['rate']:g} FPS "
                    f"(loss {100 * res['loss']:.3f} %)")
    ax[1].legend(fontsize=7)
    if res.get("passes"):
        ps = res["passes"]
        k = [r["pass"] for r in ps]
        ax[2].plot(k, [r["loop_closures"] / r["frames"] for r in ps], "o-", label="loop closures")
        ax[2].plot(k, [r["new_templates"] / r["frames"] for r in ps], "s-", label="new templates")
        ax[2].set(xlabel="pass of the route", ylabel="per frame of the pass", title="The map, pass by pass")
        ax[2].legend(fontsize=7)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=3600.0, help="seconds (default 3600)")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--every", type=float, default=60.0, help="seconds between two samples")
    ap.add_argument("--config", default=None)
    ap.add_argument("--backbone", default=None,
                    help="feature backbone (default: the config's, as a user runs it; random_alexnet: "
                         "the AlexNet-cost backbone of the paper's comparison)")
    ap.add_argument("--matrix-dtype", choices=["float32", "float16", "int8"],
                    help="storage of B's Gaussian matrix (projector.matrix_dtype; default: the config's)")
    ap.add_argument("--feature-bits", type=int, choices=[16, 7],
                    help="with int8 storage: 16- or 7-bit features (projector.feature_bits; default: the config's)")
    ap.add_argument("--flat-after", type=float, default=FLAT_AFTER_S,
                    help="seconds after which memory must stay flat (default 600: the first ten minutes)")
    ap.add_argument("--flat-within", type=float, default=FLAT_WITHIN_MB, help="MB the memory may rise after --flat-after")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "soak.json"))
    ap.add_argument("--from-run", help="analyse this finished soak run folder instead of running one")
    ap.add_argument("--steal-log", help="with --from-run: the /proc/stat log taken beside it "
                                        "(default: steal.log two folders above the run folder)")
    args = ap.parse_args()
    out = Path(args.out)
    work = out.parent / "soak_runs"
    run_dir = work / "runs" / f"pipeline-{args.rate:g}"
    steal_log = work / "steal.log"
    if args.from_run:  # analyse a finished soak again (e.g. after changing this script)
        run_dir = Path(args.from_run)
        steal_log = Path(args.steal_log) if args.steal_log else run_dir.parents[1] / "steal.log"
        report = json.loads((run_dir / "report.json").read_text())
        row = summarise(report, "pipeline", args.rate, args.duration)
        cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
        row.update({"matrix_dtype": cfg["projector"]["matrix_dtype"], "max_batch": cfg["run"]["max_batch"],
                    "feature_bits": cfg["projector"].get("feature_bits", 16)})
    else:
        chosen = {"matrix_dtype": args.matrix_dtype, "feature_bits": args.feature_bits}
        overrides = {"projector": {k: v for k, v in chosen.items() if v}} if any(chosen.values()) else None
        work.mkdir(parents=True, exist_ok=True)
        sampler = StealLog(steal_log, args.every)
        sampler.start()
        try:
            (row,) = rate_sweep(args.config, [args.rate], args.duration, ["pipeline"], work, args.backbone, overrides)
        finally:
            sampler.stop.set()
    rows = minutes(run_dir / "stats.jsonl", args.every)
    by_pass = passes(run_dir)
    if by_pass:  # which frames were lost is known on the synthetic world's route
        lost_by_row([f for p in by_pass for f in p["lost_frames"]], rows)
    steal_by_row(steal_log, rows)
    res = {"rate": args.rate, "duration_s": args.duration, "frames_in": row["frames_in"],
           "frames_out": row["frames_processed"], "loss": row["loss"], "errors": row["errors"],
           "restarts": row["restarts"], "backbone": row["backbone"],
           "matrix_dtype": row["matrix_dtype"], "feature_bits": row["feature_bits"], "max_batch": row["max_batch"],
           "rss_total_mb_first": rows[0]["rss_total_mb"] if rows else None,
           "rss_total_mb_last": rows[-1]["rss_total_mb"] if rows else None,
           "rss_growth_mb_per_hour_second_half": growth_per_hour(rows),
           "memory_flat_after_warmup": memory_after_warmup(rows, args.flat_after, args.flat_within,
                                                           int(row["frames_in"] - row["frames_processed"]),
                                                           until_s=args.duration),
           "stages": row["stages"], "passes": by_pass, "minutes": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    if rows:
        plot(res, out.with_suffix(".png"))
    print(json.dumps({k: v for k, v in res.items() if k not in ("minutes", "stages", "passes")}, indent=2))
    for r in res["passes"]:
        print(f"pass {r['pass']}: {r['frames']} frames, {r['loop_closures']} loop closures, "
              f"{r['new_templates']} new templates")


if __name__ == "__main__":
    main()
