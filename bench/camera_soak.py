"""An hour, live, from a served camera stream -> bench/results/camera_soak.json (+ camera_soak.png).

The shipped default's synthetic route (the ``synthetic`` source's frames at the default's camera
size, rendered once and cached as JPEGs) is served, looped, as an HTTP MJPEG stream at ``--rate``
FPS on loopback (bench/mjpeg_server.py, a thread of this process), and ``neoslam run --source
camera -p url=...`` reads it with the shipped default config for ``--duration`` seconds: in real
time (a live source's default) and without wheel odometry (a camera gives none: the run measures
visual odometry, as any camera run does; ``odometry`` in the JSON says what ran), with ``--trace``.
It writes:

* ``frames``: served by the stream, captured by the camera's thread, taken and published by the
  source, recognised by D (rows of templates.csv) and processed (reached the run's final topic);
  ``dropped``: each cause (the camera's one-frame slot, the stages' rings, transport, frames read
  before the run took its first, frames served but never read); ``outages`` with the reopenings;
* ``memory``: the RSS of every process of the run (supervisor, monitor, source, each worker; read
  by psutil as the workers report it in stats.jsonl, which bench/soak.py reads) every ``--every``
  seconds; ``memory_flat_range_mb``: max - min of their total after the first ``--flat-after``
  seconds (600), and ``memory_flat_within_50mb`` (bench/memory_flat.py: the verdict of both soaks);
* ``latency``: per frame, from its capture stamp (time.time() of the camera's thread when it read
  the frame; templates.csv's ``stamp``) to the end of D's service (the trace's D span, put back
  on the epoch by its origin): p50 / p95, every stage on the way, and minute by minute. Both are
  the wall clock of this machine (the stamps advance it by the monotonic clock from the camera's
  opening): ``clock_step_s`` says whether it was stepped meanwhile. The stamp is when OpenCV
  returned the frame (not its exposure); capture -> publication is about constant within a run
  (a live source without a rate is paced by its stamps from its first frame, so each frame waits
  what the first one waited: ``by_stage_ms.source``);
* ``report``: the run's own report.json loss figures.

``--kill-server-at S`` stops the stream S seconds after its first frame for ``--outage-s`` seconds
(once), so that the record shows an outage and its reopening.

Run: ``.venv/bin/python bench/camera_soak.py [--duration 3600] [--rate 30] [--every 10]
[--kill-server-at S] [--platform-speed MPS] [--out bench/results/camera_soak.json]``
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from memory_flat import FLAT_AFTER_S, memory_flat  # noqa: E402

#: the frames' JPEG quality (an IP camera's usual range)
JPEG_QUALITY = 90
#: the stages a frame passes up to its template, in order (the trace's names)
TO_TEMPLATE = ("source", "A", "B", "C", "D")

# ----------------------------------------------------------------------------- the stream
def route_jpegs(cache_dir: Path, quality: int = JPEG_QUALITY) -> tuple[list[bytes], dict[str, Any]]:
    """The default config's synthetic route, one frame per JPEG (BGR, as a camera sends it), rendered
    once into ``cache_dir`` (a stored zip named after the source's parameters, the renderer's code
    and the quality) and read from there afterwards."""
    from neoslam_stream.config import load_config
    from neoslam_stream.sources import synthetic

    src_cfg = load_config("default").source
    if src_cfg.kind != "synthetic":
        raise SystemExit(f"the default config's source is {src_cfg.kind!r}, not the synthetic world")
    params = dict(src_cfg.params)
    key = hashlib.sha1(json.dumps([params, quality, Path(synthetic.__file__).read_text()],
                                  sort_keys=True).encode()).hexdigest()[:12]
    path = cache_dir / f"route-{key}.zip"
    if not path.exists():
        from mjpeg_server import jpeg

        source = synthetic.SyntheticWorldSource(**params)
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as z:
            for f in source:  # one route (the default gives no frame count)
                z.writestr(f"{f.frame:06d}.jpg", jpeg(f.image[:, :, ::-1], quality))
        tmp.replace(path)
    with zipfile.ZipFile(path) as z:
        frames = [z.read(n) for n in sorted(z.namelist())]
    world = synthetic.SyntheticConfig(**params)
    return frames, {"frames": len(frames), "size": [world.width, world.height], "params": params,
                    "jpeg_quality": quality, "mean_jpeg_kb": round(sum(map(len, frames)) / len(frames) / 1024, 1),
                    "cache": str(path)}


def kill_server_once(server: Any, at_s: float, outage_s: float, record: dict[str, Any],
                     done: threading.Event) -> None:
    """Stop ``server`` ``at_s`` seconds after its first frame, start it again ``outage_s`` later."""
    while server.first_sent_at is None:
        if done.wait(0.2):
            return
    if done.wait(max(0.0, server.first_sent_at + at_s - time.time())):
        return
    record["stopped_s"] = round(time.time() - server.first_sent_at, 3)
    record["served_before"] = server.sent
    server.stop()
    done.wait(outage_s)
    server.start()
    record["restarted_s"] = round(time.time() - server.first_sent_at, 3)


# ----------------------------------------------------------------------------- memory
def process_label(proc: Any, root_pid: int) -> str:
    """What a process of the run is: ``supervisor`` (``neoslam run`` itself), a worker, ``monitor``
    or ``source`` (their ``neoslam-NAME`` process names, cut at 15 characters by the kernel), or
    its own name (multiprocessing's resource tracker)."""
    if proc.pid == root_pid:
        return "supervisor"
    name = proc.name()
    if name.startswith("neoslam-"):
        return name.removeprefix("neoslam-")
    try:
        if any("resource_tracker" in part for part in proc.cmdline()):
            return "resource_tracker"
    except Exception:  # gone, or not ours to read
        pass
    return name


class MemorySampler(threading.Thread):
    """Every ``every_s`` seconds: the RSS (MB) of every process of the run rooted at ``root_pid``,
    by :func:`process_label`, with the time (epoch) and the frames served so far."""

    def __init__(self, root_pid: int, every_s: float, served: Any) -> None:
        super().__init__(name="memory-sampler", daemon=True)
        self.root_pid, self.every_s, self.served = root_pid, every_s, served
        self.samples: list[dict[str, Any]] = []
        self.stop = threading.Event()

    def sample(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.root_pid)
            procs = [root, *root.children(recursive=True)]
        except psutil.Error:
            return
        rss: dict[str, float] = {}
        for p in procs:
            try:
                if p.status() == psutil.STATUS_ZOMBIE:  # ended, not yet reaped: no memory to count
                    continue
                label = process_label(p, self.root_pid)
                rss[label] = rss.get(label, 0.0) + p.memory_info().rss / 2**20
            except psutil.Error:  # ended between the listing and the reading
                continue
        self.samples.append({"time": time.time(), "served": self.served(),
                             "rss_mb": {k: round(v, 1) for k, v in sorted(rss.items())}})

    def run(self) -> None:
        while True:
            self.sample()
            if self.stop.wait(self.every_s):
                return


def worker_label(label: str, workers: list[str]) -> str:
    """The full worker name of a process label cut by the kernel (``experie`` -> ``experience_map``)."""
    for w in workers:
        if label != w and ("neoslam-" + w)[:15] == "neoslam-" + label:
            return w
    return label


def memory_rows(samples: list[dict[str, Any]], t0: float, workers: list[str]) -> list[dict[str, Any]]:
    """The samples as rows: ``t_s`` since ``t0`` (the first frame served; negative while the run
    starts), RSS per process with full worker names, and their total."""
    rows = []
    for s in samples:
        rss = {worker_label(k, workers): v for k, v in s["rss_mb"].items()}
        rows.append({"t_s": round(s["time"] - t0, 1), "served": s["served"], "rss_mb": rss,
                     "rss_total_mb": round(sum(rss.values()), 1)})
    return rows


# ----------------------------------------------------------------------------- latency
def read_stamps(templates_csv: Path) -> dict[int, float]:
    """frame -> its stamp (the camera's capture time) from a run's templates.csv."""
    stamps: dict[int, float] = {}
    with open(templates_csv) as fh:
        next(fh, None)
        for line in fh:
            parts = line.split(",", 2)
            if len(parts) >= 2:
                stamps[int(parts[0])] = float(parts[1])
    return stamps


def trace_finish_times(path: Path, stages: tuple[str, ...] = TO_TEMPLATE) -> dict[str, dict[int, float]]:
    """Per stage of ``stages``: frame -> the end of that stage's service for the frame (s since the
    epoch), from a ``--trace`` file's service spans (``ts + dur``, µs from the trace's origin), read
    line by line (an hour's trace is some hundred MB)."""
    from neoslam_stream.runtime.trace import trace_origin

    origin = trace_origin(path)
    if origin is None:
        raise ValueError(f"{path} records no origin (a trace written before it did): no epoch times")
    out: dict[str, dict[int, float]] = {s: {} for s in stages}
    wanted = set(stages)
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            if not line.startswith('{"ph":"X"'):
                continue
            try:
                e = json.loads(line.rstrip().rstrip(","))
            except json.JSONDecodeError:  # a line cut short by a killed monitor
                continue
            if e.get("name") in wanted:
                end = origin + (e["ts"] + e["dur"]) / 1e6
                for f in e["args"]["frames"]:
                    out[e["name"]][int(f)] = end
    return out


def _pcts(values: list[float]) -> dict[str, Any]:
    import numpy as np

    if not values:
        return {"n": 0, "p50": None, "p95": None, "mean": None, "min": None, "max": None}
    a = np.asarray(values) * 1e3
    return {"n": len(values), "p50": round(float(np.percentile(a, 50)), 2),
            "p95": round(float(np.percentile(a, 95)), 2), "mean": round(float(a.mean()), 2),
            "min": round(float(a.min()), 2), "max": round(float(a.max()), 2)}


def latency_figures(stamps: dict[int, float], finished: dict[str, dict[int, float]], t0: float | None = None,
                    stages: tuple[str, ...] = TO_TEMPLATE, bin_s: float = 60.0) -> dict[str, Any]:
    """Capture to template per frame: ``finished[D][f] - stamps[f]`` over the frames with both (ms:
    n, p50, p95, mean, min, max), the same from the capture to the end of every stage on the way
    (``by_stage_ms``: the source's is its publication), and p50 / p95 per ``bin_s`` seconds of
    capture time since ``t0`` (``over_time``: ``t_s`` the bin's start)."""
    import numpy as np

    last = stages[-1]
    frames = sorted(f for f in finished.get(last, {}) if f in stamps)
    lat = [finished[last][f] - stamps[f] for f in frames]
    out: dict[str, Any] = {"capture_to_template_ms": _pcts(lat), "by_stage_ms": {}}
    for s in stages:
        got = finished.get(s, {})
        out["by_stage_ms"][s] = _pcts([got[f] - stamps[f] for f in frames if f in got])
    if t0 is not None and frames:
        bins: dict[int, list[float]] = {}
        for f, v in zip(frames, lat, strict=True):
            bins.setdefault(int((stamps[f] - t0) // bin_s), []).append(v)
        out["bin_s"] = bin_s
        out["over_time"] = [{"t_s": round(k * bin_s, 3), "n": len(v),
                             "p50_ms": round(float(np.percentile(v, 50)) * 1e3, 2),
                             "p95_ms": round(float(np.percentile(v, 95)) * 1e3, 2)} for k, v in sorted(bins.items())]
    return out


# ----------------------------------------------------------------------------- frames
def served_until(sent_times: list[float], end: float | None) -> int:
    """The frames written by ``end`` (s, epoch; all of them when None)."""
    import bisect

    return len(sent_times) if end is None else bisect.bisect_right(sent_times, end)


def frame_figures(report: dict[str, Any], served: int, connections: int, templates: int) -> dict[str, Any]:
    """Where the frames went, from the run's report.json and the stream's counts: ``frames``,
    ``dropped`` by cause and ``outages`` (with the reopenings, as the camera and the server saw
    them). ``served``: the frames written while the run's stream lasted (the camera's figures in
    report.json stop when the stream ends, the server serves on until the run has drained)."""
    src = report.get("source") or {}
    cam = src.get("camera") or {}
    stages = report.get("stages") or {}
    evicted = {n: int(r.get("dropped_queue", 0)) for n, r in stages.items() if r.get("dropped_queue")}
    transport = {n: int(r.get("dropped_transport", 0)) for n, r in stages.items() if r.get("dropped_transport")}
    frames = {"served": served, "captured": cam.get("captured"), "taken_by_source": cam.get("taken"),
              "published": report.get("frames_in"), "templates": templates, "processed": report.get("frames_out")}
    dropped = {
        # replaced in the camera's one-frame slot before the source took them (the run's loss)
        "source_ring": cam.get("dropped"),
        # read while the run was starting, before the source's first take (not the run's loss)
        "before_first_take": cam.get("discarded_at_start"),
        "rings_evicted": evicted, "rings_evicted_total": sum(evicted.values()),
        "transport": transport, "transport_total": sum(transport.values()),
        "outage_frames_estimated": cam.get("outage_frames_missed"),
        "camera_skipped": cam.get("skipped") or {},
        # served but never read by the camera (FFmpeg's probe of a stream it opens, frames in the
        # socket when the stream was cut), to within a frame or two (the stream's end is estimated)
        "served_not_captured": served - int(cam.get("captured") or 0),
        "unattributed": (report.get("loss_breakdown") or {}).get("unattributed"),
    }
    outages = {"count": cam.get("outage_count"), "seconds": cam.get("outage_s"), "list": cam.get("outages") or [],
               "camera_reopenings": cam.get("outage_count"), "server_reopenings": max(0, connections - 1)}
    return {"frames": frames, "dropped": dropped, "outages": outages}


REPORT_KEYS = ("status", "mode", "f_in", "f_out", "frames_in", "frames_out", "frames_expected", "frames_lost",
               "frames_lost_at_source", "loss", "loss_percent", "loss_breakdown", "latency_p50_ms",
               "latency_p95_ms", "bottleneck", "bottleneck_tau_ms", "f_pipeline_predicted", "errors", "restarts",
               "memory", "host")


# ----------------------------------------------------------------------------- plot
def plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(17, 4.3))
    flat = res["memory"]["flat"]
    # the stream's time only (not the start-up nor the shut-down), each process from its first sample
    rows = [r for r in res["memory"]["samples"] if 0 <= r["t_s"] <= res["duration_s"]]
    t = [r["t_s"] / 60 for r in rows]
    if rows:
        ax[0].plot(t, [r["rss_total_mb"] - rows[0]["rss_total_mb"] for r in rows], "k-", lw=2,
                   label=f"all processes (from {rows[0]['rss_total_mb']:.0f} MB)")
        for name in sorted(rows[0]["rss_mb"]):
            ax[0].plot(t, [r["rss_mb"].get(name, float("nan")) - rows[0]["rss_mb"][name] for r in rows], lw=0.8,
                       label=name)
        ax[0].axvspan(flat["after_s"] / 60, t[-1], color="0.92", zorder=0, label="the verdict's window")
    ax[0].set(xlabel="minutes since the first frame served", ylabel="RSS growth since the first frame (MB)",
              title=f"Memory: {flat['range_mb']} MB range after {flat['after_s'] / 60:g} min")
    ax[0].legend(fontsize=6, ncol=2)
    lat = res["latency"]
    bins = lat.get("over_time") or []
    tb = [b["t_s"] / 60 for b in bins]
    ax[1].plot(tb, [b["p50_ms"] for b in bins], "o-", ms=3, label=f"p50 per {lat.get('bin_s', 60):g} s")
    ax[1].plot(tb, [b["p95_ms"] for b in bins], "s-", ms=3, label=f"p95 per {lat.get('bin_s', 60):g} s")
    for o in res["outages"]["list"]:
        start = (o["start"] - res["t0"]) / 60
        ax[1].axvspan(start, start + o["length_s"] / 60, color="tab:red", alpha=0.3, label="outage")
    c2t = lat["capture_to_template_ms"]
    ax[1].set(xlabel="minutes (capture time)", ylabel="ms", ylim=(0, None),
              title=f"Capture to template: p50 {c2t['p50']} / p95 {c2t['p95']} ms")
    ax[1].legend(fontsize=7)
    fr, dr = res["frames"], res["dropped"]
    labels = ["served", "captured", "published", "templates", "processed", "source ring", "rings", "outages (est.)"]
    vals = [fr["served"], fr["captured"] or 0, fr["published"] or 0, fr["templates"], fr["processed"] or 0,
            dr["source_ring"] or 0, dr["rings_evicted_total"], dr["outage_frames_estimated"] or 0]
    ax[2].barh(labels[::-1], vals[::-1], color=["tab:red"] * 3 + ["tab:blue"] * 5)
    for y, v in enumerate(vals[::-1]):
        ax[2].text(v, y, f" {v}", va="center", fontsize=7)
    loss = res["report"].get("loss_percent")
    ax[2].set(xlabel="frames", title=f"Frames (loss {loss:.2f} %)" if loss is not None else "Frames")
    for a in ax[:2]:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------- main
def analyse(run_dir: Path, trace: Path, server: Any, samples: list[dict[str, Any]], args: argparse.Namespace,
            extra: dict[str, Any]) -> dict[str, Any]:
    import yaml

    if not (run_dir / "report.json").exists():
        raise SystemExit(f"the run wrote no report.json (see {run_dir}): nothing to analyse")
    report = json.loads((run_dir / "report.json").read_text())
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    t0 = server.first_sent_at or time.time()
    workers = sorted({r.get("worker", n) for n, r in (report.get("stages") or {}).items()})
    rows = memory_rows(samples, t0, workers)
    stamps = read_stamps(run_dir / "templates.csv") if (run_dir / "templates.csv").exists() else {}
    # the stream's end, when the camera's figures in report.json stop: two frame periods after the
    # capture of the newest frame the run recorded (the source took one more, the slot held one)
    served = served_until(server.sent_times, max(stamps.values()) + 2.0 / args.rate if stamps else None)
    finished = trace_finish_times(trace) if trace.exists() else {}
    latency = latency_figures(stamps, finished, t0, bin_s=60.0 if args.duration >= 600 else 10.0)
    flat = memory_flat(rows, args.flat_after, until_s=args.duration)
    vo = (report.get("stages") or {}).get("visual_odometry") or {}
    res: dict[str, Any] = {
        "rate": args.rate, "duration_s": args.duration, "config": "default (shipped)", "t0": t0,
        "mode": report.get("mode"), "odometry": cfg.get("odometry"),
        "visual_odometry_frames": vo.get("processed"),
        "wheel_odometry_received": (report.get("source") or {}).get("odometry_received"),
        **extra,
        **frame_figures(report, served, server.connections, len(stamps)),
        "served_after_stream_end": server.sent - served,
        "memory_flat_range_mb": flat["range_mb"], "memory_flat_within_50mb": flat["flat"],
        "latency_capture_to_template_p50_ms": latency["capture_to_template_ms"]["p50"],
        "latency_capture_to_template_p95_ms": latency["capture_to_template_ms"]["p95"],
        "latency": latency,
        "memory": {"every_s": args.every, "flat": flat,
                   "first_total_mb": rows[0]["rss_total_mb"] if rows else None,
                   "last_total_mb": rows[-1]["rss_total_mb"] if rows else None, "samples": rows},
        "report": {k: report.get(k) for k in REPORT_KEYS},
        "run_dir": str(run_dir),
    }
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=3600.0, help="seconds of the run (default 3600)")
    ap.add_argument("--rate", type=float, default=30.0, help="frames per second the stream serves (30)")
    ap.add_argument("--every", type=float, default=10.0, help="seconds between two memory samples (10)")
    ap.add_argument("--flat-after", type=float, default=FLAT_AFTER_S,
                    help="the memory verdict's window starts this many seconds after the first frame (600)")
    ap.add_argument("--kill-server-at", type=float, metavar="S",
                    help="stop the stream S seconds after its first frame, once (default: never)")
    ap.add_argument("--outage-s", type=float, default=5.0, help="how long --kill-server-at stops it (5 s)")
    ap.add_argument("--platform-speed", type=float, metavar="MPS",
                    help="the run's platform.speed_mps (default: the shipped default's). The route was "
                         "recorded at 10 Hz, so served at --rate FPS it moves rate / 10 times as fast: "
                         "0.9 at 30 FPS says what a user of that camera would")
    ap.add_argument("--keep-trace", action="store_true",
                    help="keep the run's trace.json (an hour's is ~300 MB; deleted once read by default)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "camera_soak.json"))
    args = ap.parse_args()
    out = Path(args.out)
    work = out.parent / "camera_soak_runs"
    run_dir, trace = work / "run", work / "run" / "trace.json"

    from mjpeg_server import MjpegServer

    frames, route = route_jpegs(work)
    print(f"route: {route['frames']} frames {route['size'][0]}x{route['size'][1]}, "
          f"{route['mean_jpeg_kb']} kB a JPEG, served at {args.rate:g} FPS", flush=True)
    server = MjpegServer(args.rate, lambda i: frames[i % len(frames)], keep_times=True).start()
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [sys.executable, "-m", "neoslam_stream.cli", "run", "--source", "camera", "-p", f"url={server.url}",
           "--duration", f"{args.duration:g}", "--no-live", "--trace", str(trace), "--out", str(run_dir)]
    if args.platform_speed is not None:  # a config of one's own: applied on top of the shipped default
        overlay = work / "platform.yaml"
        overlay.write_text(f"platform:\n  speed_mps: {args.platform_speed:g}\n")
        cmd += ["-c", str(overlay)]
    done = threading.Event()
    kill: dict[str, Any] = {}
    if args.kill_server_at is not None:
        kill = {"at_s": args.kill_server_at, "outage_s": args.outage_s}
        threading.Thread(target=kill_server_once, args=(server, args.kill_server_at, args.outage_s, kill, done),
                         daemon=True).start()
    clock0 = time.time() - time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT)
    sampler = MemorySampler(proc.pid, args.every, lambda: server.sent)
    sampler.start()
    try:
        rc = proc.wait()
    except KeyboardInterrupt:  # Ctrl-C reached the run too: it stops with every output
        rc = proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(120)
        done.set()
        sampler.stop.set()
        sampler.join(5)
        server.stop()
    # the capture stamps count from the wall clock read when the camera opened, advanced by the
    # monotonic clock; the stages read the wall clock: they agree unless the wall clock was stepped
    clock_step = (time.time() - time.monotonic()) - clock0
    extra = {"command": " ".join(cmd[1:]), "exit_code": rc, "route": route, "kill_server": kill or None,
             "platform_speed_mps": args.platform_speed,
             "clock_step_s": round(clock_step, 6)}
    res = analyse(run_dir, trace, server, sampler.samples, args, extra)
    if trace.exists() and not args.keep_trace:
        res["trace_mb"] = round(trace.stat().st_size / 2**20, 1)
        trace.unlink()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    plot(res, out.with_suffix(".png"))
    brief = {k: res[k] for k in ("frames", "dropped", "memory_flat_range_mb", "memory_flat_within_50mb",
                                 "latency_capture_to_template_p50_ms", "latency_capture_to_template_p95_ms",
                                 "odometry", "mode", "clock_step_s")}
    brief["outages"] = {k: v for k, v in res["outages"].items() if k != "list"}
    brief["loss_percent"] = res["report"]["loss_percent"]
    print(json.dumps(brief, indent=2))
    print(f"wrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
