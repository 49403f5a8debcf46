"""Temporal Memory benchmark with NeoSLAM's parameters -> bench/results/tm.json.

Inputs (512 active columns of 2048 each step, generated here, seeded):
* ``repeat``: a fixed sequence of 50 random SDRs repeated 20 times (1000 steps);
* ``route``: 300 places, each step moves on with probability 0.5 or stays, every step with 10 % of
  the place's bits resampled, 3 laps (~1800 steps);
* ``random``: 3000 independent random SDRs (the worst case).

Per kind: steps/s overall and over the last 500 steps, segments and synapses at the end, peak RSS,
and the share of winners that are cell 0 / the column's most frequent winner (sequence context).
Reference: htm.core C++ on this kind of machine (``HTM_CORE_MEDIAN``; docs/temporal_memory.md).
Run: ``.venv/bin/python bench/tm.py [--tie-break random]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.algorithms.neocortex import Neocortex  # noqa: E402

HTM_CORE_MEDIAN = {"repeat": 171, "route": 90, "random": 83}


def sdr(rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(2048, 512, replace=False))


def inputs(kind: str, seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    if kind == "repeat":
        seq = [sdr(rng) for _ in range(50)]
        return [seq[i % 50] for i in range(1000)]
    if kind == "route":
        places = [sdr(rng) for _ in range(300)]
        out, p, lap = [], 0, 0
        while lap < 3:
            base = places[p]
            keep = rng.choice(512, int(512 * 0.9), replace=False)
            kept = base[keep]
            rest = np.setdiff1d(np.arange(2048), kept)
            out.append(np.sort(np.concatenate([kept, rng.choice(rest, 512 - kept.size, replace=False)])))
            if rng.random() < 0.5:
                p += 1
                if p == 300:
                    p, lap = 0, lap + 1
        return out
    if kind == "random":
        return [sdr(rng) for _ in range(3000)]
    raise ValueError(kind)


def run(kind: str, tie_break: str) -> dict:
    xs = inputs(kind)
    nc = Neocortex(tie_break=tie_break)
    warm = Neocortex(tie_break=tie_break)  # compile outside the timing
    warm.compute(xs[0])
    warm.compute(xs[1])
    times = np.empty(len(xs))
    per_cell = np.zeros(nc.n_cells, dtype=np.int64)  # how often each cell won
    for i, x in enumerate(xs):
        t = time.perf_counter()
        w = nc.compute(x)
        times[i] = time.perf_counter() - t
        per_cell[w] += 1
    per_col = per_cell.reshape(-1, nc.config.cells_per_column)
    return {"steps": len(xs), "steps_per_s": len(xs) / times.sum(),
            "steps_per_s_last500": 500 / times[-500:].sum(),
            "step_ms_p50": float(np.median(times) * 1e3), "step_ms_max": float(times.max() * 1e3),
            "segments": nc.tm.segments, "synapses": nc.tm.synapses,
            "mean_anomaly": nc.anomaly_sum / nc.steps,
            # context check: a share near 1 means each column always picks the same cell
            "winners_in_cell0": float(per_col[:, 0].sum() / per_cell.sum()),
            "winners_in_modal_cell_of_column": float(per_col.max(axis=1).sum() / per_cell.sum()),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "htm_core_median_steps_per_s": HTM_CORE_MEDIAN[kind]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tie-break", choices=["lowest", "random"], default="lowest")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "tm.json"))
    args = ap.parse_args()
    res = {"tie_break": args.tie_break}
    for kind in ("repeat", "route", "random"):
        res[kind] = run(kind, args.tie_break)
        print(kind, {k: round(v, 3) if isinstance(v, float) else v for k, v in res[kind].items()}, flush=True)
    if args.tie_break == "lowest":
        res["random_tie_break"] = {k: run(k, "random") for k in ("repeat", "route")}
        print("random tie break", res["random_tie_break"], flush=True)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
