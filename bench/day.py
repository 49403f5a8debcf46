"""A day on a route the map knows, compressed: the default drives its synthetic route again and again,
lossless and as fast as the pipeline goes, for a given wall time -> bench/results/<name>.json, .png.

One ``neoslam run`` of the shipped default (pipeline topology, one process per stage, lossless: the
source waits for the slowest stage, nothing is lost) on the looped synthetic route (2445 frames of
10 Hz a lap; at 30 FPS a lap is 82 s of driving) for ``--duration`` seconds of wall time (or
``--laps`` laps). Per lap, from the monitor's stats.jsonl (its samples every 5 s, read at each lap's
last frame by linear interpolation over the frames the map has integrated; the last lap at the last
sample before the run's end, whose flushes and files are no lap's) and the run folder:
experiences, D's intervals (made, kept, indexed), templates, each worker's RSS and their sum, D's
recent query time (p50), the seconds the map spent solving and pruning in the lap, the lap's loop
closures (templates.csv), and the lap's frames on the final map against ground truth (APE after one
SE(2) alignment of the whole run, trajectory_map.tum) and online, as the map placed them while the
lap was driven (trajectory.tum, each lap aligned alone). ``neoslam map export`` after the third lap
(a separate lossless run of exactly three laps: a lossless run is repeatable frame for frame, so it
holds the day's state at its third lap) and at the end: both sizes.

Targets (``targets``, docs/long_runs.md): from the third lap on, experiences, D's kept intervals
and the workers' memory grow by at most 1 % a lap (the slope of a line through laps 3.., relative
to lap 3's value); each lap's final-map APE, and its online APE, within 10 % of lap 2's; closures per lap do not fall
(every lap from the third at least 99 % of the second's); the export at the end at most 10 % larger
than after lap 3.

Run (the target run: two hours of wall time on a quiet machine, about seven hours of 30-FPS
driving): ``.venv/bin/python bench/day.py --duration 7200 --out bench/results/day.json``; a short
check: ``--laps 8 --out bench/results/day_short.json``. bench/day_back_end.py replays a finished
day's back end with other settings, in minutes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.config import load_config  # noqa: E402

GROWTH_MAX = 0.01   # per lap, relative to lap 3's value
APE_SLACK = 0.10    # each lap's APE (on the final map; online) within this fraction of lap 2's
CLOSURES_MIN = 0.99  # each lap's closures at least this fraction of lap 2's
EXPORT_SLACK = 0.10  # the end's export at most this much larger than lap 3's


def day_config(config: str | None, laps: int | None, duration: float | None, route: int) -> Any:
    src: dict[str, Any] = {"params": {"loop": True}, "duration": duration,
                           "max_frames": laps * route if laps else None}
    return load_config(config or "default", {"source": src, "run": {"mode": "lossless", "live": False,
                                                                    "topology": "pipeline"}})


def route_of(cfg: Any) -> tuple[int, np.ndarray]:
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    src = SyntheticWorldSource(**{**cfg.source.params, "width": 8, "height": 8, "loop": False})
    return src.route_len, src.gt


def stats_rows(stats: Path) -> list[dict[str, Any]]:
    rows = []
    for line in stats.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def at_frames(rows: list[dict[str, Any]], frames: list[int]) -> dict[str, list[float | None]]:
    """Each figure of the samples, read at each of ``frames`` (the frames the map had integrated),
    linearly between the two samples around it; the samples that saw the last frame (the run's
    end: flushes, files, final states) are left out."""
    def get(snap: dict[str, Any], stage: str, *keys: str) -> float | None:
        v: Any = snap["stages"].get(stage, {})
        for k in keys:
            v = (v or {}).get(k)
        return None if v is None else float(v)

    done = np.array([get(s, "experience_map", "processed") or 0.0 for s in rows])
    # a sample that saw the map's last frame is the end of the run (flushes, files, final states):
    # left out, so the last lap is read at the last sample before it
    keep = done < max(frames)
    if keep.sum() >= 2:
        rows, done = [r for r, k in zip(rows, keep, strict=True) if k], done[keep]
    workers = sorted({st.get("worker", n) for s in rows for n, st in s["stages"].items()})
    series = {
        "experiences": [get(s, "experience_map", "info", "experiences") for s in rows],
        "experiences_merged": [get(s, "experience_map", "info", "experiences_merged") for s in rows],
        "links": [get(s, "experience_map", "info", "links") for s in rows],
        "solve_s_total": [get(s, "experience_map", "info", "solve_s_total") for s in rows],
        "intervals_made": [get(s, "D", "info", "intervals") for s in rows],
        "intervals_kept": [get(s, "D", "info", "intervals_stored") for s in rows],
        "intervals_indexed": [get(s, "D", "info", "indexed_intervals") for s in rows],
        "templates": [get(s, "D", "info", "templates") for s in rows],
        "pose_cell_templates": [get(s, "pose_cells", "info", "templates") for s in rows],
        "d_query_p50_ms": [get(s, "D", "tau_recent_p50_ms") for s in rows],
    }
    for w in workers:  # a worker's RSS (the recorder shares the map's worker)
        series[f"rss_mb:{w}"] = [next((float(st["rss_mb"]) for n, st in s["stages"].items()
                                       if st.get("worker", n) == w and st.get("rss_mb") is not None), None)
                                 for s in rows]
    series["rss_total_mb"] = [sum(v for k, vs in series.items() if k.startswith("rss_mb:") and (v := vs[i]) is not None)
                              for i in range(len(rows))]
    out: dict[str, list[float | None]] = {}
    for name, vals in series.items():
        ok = np.array([v is not None for v in vals])
        if not ok.any():
            continue
        x, y = done[ok], np.array([v for v in vals if v is not None], dtype=float)
        out[name] = [round(float(np.interp(f, x, y)), 3) for f in frames]
    return out


def closures_by_lap(run_dir: Path, route: int) -> tuple[list[int], list[int]]:
    """Loop closures and new template ids per lap (templates.csv)."""
    closures: dict[int, int] = {}
    new: dict[int, int] = {}
    seen: set[int] = set()
    with open(run_dir / "templates.csv") as f:
        next(f)
        for line in f:
            frame, _, template, closure = line.split(",")[:4]
            lap = int(frame) // route
            closures[lap] = closures.get(lap, 0) + int(closure)
            if int(template) not in seen:
                seen.add(int(template))
                new[lap] = new.get(lap, 0) + 1
    laps = max(closures, default=-1) + 1
    return [closures.get(k, 0) for k in range(laps)], [new.get(k, 0) for k in range(laps)]


def ape_by_lap(run_dir: Path, gt: np.ndarray, route: int, name: str = "trajectory_map.tum",
               per_lap: bool = False) -> list[float]:
    """Each lap's mean pose error against ground truth: of its frames on the final map
    (trajectory_map.tum) after one SE(2) alignment of the whole run; or, with
    ``name="trajectory.tum", per_lap=True``, of the map's poses as the lap was driven (online), each
    lap after the SE(2) alignment that fits it best: the map's shape at that time of the day, which
    the final map cannot show (every lap is read on the same final map)."""
    from neoslam_stream.tum import read_tum

    traj = read_tum(run_dir / name)
    frames = np.rint(traj[:, 0] * 10.0).astype(np.int64)  # stamps of a 10 Hz source
    return lap_ape(traj[:, 1:3], gt[frames % route, :2], frames // route, per_lap)


def lap_ape(xy: np.ndarray, ref: np.ndarray, lap: np.ndarray, per_lap: bool) -> list[float]:
    """Each lap's mean distance of ``xy`` to ``ref`` after one SE(2) alignment of them all, or
    (``per_lap``) of that lap alone; ``lap`` numbers each row's lap from 0."""
    from neoslam_stream.evaluation.poses import umeyama_se2

    out = []
    if not per_lap:
        R, t = umeyama_se2(xy, ref)
    for k in range(int(lap.max()) + 1):
        m = lap == k
        if per_lap:
            R, t = umeyama_se2(xy[m], ref[m])
        out.append(round(float(np.linalg.norm(xy[m] @ R.T + t - ref[m], axis=1).mean()), 4))
    return out


