"""Stage A of the shipped default: its cost per frame, and what running it frozen changes.

``features.inference``: ``eager`` (the module as written) against ``frozen`` (traced, frozen and
optimised for inference on a CPU, the default). Time: the default's backbone on one thread, one
frame at a time (preprocessing included), on the embedded synthetic world's frames, both variants
interleaved in three rounds; and the frozen backbone on batches of 1-8 frames (``by_batch``: the
first call of each batch size, which ``warm_up`` pays before a live run, and the time per frame
after it); and the frozen backbone at the reference's 224 against the default's input size
(``input_size``), interleaved. Closures: B's bits from each variant on the same frames (the default
route's first 1000 frames, Nordland's summer and winter test subset), in order through the same
running centring; a frame whose bits differ is counted (identical bits give identical templates
downstream). Writes bench/results/stage_a.json.

Run: ``.venv/bin/python bench/stage_a.py [--out bench/results/stage_a.json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from bench_settings import load_settings  # noqa: E402
from nordland import load_frames  # noqa: E402

from neoslam_stream.algorithms.features import VisualFeatureExtractor  # noqa: E402
from neoslam_stream.algorithms.frontend import FrontEnd  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402

VARIANTS = ("eager", "frozen")


def _interleaved(fx: dict[Any, VisualFeatureExtractor], frames: list[np.ndarray], rounds: int) -> dict[Any, list[float]]:
    """Seconds per frame of each extractor, one frame at a time (preprocessing included), after ten
    warm-up frames each, the extractors taking turns over ``frames`` in each of ``rounds``."""
    for f in fx.values():
        for im in frames[:10]:
            f.extract(im)
    t: dict[Any, list[float]] = {k: [] for k in fx}
    for _ in range(rounds):
        for k, f in fx.items():
            for im in frames:
                t0 = time.perf_counter()
                f.extract(im)
                t[k].append(time.perf_counter() - t0)
    return t


def timing(frames: list[np.ndarray], rounds: int = 3) -> dict[str, dict[str, float]]:
    cfg = load_config("default").features
    fx = {v: VisualFeatureExtractor(cfg.model_copy(update={"inference": v, "threads": 1})) for v in VARIANTS}
    t = _interleaved(fx, frames, rounds)
    return {v: {"backbone": fx[v].backbone, "p50_ms": 1e3 * float(np.median(x)), "mean_ms": 1e3 * float(np.mean(x)),
                "p95_ms": 1e3 * float(np.percentile(x, 95)), "frames": len(x)} for v, x in t.items()}


def by_batch(frames: list[np.ndarray], max_batch: int = 8, rounds: int = 8) -> dict[str, dict[str, float]]:
    """The frozen backbone (one thread) on batches of 1..``max_batch`` frames: the first call of each
    size on a fresh extractor (what ``warm_up`` pays before a live run), then the median time per
    frame over ``rounds`` calls of each size, interleaved."""
    cfg = load_config("default").features.model_copy(update={"inference": "frozen", "threads": 1})
    fx = VisualFeatureExtractor(cfg)
    first = {}
    for n in range(1, max_batch + 1):
        t0 = time.perf_counter()
        fx.extract_batch(frames[:n])
        first[n] = 1e3 * (time.perf_counter() - t0)
    fx.warm_up(max_batch)
    t: dict[int, list[float]] = {n: [] for n in range(1, max_batch + 1)}
    for _ in range(rounds):
        for n in t:
            t0 = time.perf_counter()
            fx.extract_batch(frames[:n])
            t[n].append(1e3 * (time.perf_counter() - t0) / n)
    return {str(n): {"first_call_ms": first[n], "p50_ms_per_frame": float(np.median(t[n]))} for n in t}


def by_input_size(frames: list[np.ndarray], rounds: int = 3) -> dict[str, Any]:
    """The frozen backbone (one thread, one frame at a time, preprocessing included) at the
    reference's 224 and at the default's input size, interleaved in ``rounds``: the ratio of one run."""
    cfg = load_config("default").features.model_copy(update={"inference": "frozen", "threads": 1})
    sizes = sorted({224, cfg.input_size}, reverse=True)
    fx = {s: VisualFeatureExtractor(cfg.model_copy(update={"input_size": s})) for s in sizes}
    t = _interleaved(fx, frames, rounds)
    res: dict[str, Any] = {str(s): {"p50_ms": 1e3 * float(np.median(x)), "p95_ms": 1e3 * float(np.percentile(x, 95)),
                                    "features": fx[s].output_dim, "frames": len(x)} for s, x in t.items()}
    res["default"] = cfg.input_size
    res["ratio_p50"] = res[str(cfg.input_size)]["p50_ms"] / res["224"]["p50_ms"]
    return res


def bits_agreement(frames: list[np.ndarray]) -> dict[str, int]:
    bits = {}
    for v in VARIANTS:
        cfg = load_config("default")
        cfg.features.inference = v
        fe = FrontEnd(cfg.front_end().resolved())
        bits[v] = [b for i in range(0, len(frames), 8) for b in fe.bits_of_frames(frames[i:i + 8])]
    diff = [len(np.setxor1d(a, b)) for a, b in zip(bits["eager"], bits["frozen"], strict=True)]
    return {"frames": len(frames), "frames_differing": sum(1 for d in diff if d), "bits_differing": sum(diff)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "stage_a.json"))
    args = ap.parse_args()
    cfg = load_config("default")
    route = [sf.image for sf in SyntheticWorldSource(**{**cfg.source.params, "frames": 1000})]
    proto = load_settings("nordland")["protocol"]
    summer, winter, _ = load_frames(proto["step"], min_std=proto["min_std"])
    res = {"time_per_frame": timing(route[:200]), "by_batch": by_batch(route[:8]),
           "input_size": by_input_size(route[:200]),
           "bits": {"synthetic_route_1000": bits_agreement(route),
                    "nordland_summer_winter": bits_agreement(summer + winter)}}
    e, f = res["time_per_frame"]["eager"], res["time_per_frame"]["frozen"]
    res["speedup_p50"] = e["p50_ms"] / f["p50_ms"]
    Path(args.out).write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
