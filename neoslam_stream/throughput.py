"""``neoslam bench throughput``: the paper's Part I (frame loss at camera rate) on the real stages.

Two experiments on the embedded synthetic world, looped so that any duration works (docs/performance.md):

* **rate sweep** (real-time: the source publishes at a fixed rate into bounded rings that drop the
  oldest message): one run of ``duration`` seconds per (topology, rate), one row of
  ``throughput.json``'s ``runs`` (frames, loss, per-stage tau, CPU and RSS per worker, predicted
  f_pipeline, bottleneck, latency), and the paper's table (Algorithm | Processed Frames | Data Loss).
* **scaling** (lossless, ``--scaling N`` frames): the monitor's stats.jsonl sampled every 1000
  frames (per-stage tau, RSS, TM segments/synapses, intervals, map size, relaxation time) and a
  linear fit of total RSS extrapolated to 100k frames.

The runtime only moves messages; what the numbers mean comes from the stages' own ``info()``, so
this module reads them by name from the run's stats.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from .config import FullRunConfig, load_config

log = logging.getLogger(__name__)

#: the paper's two conditions (Table I: 13 FPS and 10 FPS) are always part of the default sweep
DEFAULT_RATES = (10.0, 13.0, 20.0, 30.0, 45.0, 60.0)
#: the highest rate whose loss is below this is reported as sustainable
SUSTAINABLE_LOSS = 0.001
#: scaling curve step (frames)
SCALING_STEP = 1000


def bench_config(config: str | None, topology: str, mode: str, backbone: str | None,
                 overrides: dict[str, Any] | None = None) -> FullRunConfig:
    """The run config of one bench run: NeoSLAM on the looped synthetic world."""
    over: dict[str, Any] = {
        "run": {"pipeline": "neoslam", "topology": topology, "mode": mode, "live": False},
        "source": {"kind": "synthetic", "params": {"seed": 0, "loop": True}},
    }
    if backbone:
        over["features"] = {"backbone": backbone}
    if overrides:
        from .runtime.config import merge_dicts

        over = merge_dicts(over, overrides)
    return load_config(config or "default", over)


def summarise(report: dict[str, Any], topology: str, rate: float, duration: float) -> dict[str, Any]:
    """One row of throughput.json from a run's report.json."""
    stages = {}
    for name, st in report.get("stages", {}).items():
        if st.get("missing"):
            stages[name] = {"missing": True}
            continue
        stages[name] = {"worker": st["worker"], "tau_p50_ms": st["tau_p50_ms"], "tau_p95_ms": st["tau_p95_ms"],
                        "tau_mean_ms": st["tau_mean_ms"], "processed": st["processed"],
                        "dropped": st["dropped"], "errors": st["errors"],
                        "cpu_percent": st.get("cpu_mean_percent", st.get("cpu_percent", 0.0)),
                        "rss_mb": st["rss_mb"]}
    a_info = report.get("stages", {}).get("A", {}).get("info", {})
    return {"topology": topology, "rate": rate, "duration_s": duration,
            "frames_in": report["frames_in"], "frames_processed": report["frames_out"],
            "loss": report["loss"], "f_in": report["f_in"], "f_out": report["f_out"],
            "stages": stages, "bottleneck": report["bottleneck"],
            "bottleneck_tau_ms": report["bottleneck_tau_ms"],
            "f_pipeline_predicted": report["f_pipeline_predicted"],
            "predicted_loss": report["predicted_loss"],
            "latency_p50_ms": report["latency_p50_ms"], "latency_p95_ms": report["latency_p95_ms"],
            "errors": report["errors"], "restarts": report.get("restarts", {}),
            "backbone": a_info.get("backbone"), "backbone_is_random": a_info.get("backbone_is_random"),
            "host": report.get("host")}  # what the hypervisor took over the run: a slow hour shows