def growth(values: list[float | None], first: int = 2) -> float | None:
    """The slope per lap of a line through laps ``first``+1.. (0-based ``first``), relative to that
    lap's value."""
    pts = [(k, v) for k, v in enumerate(values) if k >= first and v is not None]
    if len(pts) < 2 or not pts[0][1]:
        return None
    k, v = np.array(pts, dtype=float).T
    return round(float(np.polyfit(k, v, 1)[0] / pts[0][1]), 5)


def export_size(run_dir: Path, out: Path) -> int:
    from neoslam_stream.runtime.checkpoint import export_map

    export_map(run_dir, out)
    return out.stat().st_size


def targets(res: dict[str, Any]) -> dict[str, Any]:
    laps = res["laps"]
    full = [r for r in laps if r["complete"]]
    t: dict[str, Any] = {"growth_max_per_lap": GROWTH_MAX, "ape_slack": APE_SLACK, "closures_min": CLOSURES_MIN,
                         "export_slack": EXPORT_SLACK}
    if len(full) < 4:
        t["reached"] = None
        t["why"] = "fewer than four complete laps"
        return t
    g = {k: growth([r.get(k) for r in full]) for k in ("experiences", "intervals_kept", "rss_total_mb", "templates")}
    ape2 = full[1]["ape_final_map_m"]
    c2 = full[1]["closures"]
    t["growth_per_lap_from_lap3"] = g
    t["ape_worst_vs_lap2"] = round(max(r["ape_final_map_m"] for r in full[2:]) / ape2, 4) if ape2 else None
    online2 = full[1].get("ape_online_m")
    t["ape_online_worst_vs_lap2"] = round(max(r["ape_online_m"] for r in full[2:]) / online2, 4) \
        if online2 else None
    t["closures_fewest_vs_lap2"] = round(min(r["closures"] for r in full[2:]) / c2, 4) if c2 else None
    t["export_end_vs_lap3"] = round(res["export_bytes_end"] / res["export_bytes_lap3"], 4) \
        if res.get("export_bytes_lap3") else None
    t["reached"] = {
        "growth": all(v is not None and v <= GROWTH_MAX for k, v in g.items() if k != "templates"),
        "ape": t["ape_worst_vs_lap2"] is not None and t["ape_worst_vs_lap2"] <= 1 + APE_SLACK,
        "ape_online": t["ape_online_worst_vs_lap2"] is not None and t["ape_online_worst_vs_lap2"] <= 1 + APE_SLACK,
        "closures": t["closures_fewest_vs_lap2"] is not None and t["closures_fewest_vs_lap2"] >= CLOSURES_MIN,
        "export": t["export_end_vs_lap3"] is not None and t["export_end_vs_lap3"] <= 1 + EXPORT_SLACK,
    }
    return t


def plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    laps = res["laps"]
    k = [r["lap"] for r in laps]
    fig, ax = plt.subplots(2, 3, figsize=(16, 8))
    for key in ("experiences", "intervals_kept", "intervals_indexed", "templates"):
        ax[0, 0].plot(k, [r.get(key) for r in laps], ".-", label=key)
    ax[0, 0].set(title="What the run keeps", xlabel="lap", yscale="log")
    for key in sorted(x for x in laps[-1] if x.startswith("rss_mb:")):
        ax[0, 1].plot(k, [r.get(key) for r in laps], lw=0.8, label=key.split(":", 1)[1])
    ax[0, 1].plot(k, [r.get("rss_total_mb") for r in laps], "k.-", label="all workers")
    ax[0, 1].set(title="Memory (RSS, MB)", xlabel="lap", yscale="log")
    ax[0, 2].plot(k, [r.get("d_query_p50_ms") for r in laps], ".-", label="D's query p50 (ms)")
    ax[0, 2].plot(k, [1e3 * (r.get("solve_s") or 0) for r in laps], ".-", label="map solve + prune in the lap (ms)")
    ax[0, 2].set(title="Time", xlabel="lap", yscale="log")
    ax[1, 0].plot(k, [r["closures"] for r in laps], ".-")
    ax[1, 0].set(title="Loop closures per lap", xlabel="lap")
    ax[1, 1].plot(k, [r["ape_final_map_m"] for r in laps], ".-", label="on the final map")
    ax[1, 1].plot(k, [r.get("ape_online_m") for r in laps], ".-", label="online, the lap aligned alone")
    ax[1, 1].set(title="APE of the lap's frames (m)", xlabel="lap")
    ax[1, 1].legend(fontsize=7)
    ax[1, 2].bar(["after lap 3", "at the end"], [res.get("export_bytes_lap3") or 0, res.get("export_bytes_end") or 0])
    ax[1, 2].set(title="neoslam map export (bytes)")
    for a in ax.flat:
        a.grid(alpha=0.3)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.suptitle(f"{res['frames']} frames, {len(laps)} laps in {res['wall_s']:.0f} s of wall time "
                 f"({res['frames'] / 30.0 / 3600:.2f} h of 30-FPS driving)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, help="seconds of wall time (the target run: 7200)")
    ap.add_argument("--laps", type=int, help="laps of the route instead of a duration")
    ap.add_argument("--config", default=None, help="the config (default: the shipped default)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "day.json"))
    ap.add_argument("--from-run", help="analyse this finished day's run folder (with its lap3 folder beside it)")
    args = ap.parse_args()
    if not args.from_run and not (args.duration or args.laps):
        ap.error("give --duration SECONDS or --laps N")
    from neoslam_stream.launch import run

    out = Path(args.out)
    work = out.parent / f"{out.stem}_runs"
    run_dir, lap3_dir = (Path(args.from_run), Path(args.from_run).parent / "lap3") if args.from_run \
        else (work / "day", work / "lap3")
    probe = load_config(args.config or "default", {"source": {"params": {"loop": True}}})
    route, gt = route_of(probe)
    if not args.from_run:
        for d in (run_dir, lap3_dir):
            shutil.rmtree(d, ignore_errors=True)
        print(f"lap 3's state: {3 * route} frames, lossless", flush=True)
        run(day_config(args.config, 3, None, route), lap3_dir)
        print(f"the day: {args.duration or 0:g} s of wall time / {args.laps or 0} laps", flush=True)
        run(day_config(args.config, args.laps, args.duration, route), run_dir)  # its report.json, read below
    report = json.loads((run_dir / "report.json").read_text())
    frames = int(report.get("frames_out") or 0)
    closures, new_templates = closures_by_lap(run_dir, route)
    n_laps = len(closures)
    ends = [min((k + 1) * route, frames) for k in range(n_laps)]
    figures = at_frames(stats_rows(run_dir / "stats.jsonl"), ends)
    ape = ape_by_lap(run_dir, gt, route)
    ape_online = ape_by_lap(run_dir, gt, route, "trajectory.tum", per_lap=True)
    laps = []
    prev_solve = 0.0
    for k in range(n_laps):
        row: dict[str, Any] = {"lap": k + 1, "complete": ends[k] == (k + 1) * route, "closures": closures[k],
                               "new_template_ids": new_templates[k], "ape_final_map_m": ape[k] if k < len(ape) else None,
                               "ape_online_m": ape_online[k] if k < len(ape_online) else None}
        for name, vals in figures.items():
            row[name] = vals[k]
        solve = row.pop("solve_s_total", None)
        if solve is not None:
            row["solve_s"] = round(solve - prev_solve, 3)
            prev_solve = solve
        laps.append(row)
    work.mkdir(parents=True, exist_ok=True)
    res: dict[str, Any] = {
        "config": args.config or "default", "route_frames": route, "frames": frames,
        "frames_lost": report.get("frames_in", frames) - frames if report.get("mode") != "lossless" else 0,
        "loss": report.get("loss"), "errors": report.get("errors"),
        "wall_s": report.get("duration_s") or 0.0,
        "hours_of_30fps_driving": round(frames / 30.0 / 3600, 3),
        "frames_per_s": report.get("f_out_hz") or report.get("f_out"),
        "export_bytes_lap3": export_size(lap3_dir, work / "lap3.neoslam") if (lap3_dir / "report.json").exists() else None,
        "export_bytes_end": export_size(run_dir, work / "day.neoslam"),
        "laps": laps}
    res["targets"] = targets(res)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    plot(res, out.with_suffix(".png"))
    for r in laps:
        print(json.dumps({k: r.get(k) for k in ("lap", "closures", "experiences", "intervals_kept", "intervals_indexed",
                                                "templates", "rss_total_mb", "d_query_p50_ms", "solve_s",
                                                "ape_final_map_m", "ape_online_m")}))
    print(json.dumps({k: v for k, v in res.items() if k != "laps"}, indent=1))


if __name__ == "__main__":
    main()
