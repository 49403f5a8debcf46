"""Nordland summer -> winter through A, B, C and D: loop-closure precision and recall.

Summer frames, then winter frames, stream as one sequence through the stages of a
:class:`~neoslam_stream.algorithms.frontend.FrontEnd` (A and B eight frames at a time, as their
nodes batch them in a lossless run); A, B and C run once, D once per parameter set. The seasons
are frame-aligned: winter frame i shows summer frame i's place. A winter closure is correct when
the template it matched was created within +-``tolerance`` source frames of that place during the
summer pass; recall = correct closures / winter frames. Protocol (docs/frontend.md): every
``step``-th thumbnail; places where either season's frame is featureless (grey-level std below
``min_std``: tunnels, night) left out of both passes; ``theta_sigma`` None in a parameter set:
calibrated on the summer pass alone (a percentile of the overlaps between summer frames more than
``tolerance`` apart). The protocol's constants: bench/settings/nordland.yaml.
Used by bench/frontend.py, studies/maps.py, bench/streams.py and tests/test_frontend_nordland.py.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from bench_settings import data_root

from neoslam_stream.algorithms.frontend import FrontEnd

DATA = data_root() / "nordland_64x32"


def load_frames(step: int, limit: int | None = None, min_std: float | None = None,
                offset: int = 0) -> tuple[list[np.ndarray], list[np.ndarray], list[int]]:
    """RGB summer and winter frames of every step-th place from the ``offset``-th on, and the places'
    source frame numbers (``offset`` 1 .. step-1 gives a subset disjoint from offset 0's)."""
    names = sorted(p.name for p in (DATA / "summer").glob("images-*.png"))[offset::step]
    if limit:
        names = names[:limit]
    summer, winter, ids = [], [], []
    for n in names:
        s = cv2.imread(str(DATA / "summer" / n))[:, :, ::-1]
        w = cv2.imread(str(DATA / "winter" / n))[:, :, ::-1]
        if min_std is not None and min(s.std(), w.std()) < min_std:
            continue
        summer.append(s)
        winter.append(w)
        ids.append(int(n[7:12]))
    return summer, winter, ids


def overlaps(bits: list[np.ndarray], n_bits: int = 2048) -> np.ndarray:
    """Pairwise |b_i & b_j| of sorted bit-index arrays."""
    m = np.zeros((len(bits), n_bits), np.float32)
    for i, b in enumerate(bits):
        m[i, b] = 1.0
    return (m @ m.T).astype(np.int64)


def calibrate_theta_sigma(summer_bits: list[np.ndarray], ids: list[int], tolerance: int,
                          quantile: float = 99.9) -> int:
    """The quantile-th percentile of overlaps between summer frames more than ``tolerance`` apart."""
    o = overlaps(summer_bits)
    a = np.asarray(ids)
    far = np.abs(a[:, None] - a[None, :]) > tolerance
    return int(np.floor(np.percentile(o[far], quantile)))


def passthrough_neocortex(bits: np.ndarray, cells_per_column: int = 32) -> np.ndarray:
    """What htm.core's TM effectively emits with NeoSLAM's parameters: cell 0 of each active column."""
    return bits.astype(np.uint32) * cells_per_column


def evaluate(template_ids: list[int], loops: list[bool], source_ids: list[int], n_summer: int,
             tolerance: int) -> dict:
    """Precision/recall of winter closures against the template creation place in summer."""
    created: dict[int, int] = {}
    for i, t in enumerate(template_ids[:n_summer]):
        created.setdefault(t, source_ids[i])
    closures = correct = 0
    for j in range(n_summer, len(template_ids)):
        if not loops[j]:
            continue
        closures += 1
        place = source_ids[j - n_summer]
        origin = created.get(template_ids[j])
        if origin is not None and abs(origin - place) <= tolerance:
            correct += 1
    n_winter = len(template_ids) - n_summer
    return {"closures": closures, "correct": correct,
            "precision": correct / closures if closures else None,
            "recall": correct / n_winter if n_winter else 0.0}


def resolve_params(params: dict, bits: list[np.ndarray], ids: list[int], n: int, tolerance: int,
                   quantile: float, calibrated: dict[float, int] | None = None) -> dict:
    """D's parameters of one set with the protocol's two deferred keys resolved: theta_sigma None
    -> calibrated on summer's bits at ``calibration_quantile`` (default ``quantile``), and
    ``min_gap_fraction`` f -> ``sequence.min_gap_frames`` = int(f * n) (n: places per traversal)."""
    params = dict(params)
    q = float(params.pop("calibration_quantile", quantile))
    frac = params.pop("min_gap_fraction", None)
    if params.get("theta_sigma") is None:
        cache = calibrated if calibrated is not None else {}
        if q not in cache:
            cache[q] = calibrate_theta_sigma(bits[:n], ids, tolerance, q)
        params["theta_sigma"] = cache[q]
    if frac is not None:
        params["sequence"] = {**params.get("sequence", {}), "min_gap_frames": int(frac * n)}
    return params


def spatial_view_runs(bits: list[np.ndarray], sdrs: list[np.ndarray], ids: list[int], n: int,
                      svc_params: list[dict], tolerance: int = 150, quantile: float = 99.9):
    """D once per parameter set over one stream (the ``n`` summer frames, then winter), each in a
    front end of its own handed C's cells: yields (parameters, its SpatialViewCells, its templates,
    :func:`evaluate`'s result, the theta_sigma calibrated at ``quantile``). A set's deferred keys are
    resolved by :func:`resolve_params`."""
    cache: dict[float, int] = {}
    calibrated = resolve_params({"theta_sigma": None}, bits, ids, n, tolerance, quantile, cache)["theta_sigma"]
    for params in svc_params:
        params = resolve_params(params, bits, ids, n, tolerance, quantile, cache)
        fe = FrontEnd(spatial_view=params)
        out = [fe.template(c.astype(np.uint32)) for c in sdrs]
        res = evaluate([int(m["id"]) for m in out], [bool(m["is_loop_closure"]) for m in out], ids, n, tolerance)
        yield params, fe.spatial_view, out, res, calibrated


@lru_cache(maxsize=1)
def stream_features(backbone: str, step: int, limit: int | None = None, min_std: float | None = None,
                    offset: int = 0, seed: int = 42, photometric: str = "none",
                    input_size: int = 224) -> tuple[np.ndarray, tuple[int, ...], int, str]:
    """A's features of the summer then winter frames (8 at a time, as its node batches them), the
    places' source frame numbers, the number of summer frames and the backbone that ran. The last
    stream is kept (up to 0.2 GB): several B settings over one stream run A once. A's input as
    captured at 224 unless ``photometric`` and ``input_size`` say otherwise (the default's)."""
    summer, winter, ids = load_frames(step, limit, min_std, offset)
    fe = FrontEnd(features={"backbone": backbone, "seed": seed, "photometric": photometric,
                            "input_size": input_size})
    frames = summer + winter
    feats = np.concatenate([fe.features(frames[k:k + 8]) for k in range(0, len(frames), 8)])
    feats.setflags(write=False)
    return feats, tuple(ids), len(summer), fe.extractor.backbone


def stream_codes(features: np.ndarray, fe: FrontEnd, cells_of: Any = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """B's bits and C's cells of every frame: A's ``features`` through ``fe``'s B 8 frames at a
    time, as B's node batches them, each frame's bits then through ``fe``'s C (or ``cells_of``)."""
    cells_of = cells_of or fe.cells
    bits: list[np.ndarray] = []
    sdrs: list[np.ndarray] = []
    for k in range(0, len(features), 8):
        for b in fe.bits(features[k:k + 8]):
            bits.append(b)
            sdrs.append(cells_of(b))
    return bits, sdrs


def run_frontend(backbone: str, step: int, svc_params: list[dict], tolerance: int = 150,
                 limit: int | None = None, neocortex: Any = "passthrough", projection: str = "gaussian",
                 seed: int = 42, centre_window: int = 0, min_std: float | None = None,
                 quantile: float = 99.9, offset: int = 0) -> list[dict]:
    """Stream summer then winter through A, B and C once, then D per parameter set.

    ``neocortex``: ``"passthrough"`` (cell 0 of each active column), ``"tm"`` (the real
    :class:`~neoslam_stream.algorithms.neocortex.Neocortex` with its defaults), a dict of Neocortex
    parameters, or a callable bits -> cells. ``offset``: see :func:`load_frames`.
    """
    features, ids_t, n, backbone_ran = stream_features(backbone, step, limit, min_std, offset, seed)
    ids = list(ids_t)
    nc = neocortex if isinstance(neocortex, dict) else {}
    fe = FrontEnd(features={"backbone": backbone_ran, "seed": seed}, neocortex=nc,
                  projector={"projection": projection, "seed": seed, "centre_window": centre_window})
    cells_of = None
    if isinstance(neocortex, str) and neocortex == "passthrough":
        cells_of = passthrough_neocortex
        nc_name = "passthrough (cell 0 of each active column)"
    elif callable(neocortex):
        def cells_of(bits: np.ndarray) -> np.ndarray:
            return np.asarray(neocortex(bits))
        nc_name = getattr(neocortex, "__name__", "callable")
    else:
        nc_name = f"neocortex (tie_break {fe.config.neocortex.tie_break})"
    bits, sdrs = stream_codes(features, fe, cells_of)
    results = []
    for params, d, out, res, calibrated in spatial_view_runs(bits, sdrs, ids, n, svc_params, tolerance, quantile):
        template_ids = [int(m["id"]) for m in out]
        created: dict[int, int] = {}
        for i, t in enumerate(template_ids[:n]):
            created.setdefault(t, ids[i])
        # winter frame index -> source frame where its matched template was created (-1: in winter)
        res["closure_origin"] = {j - n: created.get(template_ids[j], -1) for j in range(n, len(out))
                                 if out[j]["is_loop_closure"]}
        window = sum(1 for i in ids if abs(i - ids[n // 2]) <= tolerance)
        res.update({"backbone": backbone_ran, "backbone_is_random": backbone_ran == "random_alexnet",
                    "neocortex": nc_name, "projection": projection, "centre_window": centre_window,
                    "places": n, "frames": len(features), "step": step, "offset": offset, "min_std": min_std,
                    "tolerance": tolerance, "templates": d.n_templates, "svc": params,
                    "theta_sigma_calibrated": calibrated, "calibration_quantile": quantile,
                    "chance_precision": window / n,
                    "summer_closures": int(sum(bool(m["is_loop_closure"]) for m in out[:n]))})
        results.append(res)
    return results
