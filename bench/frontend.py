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

from nordland import DATA, run_frontend  # noqa: E402
from timing import p50  # noqa: E402

from neoslam_stream.algorithms.features import VisualFeatureExtractor  # noqa: E402
from neoslam_stream.algorithms.projector import BinaryProjector  # noqa: E402
from neoslam_stream.algorithms.spatial_view import SpatialViewCells  # noqa: E402


def bench_a(backbone: str, reps: int, batch: int, threads: int) -> tuple[float, float]:
    torch.set_num_threads(threads)
    fx = VisualFeatureExtractor(backbone=backbone, threads=threads)
    img = np.random.default_rng(0).integers(0, 256, (240, 416, 3), dtype=np.uint8)
    fx.extract(img)
    b1 = p50(lambda: fx.extract(img), reps)
    imgs = [img] * batch
    bb = p50(lambda: fx.extract_batch(imgs), max(3, reps // batch)) / batch
    return b1, bb


def bench_b(reps: int, batch: int, threads: int) -> dict:
    out = {}
    rng = np.random.default_rng(0)
    f = rng.standard_normal(64896).astype(np.float32)
    fb = np.stack([f] * batch)
    g = BinaryProjector(projection="gaussian", threads=threads)
    out["b_ms_gaussian_batch1"] = p50(lambda: g.bits(f), reps)
    out["b_ms_gaussian_batched"] = p50(lambda: g.bits_batch(fb), max(3, reps // batch)) / batch
    s = BinaryProjector(projection="sparse")
    out["b_ms_sparse"] = p50(lambda: s.bits(f), reps)
    out["b_ms_sparse_batched"] = p50(lambda: s.bits_batch(fb), max(3, reps // batch)) / batch
    return out


def bench_b_storage(rounds: int, n: int = 64896) -> dict:
    """B's Gaussian projection on ONE thread, float32, float16 and int8 storage of P (int8 with
    16-bit and with 7-bit features: real_sdrs.VARIANTS), interleaved in one process (each variant
    in turn, the order rotating, ``rounds`` times; medians), so all see the same machine load; each
    with 1, 2 and 4 frames per call (micro-batches: the node gets every frame waiting in its queue,
    up to ``run.max_batch``), per frame."""
    from real_sdrs import VARIANTS

    rng = np.random.default_rng(0)
    fs = rng.standard_normal((4, n)).astype(np.float32)
    dtypes = tuple(VARIANTS)
    projs = {d: BinaryProjector(projection="gaussian", threads=1, input_dim=n, **VARIANTS[d]) for d in dtypes}
    times: dict[tuple[str, int], list[float]] = {(d, b): [] for d in dtypes for b in (1, 2, 4)}
    for p in projs.values():
        p.warm_up()
    for r in range(rounds):
        order = dtypes[r % len(dtypes):] + dtypes[: r % len(dtypes)]  # each variant goes first, ..., last in turn
        for d in order:
            for b in (1, 2, 4):
                t0 = time.perf_counter()
                projs[d].bits_batch(fs[:b])
                times[d, b].append((time.perf_counter() - t0) * 1e3 / b)
    med = {k: float(np.median(v)) for k, v in times.items()}
    out = {f"b_ms_gaussian_batch1_{d}_1thread": med[d, 1] for d in dtypes}
    out.update({f"b_ms_gaussian_{d}_batch{b}_1thread": med[d, b] for d in dtypes for b in (2, 4)})
    out.update({"b_float16_over_float32": med["float16", 1] / med["float32", 1],
                "b_int8_over_float32": med["int8", 1] / med["float32", 1],
                "b_int8_7bit_over_float32": med["int8_7bit", 1] / med["float32", 1], "b_storage_rounds": rounds,
                "b_storage_conditions": f"one thread, n = {n}, {'/'.join(dtypes)} interleaved in one "
                                        f"process, {rounds} rounds, medians"})
    return out


def _loaded_svc(k: int) -> tuple[np.random.Generator, list[np.ndarray], SpatialViewCells]:
    """Spatial-view cells holding K intervals whose unions are random 512-cell SDRs."""
    rng = np.random.default_rng(k)
    unions = [np.sort(rng.choice(65536, 512, replace=False)).astype(np.uint32) for _ in range(k)]
    svc = SpatialViewCells()
    svc.load_state_dict({"params": [384, 3, 470, 3, 65536], "unions": unions, "start": np.arange(k),
                         "end": np.arange(k), "template": np.arange(k), "n_templates": k,
                         "current_template": k - 1, "t": k})
    return rng, unions, svc


def bench_d(k: int, reps: int) -> float:
    """Per-frame time with K intervals whose unions are random 512-cell SDRs of 65536 cells.

    The K intervals are restored through ``load_state_dict`` (which builds the inverted index like
    K frames would, without K scoring passes), then ``reps`` random SDRs are processed.
    """
    rng, unions, svc = _loaded_svc(k)
    queries = [np.sort(rng.choice(65536, 512, replace=False)).astype(np.uint32) for _ in range(reps)]
    it = iter(queries)
    return p50(lambda: svc.compute(next(it)), reps)


def bench_d_compaction(k: int) -> float:
    """Duration (ms) of one merge of the linked postings into the CSR index at K intervals, when the
    linked part holds a quarter of the CSR part (the moment it happens in a run)."""
    _rng, unions, svc = _loaded_svc(k)
    for q in range(k // 4 - 1):  # fill the linked part just below the threshold
        svc.index.post(unions[q].astype(np.int32), k + q)
    t0 = time.perf_counter()
    svc.index.compact()
    return (time.perf_counter() - t0) * 1e3


#: the protocol of tests/test_frontend_nordland.py (see bench/nordland.py and docs/frontend.md)
PROTOCOL = dict(tolerance=150, min_std=10.0)


def _brief(r: dict) -> dict:
    return {k: r[k] for k in ("closures", "correct", "precision", "recall", "svc")}


def _agreement(a: dict, b: dict, tolerance: int = 150) -> dict:
    """How often two runs give the same loop closures: same winter frames, same matched place."""
    fa, fb = set(a["closure_origin"]), set(b["closure_origin"])
    both = fa & fb
    same_place = sum(1 for j in both if a["closure_origin"][j] >= 0 and b["closure_origin"][j] >= 0
                     and abs(a["closure_origin"][j] - b["closure_origin"][j]) <= tolerance)
    return {"closures_a": len(fa), "closures_b": len(fb), "same_frames": len(both),
            "same_frames_and_place": same_place,
            "jaccard_frames": len(both) / len(fa | fb) if fa | fb else None}


def nordland(step_main: int, step_side: int) -> dict:
    """Loop-closure quality on Nordland: the main configuration and the variants it is compared with."""
    runs: dict = {}
    cal, paper = {"theta_sigma": None}, {"theta_sigma": 470}  # D otherwise the paper's (its defaults)
    main_cfg = dict(centre_window=100, **PROTOCOL)
    r = run_frontend("efficientnet_lite0", step_main, [cal, paper], **main_cfg)
    runs["efficientnet_lite0_centred_calibrated"], runs["efficientnet_lite0_centred_sigma470"] = r
    print("Nordland main", _brief(r[0]), flush=True)
    side = {
        "efficientnet_lite0_raw": ("efficientnet_lite0", dict(centre_window=0, **PROTOCOL), "passthrough", "gaussian"),
        "random_alexnet_centred": ("random_alexnet", main_cfg, "passthrough", "gaussian"),
        "efficientnet_lite0_centred_gaussian_side": ("efficientnet_lite0", main_cfg, "passthrough", "gaussian"),
        "efficientnet_lite0_centred_sparse_side": ("efficientnet_lite0", main_cfg, "passthrough", "sparse"),
    }
    for name, (bb, cfg, nc, proj) in side.items():
        rs = run_frontend(bb, step_side, [cal, paper], neocortex=nc, projection=proj, **cfg)
        runs[f"{name}_calibrated"], runs[f"{name}_sigma470"] = rs
        print("Nordland", name, _brief(rs[0]), flush=True)
    agreement = _agreement(runs["efficientnet_lite0_centred_gaussian_side_calibrated"],
                           runs["efficientnet_lite0_centred_sparse_side_calibrated"])
    tie = {}
    for rule in ("lowest", "random"):
        rs = run_frontend("efficientnet_lite0", step_side, [cal], neocortex={"tie_break": rule}, **main_cfg)
        tie[rule] = rs[0]
        print("Nordland TM", rule, _brief(rs[0]), flush=True)
    main_run = runs["efficientnet_lite0_centred_calibrated"]
    for r in list(runs.values()) + [v for v in tie.values() if isinstance(v, dict)]:
        r.pop("closure_origin", None)
    return {"nordland_precision": main_run["precision"], "nordland_recall": main_run["recall"],
            "backbone": main_run["backbone"], "nordland_runs": runs,
            "nordland_sparse_vs_gaussian": agreement, "nordland_tm_tie_break": tie,
            "nordland_method": (
                f"summer then winter through the nodes of A, B, C (pass-through: cell 0 of each active "
                f"column) and D; every {step_main}th thumbnail for the main run, every {step_side}th for the "
                "variants; places with a featureless frame (grey std < 10: tunnels) left out of both seasons; "
                "B centres features with a running mean (window 100); theta_sigma calibrated on the summer "
                "pass alone (99.9th percentile of overlaps between summer frames > 150 source frames apart); "
                "a closure is correct when its template was created within +-150 source frames of the place")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer repetitions, smaller Nordland subset")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "frontend.json"))
    ap.add_argument("--storage-and-real-sdrs", action="store_true",
                    help="only the storage and real-SDR measurements (B storage, D on real SDRs, float16 "
                         "agreement), merged into --out")
    ap.add_argument("--part", choices=["b", "d"],
                    help="with --storage-and-real-sdrs: only B (storage timings and agreement) or only D (real and random SDRs)")
    ap.add_argument("--timing-only", action="store_true",
                    help="re-measure A, B, D and keep the Nordland results already in --out")
    args = ap.parse_args()
    reps = 10 if args.quick else 30
    previous = json.loads(Path(args.out).read_text()) if Path(args.out).exists() else {}
    if args.storage_and_real_sdrs:
        import real_sdrs

        res = dict(previous)
        if args.part != "d":
            res.update(bench_b_storage(20 if args.quick else 40))
            print("B storage", {k: v for k, v in res.items() if k.startswith("b_ms")}, flush=True)
        rec = real_sdrs.record_synthetic()
        if args.part != "b":
            k = 20000 if args.quick else 100000
            real = real_sdrs.bench_d_real(k, 100 if args.quick else 200, rec)
            res[f"d_real_k{k}"] = real
            res[f"d_ms_real_k{k}"] = real["compute_ms_bounded"]
            res.pop("d_real_conditions", None)  # now recorded in each d_real_k* block
            print("D real", real, flush=True)
            for kr in (1000, 10000, 100000):  # and on random SDRs (the same keys as the full run)
                res[f"d_ms_k{kr}"] = bench_d(kr, 300)
                print("D random", kr, res[f"d_ms_k{kr}"], flush=True)
        for dtype in ("float16", "int8", "int8_7bit") if args.part != "d" else ():
            res[f"b_{dtype}_agreement"] = {"synthetic": real_sdrs.storage_synthetic(rec, dtype),
                                           "nordland": real_sdrs.storage_nordland(8 if args.quick else 4, dtype)}
            print(f"{dtype} agreement", res[f"b_{dtype}_agreement"], flush=True)
        Path(args.out).write_text(json.dumps(res, indent=2))
        print(f"wrote {args.out}")
        return
    res: dict = {"threads": args.threads}
    if args.timing_only:
        res.update({k: v for k, v in previous.items() if k.startswith("nordland") or k == "backbone"})
    a1, ab = bench_a("random_alexnet", reps, 8, args.threads)
    res.update({"a_ms_batch1": a1, "a_ms_batched": ab, "a_backbone_timed": "random_alexnet (same cost as alexnet)"})
    e1, eb = bench_a("efficientnet_lite0", reps, 8, args.threads)
    res.update({"a_ms_efficientnet_batch1": e1, "a_ms_efficientnet_batched": eb})
    print("A", res, flush=True)
    res.update(bench_b(reps, 8, args.threads))
    print("B", res, flush=True)
    for k in (1000, 10000, 100000):
        res[f"d_ms_k{k}"] = bench_d(k, 300)
        print("D", k, res[f"d_ms_k{k}"], flush=True)
    res["d_compaction_ms_k100000"] = bench_d_compaction(100000)
    print("D compaction", res["d_compaction_ms_k100000"], flush=True)
    if DATA.is_dir() and not args.timing_only:
        res.update(nordland(8 if args.quick else 4, 8))
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
