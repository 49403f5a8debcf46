"""Front-end benchmark: service time of stages A, B, D and Nordland loop-closure quality.

Writes bench/results/frontend.json with the keys a_ms_batch1, a_ms_batched, b_ms_gaussian_batch1,
b_ms_gaussian_batched, b_ms_sparse, d_ms_k1000, d_ms_k10000, d_ms_k100000, nordland_precision,
nordland_recall, backbone (plus details). Times are medians (p50) per frame on this machine.

Run: ``.venv/bin/python bench/frontend.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nordland import DATA, run_frontend  # noqa: E402

from stages.features import VisualFeatureExtractor  # noqa: E402
from stages.projector import BinaryProjector  # noqa: E402
from stages.spatial_view import SpatialViewCells  # noqa: E402


def p50(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def bench_a(backbone: str, reps: int, batch: int, threads: int) -> tuple[float, float]:
    torch.set_num_threads(threads)
    fx = VisualFeatureExtractor(backbone=backbone, threads=threads)
    img = np.random.default_rng(0).integers(0, 256, (240, 416, 3), dtype=np.uint8)
    fx.extract(img)
    b1 = p50(lambda: fx.extract(img), reps)
    imgs = [img] * batch
    bb = p50(lambda: fx.extract_batch(imgs), max(3, reps // batch)) / batch
    return b1, bb


def bench_b(reps: int, batch: int) -> dict:
    out = {}
    rng = np.random.default_rng(0)
    f = rng.standard_normal(64896).astype(np.float32)
    fb = np.stack([f] * batch)
    g = BinaryProjector(projection="gaussian")
    out["b_ms_gaussian_batch1"] = p50(lambda: g.bits(f), reps)
    out["b_ms_gaussian_batched"] = p50(lambda: g.bits_batch(fb), max(3, reps // batch)) / batch
    s = BinaryProjector(projection="sparse")
    out["b_ms_sparse"] = p50(lambda: s.bits(f), reps)
    out["b_ms_sparse_batched"] = p50(lambda: s.bits_batch(fb), max(3, reps // batch)) / batch
    return out


def bench_d(k: int, reps: int) -> float:
    """Per-frame time with K intervals of random 512-cell SDRs (new interval each frame)."""
    rng = np.random.default_rng(k)
    svc = SpatialViewCells()
    pool = [np.sort(rng.choice(65536, 512, replace=False)).astype(np.uint32) for _ in range(256)]
    for i in range(k):
        svc.compute(pool[i % 256] ^ np.uint32(i % 64))  # cheap variety; unions stay 512 cells
    queries = [np.sort(rng.choice(65536, 512, replace=False)).astype(np.uint32) for _ in range(reps)]
    it = iter(queries)
    return p50(lambda: svc.compute(next(it)), reps)


def compare_tie_rules(path: Path, step: int = 8) -> None:
    """Loop-closure quality with the real neocortex, htm.core's tie rule vs NuPIC's."""
    from stages.neocortex import Neocortex

    res = json.loads(path.read_text()) if path.exists() else {}
    svc = dict(theta_alpha=384, theta_rho=3, theta_sigma=470, exclude_recent_intervals=3)
    out = {}
    for rule in ("lowest", "random"):
        nc = Neocortex(tie_break=rule)
        runs = run_frontend("efficientnet_lite0", step, [svc, {**svc, "theta_sigma": 400}], tolerance=150,
                            neocortex=nc.compute)
        out[rule] = {"sigma470": runs[0], "sigma400": runs[1]}
        print(rule, [{k: r[k] for k in ("closures", "correct", "precision", "recall")} for r in runs], flush=True)
    res["nordland_tm_tie_break"] = out
    path.write_text(json.dumps(res, indent=2))
    print(f"merged nordland_tm_tie_break into {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, K up to 10k, Nordland subset")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "frontend.json"))
    ap.add_argument("--timing-only", action="store_true",
                    help="re-measure A, B, D and keep the Nordland results already in --out")
    ap.add_argument("--tm-compare", action="store_true",
                    help="only compare the TM tie rules on Nordland (real neocortex) and merge into --out")
    args = ap.parse_args()
    if args.tm_compare:
        compare_tie_rules(Path(args.out))
        return
    reps = 10 if args.quick else 30
    previous = json.loads(Path(args.out).read_text()) if Path(args.out).exists() else {}
    res: dict = {"threads": args.threads}
    if args.timing_only:
        res.update({k: v for k, v in previous.items() if k.startswith("nordland") or k == "backbone"})
    a1, ab = bench_a("random_alexnet", reps, 8, args.threads)
    res.update({"a_ms_batch1": a1, "a_ms_batched": ab, "a_backbone_timed": "random_alexnet (same cost as alexnet)"})
    e1, eb = bench_a("efficientnet_lite0", reps, 8, args.threads)
    res.update({"a_ms_efficientnet_batch1": e1, "a_ms_efficientnet_batched": eb})
    print("A", res, flush=True)
    res.update(bench_b(reps, 8))
    print("B", res, flush=True)
    for k in (1000, 10000) + (() if args.quick else (100000,)):
        res[f"d_ms_k{k}"] = bench_d(k, 200)
        print("D", k, res[f"d_ms_k{k}"], flush=True)
    if args.quick:
        res["d_ms_k100000"] = None
    if DATA.is_dir() and not args.timing_only:
        svc = dict(theta_alpha=384, theta_rho=3, theta_sigma=470, exclude_recent_intervals=3)
        step = 8 if args.quick else 2
        runs = {}
        sigmas = (470, 440, 400)
        for bb in ("efficientnet_lite0", "random_alexnet"):
            rs = run_frontend(bb, step, [{**svc, "theta_sigma": s} for s in sigmas], tolerance=150)
            for sigma, r in zip(sigmas, rs, strict=True):
                runs[f"{bb}_sigma{sigma}"] = r
                print("Nordland", bb, sigma, {k: r[k] for k in ("closures", "correct", "precision", "recall")},
                      flush=True)
        main_run = runs["efficientnet_lite0_sigma470"]
        res.update({"nordland_precision": main_run["precision"], "nordland_recall": main_run["recall"],
                    "backbone": main_run["backbone"], "nordland_runs": runs,
                    "nordland_method": f"summer then winter, every {step}th thumbnail, pass-through neocortex "
                                       "(cell 0 of each active column), tolerance +-150 source frames "
                                       "(+-15 thumbnails, the dataset's sample ground-truth tolerance)"})
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
