"""A picture of ``neoslam run --trace``'s timeline: a few frames' spans per stage.

Runs ``neoslam run --max-frames FRAMES --trace`` (or reads ``--trace FILE`` of an earlier run) and
draws, for ``--show`` frames from ``--first`` on, each stage's service span (a thick bar, one colour
per frame) and its queueing time before it (a thin bar), with a line through each frame's stages:
the pipeline serving several frames at once, one stage each. Writes bench/results/timeline.png
(docs/performance.md). Run: ``.venv/bin/python bench/timeline.py [--trace FILE] [--realtime --rate HZ]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.runtime.trace import read_trace  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def draw(events: list[dict], out: Path, first: int, show: int, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    threads = {(e["pid"], e["tid"]): e["args"]["name"] for e in events if e.get("name") == "thread_name"}
    procs = {e["pid"]: e["args"]["name"] for e in events if e.get("name") == "process_name"}
    frames = set(range(first, first + show))
    spans = [e for e in events if e["ph"] == "X" and frames & set(e["args"]["frames"])]
    t0 = min(e["ts"] for e in spans)
    rows = sorted({(e["pid"], e["tid"]) for e in spans})
    y = {r: len(rows) - 1 - i for i, r in enumerate(rows)}
    colours = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(10, 0.55 * len(rows) + 1.6))
    path: dict[int, list[tuple[float, float]]] = {}
    for e in spans:
        k = y[(e["pid"], e["tid"])]
        mine = sorted(frames & set(e["args"]["frames"]))
        x, w = (e["ts"] - t0) / 1e3, max(e["dur"] / 1e3, 0.05)
        ax.broken_barh([(x, w)], (k - 0.3, 0.6), color=colours(mine[0] % 10), alpha=0.9)
        if len(e["args"]["frames"]) > 1:
            ax.text(x + w / 2, k, f"x{len(e['args']['frames'])}", ha="center", va="center", fontsize=6, color="w")
        for f in mine:
            path.setdefault(f, []).append((x + w / 2, k))
    for e in events:
        if e.get("cat") == "queue" and e["ph"] == "b" and e["id"] in frames:
            end = next(x for x in events if x.get("cat") == "queue" and x["ph"] == "e" and x["id"] == e["id"]
                       and x["name"] == e["name"])
            k = y[(e["pid"], e["tid"])]
            ax.broken_barh([((e["ts"] - t0) / 1e3, (end["ts"] - e["ts"]) / 1e3)], (k - 0.08, 0.16),
                           color=colours(e["id"] % 10), alpha=0.35)
    for f, pts in path.items():
        pts.sort(key=lambda p: -p[1])
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "-", color=colours(f % 10), lw=0.6, alpha=0.6)
    ax.set_yticks([y[r] for r in rows])
    ax.set_yticklabels([f"{threads.get(r, '?')} ({procs.get(r[0], '?')})" if threads.get(r) != procs.get(r[0])
                        else threads.get(r, "?") for r in rows])
    ax.set_xlabel("ms since the first of these frames was published")
    ax.set_title(title, fontsize=9)
    ax.grid(axis="x", alpha=0.3)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trace", help="an existing trace file (default: run one)")
    ap.add_argument("--frames", type=int, default=200, help="frames of the run (without --trace)")
    ap.add_argument("--first", type=int, default=150, help="the first frame drawn")
    ap.add_argument("--show", type=int, default=8, help="frames drawn")
    ap.add_argument("--realtime", action="store_true", help="a live run (with --rate)")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--out", default=str(RESULTS / "timeline.png"))
    args = ap.parse_args()
    trace = args.trace
    mode = f"live at {args.rate:g} FPS" if args.realtime else "lossless"
    if trace is None:
        work = Path(tempfile.mkdtemp(prefix="timeline_"))
        trace = str(work / "trace.json")
        cmd = [sys.executable, "-m", "neoslam_stream.cli", "run", "--max-frames", str(args.frames), "--no-live",
               "--out", str(work / "run"), "--trace", trace]
        if args.realtime:
            cmd += ["--realtime", "--rate", str(args.rate)]
        subprocess.run(cmd, check=True)
    draw(read_trace(trace), Path(args.out), args.first, args.show,
         f"neoslam run --trace: frames {args.first}-{args.first + args.show - 1} of the default, {mode}, "
         "one process per stage (thin: waiting, thick: served; xN: a batch of N)")
    print(f"{args.out} from {trace}")


if __name__ == "__main__":
    main()