def paper_table(runs: list[dict[str, Any]]) -> str:
    """The paper's Table I form: Algorithm | Processed Frames | Data Loss, one row per run."""
    rows = [("Algorithm", "Processed Frames", "Data Loss")]
    for r in sorted(runs, key=lambda r: (r["topology"], r["rate"])):
        name = f"neoslam-stream {r['topology']} @ {r['rate']:g} FPS"
        rows.append((name, f"{r['frames_processed']} of {r['frames_in']}", f"{100 * r['loss']:.1f} %"))
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) + " |" for row in rows]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def _longest(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One run per (topology, rate): the longest."""
    best: dict[tuple[str, float], dict[str, Any]] = {}
    for r in runs:
        key = (r["topology"], r["rate"])
        if key not in best or r["duration_s"] > best[key]["duration_s"]:
            best[key] = r
    return list(best.values())


def sustainable(runs: list[dict[str, Any]], topology: str) -> float | None:
    """Highest swept rate with loss below SUSTAINABLE_LOSS such that no lower rate failed."""
    best = None
    for r in sorted((r for r in _longest(runs) if r["topology"] == topology), key=lambda r: r["rate"]):
        if r["loss"] is None or r["loss"] >= SUSTAINABLE_LOSS:  # an unmeasured loss sustains nothing
            break
        best = r["rate"]
    return best


def rate_sweep(config: str | None, rates: list[float], duration: float, topologies: list[str], out: Path,
               backbone: str | None, overrides: dict[str, Any] | None = None,
               progress: bool = True) -> list[dict[str, Any]]:
    from .launch import run

    runs = []
    total = len(rates) * len(topologies)
    for i, (topo, rate) in enumerate(((t, r) for t in topologies for r in rates), 1):
        cfg = bench_config(config, topo, "realtime", backbone, overrides)
        cfg.run.name = f"throughput-{topo}-{rate:g}"
        cfg.source.rate = rate
        cfg.source.pacing = "fixed"
        cfg.source.duration = duration
        if progress:
            print(f"[{i}/{total}] {topo} at {rate:g} FPS for {duration:g} s ...", flush=True)
        res = run(cfg, out / "runs" / f"{topo}-{rate:g}")
        if res.interrupted:  # Ctrl-C / SIGTERM stops the bench, not just the run under way
            raise KeyboardInterrupt(f"interrupted during {topo} at {rate:g} FPS")
        row = summarise(res.report, topo, rate, duration)
        # what B computed and how many waiting frames a stage may take at once (docs/performance.md)
        row.update({"projection": cfg.projector.projection, "matrix_dtype": cfg.projector.matrix_dtype,
                    "feature_bits": cfg.projector.feature_bits, "max_batch": cfg.run.max_batch,
                    "nice": dict(cfg.run.nice), "cpus": dict(cfg.run.cpus), "tx_queue": cfg.bus.tx_queue,
                    "image_capacity": image_capacity(cfg, topo),
                    "loss_breakdown": res.report.get("loss_breakdown")})  # where frames were lost
        runs.append(row)
        if progress:
            print(f"      processed {row['frames_processed']} of {row['frames_in']}, loss {100 * row['loss']:.2f} %, "
                  f"bottleneck {row['bottleneck']} ({row['bottleneck_tau_ms']:.1f} ms), "
                  f"latency p50 {row['latency_p50_ms']:.0f} ms{_steal_note(row)}", flush=True)
    return runs


def _steal_note(row: dict[str, Any]) -> str:
    """", the hypervisor took 12.3 s of CPU" when it took any over the run (a shared machine)."""
    steal = (row.get("host") or {}).get("steal_s")
    return f", the hypervisor took {steal:.1f} s of CPU" if steal else ""


def image_capacity(cfg: FullRunConfig, topology: str) -> int:
    """The frames A's image ring holds in this run, by the supervisor's rule
    (runtime/topology.py ``queue_capacities``)."""
    from .nodes.pipelines import build_plan
    from .runtime.topology import queue_capacities

    caps = queue_capacities(build_plan(cfg), cfg.bus.capacity, topology == "monolithic")
    return int(caps.get("image", cfg.bus.default_capacity))


def _scaling_rows(stats_path: Path, step: int) -> list[dict[str, Any]]:
    """Sample stats.jsonl every ``step`` frames done (the experience map's processed count)."""
    rows, next_mark = [], step
    for line in stats_path.read_text().splitlines():
        try:
            snap = json.loads(line)
        except json.JSONDecodeError:
            continue
        stages = snap.get("stages", {})
        done = stages.get("experience_map", {}).get("processed", 0)
        if done < next_mark:
            continue
        next_mark = (done // step + 1) * step
        info = {n: st.get("info") or {} for n, st in stages.items()}
        rss_by_worker: dict[str, float] = {}
        pss_by_worker: dict[str, float | None] = {}
        for n, st in stages.items():  # stages sharing a worker share its memory: count each once
            rss_by_worker[str(st.get("worker", n))] = st.get("rss_mb") or 0.0
            pss_by_worker[str(st.get("worker", n))] = st.get("pss_mb")
        pss = list(pss_by_worker.values())
        rows.append({
            "frames": done, "t_s": snap["t_s"],
            "tau_recent_p50_ms": {n: st.get("tau_recent_p50_ms") for n, st in stages.items()},
            "tau_recent_p95_ms": {n: st.get("tau_recent_p95_ms") for n, st in stages.items()},
            "rss_mb": {n: st.get("rss_mb") for n, st in stages.items()},
            "rss_total_mb": sum(rss_by_worker.values()),
            # PSS counts pages shared between the processes (libraries) once in the sum
            "pss_total_mb": sum(pss) if pss and None not in pss else None,
            "tm_segments": info.get("C", {}).get("segments"), "tm_synapses": info.get("C", {}).get("synapses"),
            "svc_intervals": info.get("D", {}).get("intervals"), "svc_templates": info.get("D", {}).get("templates"),
            "svc_query_ms": stages.get("D", {}).get("tau_recent_p50_ms"),
            "em_experiences": info.get("experience_map", {}).get("experiences"),
            "em_links": info.get("experience_map", {}).get("links"),
            "em_relax_ms": info.get("experience_map", {}).get("relax_ms_last"),
        })
    return rows


def _fit_rss(rows: list[dict[str, Any]], at: int) -> float | None:
    """Least-squares line through the second half of the RSS curve, evaluated at ``at`` frames."""
    pts = [(r["frames"], r["rss_total_mb"]) for r in rows[len(rows) // 2:]]
    if len(pts) < 2:
        return None
    n = len(pts)
    mx = sum(x for x, _ in pts) / n
    my = sum(y for _, y in pts) / n
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    if sxx == 0:
        return None
    slope = sum((x - mx) * (y - my) for x, y in pts) / sxx
    return my + slope * (at - mx)


def scaling(config: str | None, frames: int, out: Path, backbone: str | None,
            overrides: dict[str, Any] | None = None, step: int = SCALING_STEP) -> dict[str, Any]:
    """A long lossless pipeline run; the curve of tau, RSS and state sizes every 1000 frames."""
    from .launch import run

    over = {"source": {"params": {"frames": frames, "loop": True}}}
    if overrides:
        from .runtime.config import merge_dicts

        over = merge_dicts(overrides, over)
    cfg = bench_config(config, "pipeline", "lossless", backbone, over)
    cfg.run.name = f"scaling-{frames}"
    print(f"scaling: {frames} frames lossless ...", flush=True)
    run_dir = out / "runs" / f"scaling-{frames}"
    res = run(cfg, run_dir)
    if res.interrupted:
        raise KeyboardInterrupt("interrupted during the scaling run")
    rows = _scaling_rows(run_dir / "stats.jsonl", step)
    final_rss = sum(st.get("rss_mb", 0.0) for st in _one_per_worker(res.report))
    out_rows = {"frames": res.report["frames_out"], "frames_in": res.report["frames_in"],
                "loss": res.report["loss"], "f_out": res.report["f_out"], "step": step,
                "rss_total_mb_end": final_rss, "rss_total_mb_at_100k_extrapolated": _fit_rss(rows, 100_000),
                "pss_total_mb_end": res.report.get("memory", {}).get("pss_total_mb"),
                "tau_p50_ms_end": {n: st.get("tau_p50_ms") for n, st in res.report["stages"].items()},
                "curve": rows}
    return out_rows


def _one_per_worker(report: dict[str, Any]) -> list[dict[str, Any]]:
    seen, rows = set(), []
    for st in report.get("stages", {}).values():
        if st.get("worker") not in seen:
            seen.add(st.get("worker"))
            rows.append(st)
    return rows


def plot(result: dict[str, Any], path: Path) -> None:
    """throughput.png: loss and output rate against input rate; the scaling curve when present."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = result.get("scaling")
    fig, axes = plt.subplots(1, 3 if sc else 2, figsize=(15 if sc else 10, 4))
    for topo in sorted({r["topology"] for r in result["runs"]}):
        rs = sorted((r for r in result["runs"] if r["topology"] == topo), key=lambda r: r["rate"])
        axes[0].plot([r["rate"] for r in rs], [float("nan") if r["loss"] is None else 100 * r["loss"] for r in rs], "o-", label=topo)
        axes[1].plot([r["rate"] for r in rs], [r["f_out"] for r in rs], "o-", label=topo)
    axes[0].set(xlabel="input rate (FPS)", ylabel="frame loss (%)", title="Frame loss")
    axes[1].set(xlabel="input rate (FPS)", ylabel="processed frames per second", title="Output rate")
    lim = max(r["rate"] for r in result["runs"])
    axes[1].plot([0, lim], [0, lim], "k:", lw=0.8, label="no loss")
    for ax in axes[:2]:
        ax.grid(alpha=0.3)
        ax.legend()
    if sc and sc["curve"]:
        c = sc["curve"]
        x = [r["frames"] for r in c]
        ax = axes[2]
        for st in ("A", "B", "C", "D", "pose_cells", "experience_map"):
            ys = [r["tau_recent_p50_ms"].get(st) for r in c]
            if any(y is not None for y in ys):
                ax.plot(x, ys, label=f"tau {st}")
        ax.axhline(1000 / 30, color="k", ls=":", lw=0.8, label="30 FPS budget")
        ax.set(xlabel="frames", ylabel="tau p50 of the last 1000 frames (ms)", title="Scaling")
        ax.grid(alpha=0.3)
        ax2 = ax.twinx()
        ax2.plot(x, [r["rss_total_mb"] for r in c], "k--", label="RSS total")
        ax2.set_ylabel("RSS of all workers (MB)")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_bench(config: str | None, rates: list[float], duration: float, topologies: list[str], out: Path,
              backbone: str | None, scaling_frames: int | None = None,
              overrides: dict[str, Any] | None = None, scaling_step: int = SCALING_STEP) -> dict[str, Any]:
    """The whole bench; writes ``out/throughput.json`` (and throughput.png) and returns it."""
    out.mkdir(parents=True, exist_ok=True)
    runs = rate_sweep(config, rates, duration, topologies, out, backbone, overrides) if rates else []
    result: dict[str, Any] = {"runs": runs}
    result["sustainable_rate"] = {t: sustainable(runs, t) for t in topologies} if runs else {}
    sp, sm = result["sustainable_rate"].get("pipeline"), result["sustainable_rate"].get("monolithic")
    result["pipeline_over_monolithic"] = sp / sm if sp and sm else None
    if scaling_frames:
        result["scaling"] = scaling(config, scaling_frames, out, backbone, overrides, scaling_step)
    if runs:
        result["paper_table"] = paper_table(runs)
    path = out / "throughput.json"
    if path.exists():  # keep what other invocations measured (e.g. the 5-minute run, the scaling run)
        try:
            old = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            old = {}
        result = _merge_results(old, result)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2, default=_finite))
    tmp.replace(path)
    if result["runs"]:
        plot(result, out / "throughput.png")
    return result


def _merge_results(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """New runs replace old ones with the same (topology, rate, duration); the rest is kept."""
    keys = {(r["topology"], r["rate"], r["duration_s"]) for r in new["runs"]}
    runs = [r for r in old.get("runs", []) if (r["topology"], r["rate"], r["duration_s"]) not in keys]
    runs += new["runs"]
    merged = {**old, **{k: v for k, v in new.items() if v is not None}, "runs": runs}
    merged["sustainable_rate"] = {t: sustainable(runs, t) for t in sorted({r["topology"] for r in runs})}
    sp, sm = merged["sustainable_rate"].get("pipeline"), merged["sustainable_rate"].get("monolithic")
    merged["pipeline_over_monolithic"] = sp / sm if sp and sm else None
    if runs:
        merged["paper_table"] = paper_table(runs)
    return merged


def _finite(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj)}")
