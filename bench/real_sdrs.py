"""Real pipeline data for the front-end bench: features, bits, SDRs and templates of the synthetic
world recorded from the NeoSLAM front end, and what reduced-precision storage (float16, int8) of
B's matrix changes on them and on Nordland. A protocol of ``bench/frontend.py
--storage-and-real-sdrs``, which runs it and merges its figures into frontend.json.

``record_synthetic`` runs the front end of ``load_config("default")`` (A, B, C, D exactly as
``neoslam run`` configures them, one frame at a time as the in-process API steps them) over one
route of the embedded synthetic world and keeps every frame's A features, B bits, C winner cells
and D result. The recording is cached in /tmp (A's features are 88 kB a frame, too large for
bench/results); it is regenerated when absent.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

CACHE = Path("/tmp/neoslam_bench_real_synthetic.npz")

#: B's precision variants compared with the float32 reference: name -> projector settings
VARIANTS: dict[str, dict[str, Any]] = {
    "float32": {"matrix_dtype": "float32"},
    "float16": {"matrix_dtype": "float16"},
    "int8": {"matrix_dtype": "int8"},
    "int8_7bit": {"matrix_dtype": "int8", "feature_bits": 7},
}


def record_synthetic(frames: int | None = None, cache: Path | None = CACHE) -> dict[str, Any]:
    """{features (T, n) float32, bits list, cells list, ids, loops, best_score, backbone}."""
    if cache is not None and cache.is_file():
        z = np.load(cache, allow_pickle=False)
        n = int(z["n"])
        if frames is None or n >= frames:
            t = n if frames is None else frames
            bo, co = z["bits_off"], z["cells_off"]
            return {"features": z["features"][:t], "bits": [z["bits"][bo[i]:bo[i + 1]] for i in range(t)],
                    "cells": [z["cells"][co[i]:co[i + 1]] for i in range(t)], "ids": z["ids"][:t],
                    "loops": z["loops"][:t], "best_score": z["best_score"][:t], "backbone": str(z["backbone"])}
    from neoslam_stream import load_config
    from neoslam_stream.algorithms.frontend import FrontEnd
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default")
    src = SyntheticWorldSource(**dict(cfg.source.params or {}), **({"frames": frames} if frames else {}))
    fe = FrontEnd(cfg.front_end())
    fe.warm_up()
    feats, bits, cells, ids, loops, scores = [], [], [], [], [], []
    for fr in src:
        if not fe.keep(fr.frame):
            continue
        f = fe.features([fr.image])  # A, B, C, D of one frame, as the API's step runs them
        b = fe.bits(f)[0]
        c = fe.cells(b)
        t = fe.template(c)
        feats.append(np.asarray(f[0], np.float32))
        bits.append(np.asarray(b, np.uint16))
        cells.append(np.asarray(c, np.uint32))
        ids.append(int(t["id"]))
        loops.append(bool(t["is_loop_closure"]))
        scores.append(int(t["best_score"]))
    backbone = fe.extractor.backbone
    out = {"features": np.stack(feats), "bits": bits, "cells": cells, "ids": np.asarray(ids),
           "loops": np.asarray(loops), "best_score": np.asarray(scores), "backbone": backbone}
    if cache is not None:
        np.savez(cache, n=len(ids), features=out["features"], bits=np.concatenate(bits),
                 bits_off=np.concatenate([[0], np.cumsum([len(b) for b in bits])]),
                 cells=np.concatenate(cells), cells_off=np.concatenate([[0], np.cumsum([len(c) for c in cells])]),
                 ids=out["ids"], loops=out["loops"], best_score=out["best_score"], backbone=backbone)
    return out


def _bit_agreement(a: list[np.ndarray], b: list[np.ndarray]) -> dict[str, float]:
    """Frames whose 512 bits are all identical, and the mean fraction of identical set bits."""
    same_frames = sum(1 for x, y in zip(a, b, strict=True) if np.array_equal(x, y))
    shared = [np.intersect1d(x, y).size / max(x.size, 1) for x, y in zip(a, b, strict=True)]
    return {"frames": len(a), "frames_identical": same_frames, "fraction_frames_identical": same_frames / len(a),
            "mean_fraction_bits_identical": float(np.mean(shared)), "min_fraction_bits_identical": float(np.min(shared))}


def storage_synthetic(rec: dict[str, Any], dtype: str = "float16") -> dict[str, Any]:
    """Replay the recorded A features through B (float32 and the variant ``dtype`` of
    :data:`VARIANTS`), C and D as configured by ``default``, one frame at a time as in a run;
    compare bits and templates with the recorded run."""
    from neoslam_stream import load_config
    from neoslam_stream.algorithms.frontend import FrontEnd

    out: dict[str, Any] = {}
    runs = {}
    for storage in ("float32", dtype):
        cfg = load_config("default", overrides={"projector": VARIANTS[storage],
                                                "features": {"backbone": rec["backbone"]}})
        fe = FrontEnd(cfg.front_end())
        fe.warm_up()
        bits, ids, loops = [], [], []
        for f in rec["features"]:
            b = fe.bits(f[None])[0]
            t = fe.template(fe.cells(b))
            bits.append(np.asarray(b))
            ids.append(int(t["id"]))
            loops.append(bool(t["is_loop_closure"]))
        runs[storage] = (bits, np.asarray(ids), np.asarray(loops))
    b32, i32, l32 = runs["float32"]
    b16, i16, l16 = runs[dtype]
    out["replay_float32_equals_recording"] = bool(np.array_equal(i32, rec["ids"]))
    out["bits"] = _bit_agreement(b32, b16)
    out["templates_identical"] = bool(np.array_equal(i32, i16))
    out["frames_with_same_template"] = int(np.sum(i32 == i16))
    out["loop_closures_float32"] = int(l32.sum())
    out[f"loop_closures_{dtype}"] = int(l16.sum())
    out["loop_closure_frames_identical"] = bool(np.array_equal(l32, l16))
    out["templates_float32"], out[f"templates_{dtype}"] = int(i32.max() + 1), int(i16.max() + 1)
    out["backbone"] = rec["backbone"]
    out["frames"] = len(i32)
    return out


def storage_nordland(step: int = 4, dtype: str = "float16") -> dict[str, Any]:
    """The main Nordland configuration of bench/frontend.py (EfficientNet-Lite0, centred B with
    window 100, pass-through C, calibrated theta_sigma) with B in float32 and in the variant ``dtype``
    of :data:`VARIANTS`."""
    import nordland

    from neoslam_stream.algorithms.frontend import FrontEnd

    if not nordland.DATA.is_dir():
        return {"skipped": f"{nordland.DATA} not found"}
    feats, ids_t, n, backbone = nordland.stream_features("efficientnet_lite0", step, None, 10.0)
    ids = list(ids_t)
    res: dict[str, Any] = {"places": n, "frames": len(feats), "step": step, "backbone": backbone}
    bits, cells = {}, {}
    for storage in ("float32", dtype):
        fe = FrontEnd(features={"backbone": backbone}, projector={"centre_window": 100, **VARIANTS[storage]})
        bits[storage], cells[storage] = nordland.stream_codes(feats, fe, nordland.passthrough_neocortex)
    res["bits"] = _bit_agreement(bits["float32"], bits[dtype])
    tids = {}
    for storage, b in bits.items():
        ((_, d, out, ev, theta),) = nordland.spatial_view_runs(b, cells[storage], ids, n, [{"theta_sigma": None}], 150)
        t = [int(m["id"]) for m in out]
        lo = [bool(m["is_loop_closure"]) for m in out]
        res[storage] = {"theta_sigma_calibrated": theta, "templates": d.n_templates, **ev}
        tids[storage] = (np.asarray(t), np.asarray(lo))
    res["templates_identical"] = bool(np.array_equal(tids["float32"][0], tids[dtype][0]))
    res["loop_closure_frames_identical"] = bool(np.array_equal(tids["float32"][1], tids[dtype][1]))
    return res


def grow_index(cells: list[np.ndarray], k_target: int, swap: float = 0.05, seed: int = 0) -> tuple[Any, list]:
    """Spatial-view cells (``default`` parameters) holding >= k_target intervals built from real SDRs.

    The recorded stream runs once through ``compute`` (its real intervals, unions and closures).
    Its unions are then repeated, each repetition with a fraction ``swap`` of every union's cells
    moved to a random other column (same cell of the column: real winner cells are mostly cell 0),
    like revisits under changed appearance, until k_target intervals exist; they are loaded with
    ``load_state_dict`` (the index is built as K frames would build it, without K scoring passes).
    Returns the loaded cells and the perturbation function for query streams.
    """
    from neoslam_stream import load_config
    from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig

    cfg = SpatialViewConfig(**load_config("default").spatial_view.model_dump())
    rng = np.random.default_rng(seed)

    def perturb(c: np.ndarray) -> np.ndarray:
        c = np.asarray(c, np.int64).copy()
        moved = rng.random(c.size) < swap
        c[moved] = rng.integers(0, 2048, int(moved.sum())) * 32 + c[moved] % 32
        return np.unique(c).astype(np.uint32)

    first = SpatialViewCells(cfg)
    for c in cells:
        first.compute(c)
    base = [np.asarray(u.to_array(), np.uint32) for u in first.unions]
    unions = list(base)
    while len(unions) < k_target:
        unions += [perturb(u) for u in base]
    unions = unions[:k_target]
    k = len(unions)
    svc = SpatialViewCells(cfg)
    svc.load_state_dict({"params": [cfg.theta_alpha, cfg.theta_rho, cfg.theta_sigma, cfg.exclude_recent_intervals,
                                    cfg.sdr_size], "unions": unions, "start": np.arange(k) * 4,
                         "end": np.arange(k) * 4 + 3, "template": np.arange(k), "n_templates": k,
                         "current_template": k - 1, "t": 4 * k})
    return svc, perturb


def bench_d_real(k_target: int, queries: int, rec: dict[str, Any] | None = None) -> dict[str, Any]:
    """D at k_target intervals of real SDRs (see :func:`grow_index`): per query, the exhaustive
    scoring and the bounded search on the same index (alternating which goes first, results
    checked equal), then the whole ``compute`` with the bounded search (its data evicted from the
    caches by the 126 MB exhaustive pass just before: ``compute_ms_bounded``); then as many other
    queries through ``compute`` alone, one after another as D's worker runs them
    (``compute_ms_stream``); medians in ms."""
    import time

    rec = rec or record_synthetic()
    svc, perturb = grow_index(rec["cells"], k_target)
    stream = [perturb(c) for c in rec["cells"][:queries]]
    t_exh, t_bnd, t_full, reads, verified, paths = [], [], [], [], [], []
    for i, c in enumerate(stream):
        y = svc._validate(c)
        limit = svc.n_intervals - svc.config.exclude_recent_intervals
        runs = [("exh", svc.index.top2_exhaustive), ("bnd", svc.index.top2_bounded)]
        got = {}
        for name, fn in (runs if i % 2 else runs[::-1]):
            t0 = time.perf_counter()
            got[name] = fn(y, limit)
            (t_exh if name == "exh" else t_bnd).append((time.perf_counter() - t0) * 1e3)
        if got["exh"] != got["bnd"]:
            raise AssertionError(f"bounded search differs from exhaustive scoring at query {i}")
        reads.append(svc.index.last_search[0])
        verified.append(svc.index.last_search[1])
        paths.append(svc.index.last_path)
        t0 = time.perf_counter()
        svc.compute(c)
        t_full.append((time.perf_counter() - t0) * 1e3)
    t_stream = []
    for c in [perturb(c) for c in rec["cells"][-queries:]]:
        t0 = time.perf_counter()
        svc.compute(c)
        t_stream.append((time.perf_counter() - t0) * 1e3)
    postings = int(sum(svc.index._count[svc._validate(c)].sum() for c in stream[:50]) / min(50, len(stream)))
    return {"intervals": svc.n_intervals, "queries": len(stream), "identical": True,
            "load_average_1min_at_end": round(os.getloadavg()[0], 2), "cpu_threads": os.cpu_count(),
            "scoring_ms_exhaustive": float(np.median(t_exh)), "scoring_ms_bounded": float(np.median(t_bnd)),
            "compute_ms_bounded": float(np.median(t_full)), "compute_ms_stream": float(np.median(t_stream)),
            "compute_ms_stream_p95": float(np.percentile(t_stream, 95)),
            "search_path_sliced_fraction": float(np.mean([p == "sliced" for p in paths])),
            "dense_rows": int(svc.index._n_dense - 1), "dense_rows_mb": float(svc.index._dense.nbytes / 1e6),
            "speedup_scoring": float(np.median(t_exh) / np.median(t_bnd)),
            "postings_read_bounded": float(np.median(reads)), "postings_per_query_all": postings,
            "unions_verified": float(np.median(verified)),
            "search_counters": "postings_read_bounded / unions_verified: posting-list search: postings read, unions "
                               "scored exactly; bit-sliced count: postings of cells without a dense row, intervals "
                               "whose count reached the runner-up",
            "mean_union_cells": float(np.mean([len(u) for u in svc.unions])),
            "source": f"{len(rec['cells'])} frames of the synthetic world through the default NeoSLAM front end "
                      f"(A {rec['backbone']}, B gaussian, C temporal memory), replayed with 5 % of each "
                      "union's cells moved to random columns per repetition"}
