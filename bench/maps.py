"""Lever study of issue #14 ("maps users can trust") -> bench/results/maps.json.

Each lever is measured ALONE against the paper profile (``configs/paper.yaml`` when present,
else today's settings) and then all kept levers together (the new default), on:

* the synthetic world (the full default route, 2445 frames, three laps), through the in-process
  chain of nodes (the same code as a lossless ``neoslam run``): APE mean of the experience-map
  trajectory after SE(2) alignment, odometry's APE, closure precision / recall (a closure is
  correct when the matched template's first frame lies within 1 m of the frame's true position);
* the TU Chemnitz corridor run (back end only, with its visual loop candidates; ground truth
  position rows only): map error mean vs odometry's;
* Nordland summer -> winter through B, C, D (``bench/frontend.py`` measures recall@1 of A and B).

The in-process API is deterministic, so A's features are computed once per dataset and cached
in ``$NEOSLAM_CACHE`` (default ``/tmp/neoslam_maps``), never in the repository; C's SDRs are
cached per (B, C) configuration. Run: ``.venv/bin/python bench/maps.py [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.evaluation import evaluate_run, loop_closure_quality  # noqa: E402
from neoslam_stream.nodes.pipelines import build_plan  # noqa: E402
from neoslam_stream.runtime.config import merge_dicts  # noqa: E402
from neoslam_stream.runtime.local import LocalChain  # noqa: E402
from neoslam_stream.runtime.messages import Message  # noqa: E402
from neoslam_stream.tum import integrate_odometry, write_tum  # noqa: E402

CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_maps"))
RESULTS = Path(__file__).parent / "results"


def _key(obj: Any) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def synthetic_inputs(frames: int | None = None) -> dict[str, np.ndarray]:
    """A's features (the shipped default backbone), odometry, stamps and ground truth of the
    synthetic route, computed once and cached."""
    from neoslam_stream.nodes.features import FeatureNode
    from neoslam_stream.nodes.pipelines import neoslam_feature_params
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default")
    feats_params, _ = neoslam_feature_params(cfg)
    path = CACHE / f"synthetic_{_key([feats_params, frames])}.npz"
    if path.exists():
        return dict(np.load(path))
    CACHE.mkdir(parents=True, exist_ok=True)
    params = dict(cfg.source.params)
    if frames:
        params["frames"] = frames
    node = FeatureNode(**feats_params)
    node.setup()
    F, odo, gt, st = [], [], [], []
    for sf in SyntheticWorldSource(**params):
        msg = Message("image", sf.frame, sf.stamp, {"image": sf.image, "encoding": "rgb8"})
        [(_, out)] = node.process("image", msg)
        F.append(out["features"])
        odo.append(sf.odom)
        gt.append(sf.groundtruth)
        st.append(sf.stamp)
    data = {"features": np.stack(F).astype(np.float32), "odom": np.array(odo), "gt": np.array(gt),
            "stamps": np.array(st), "backbone": np.array(feats_params["backbone"])}
    np.savez(path, **data)
    return data


def _plan(cfg: Any, skip: tuple[str, ...]) -> list:
    return [s for s in build_plan(cfg).stages if s.name not in skip]


def sdrs(cfg: Any, data: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """C's output per frame for B and C of ``cfg`` (cached per their parameters)."""
    specs = [s for s in _plan(cfg, ("A",)) if s.name in ("B", "C")]
    path = CACHE / f"sdr_{_key([[s.params for s in specs], str(data['backbone']), len(data['stamps'])])}.npz"
    if path.exists():
        z = np.load(path)
        return [{"cells": c, "size": int(z["size"])} for c in np.split(z["cells"], z["ptr"][1:-1])]
    chain = LocalChain(specs)
    out = []
    bb = str(data["backbone"])
    for i, f in enumerate(data["features"]):
        res = chain.push("visual_features", Message("visual_features", i, float(data["stamps"][i]),
                                                   {"features": f, "backbone": bb}))
        [m] = [m for t, m in res if t == "sdr"]
        out.append({"cells": np.asarray(m["cells"]), "size": int(m["size"])})
    chain.finish()
    lens = [len(o["cells"]) for o in out]
    np.savez(path, cells=np.concatenate([o["cells"] for o in out]), ptr=np.concatenate([[0], np.cumsum(lens)]),
             size=out[0]["size"])
    return out


def run_synthetic(cfg: Any, data: dict[str, np.ndarray], run_dir: Path) -> dict[str, Any]:
    """D + back end on the cached SDRs of ``cfg``'s B and C; writes the run folder and evaluates it."""
    seq = sdrs(cfg, data)
    run_dir.mkdir(parents=True, exist_ok=True)
    chain = LocalChain(_plan(cfg, ("A", "B", "C")), run_dir)
    t0 = time.perf_counter()
    for i, s in enumerate(seq):
        st = float(data["stamps"][i])
        v, w, dt = data["odom"][i]
        chain.push("odom", Message("odom", i, st, {"vtrans": float(v), "vrot": float(w), "dt": float(dt)}))
        chain.push("sdr", Message("sdr", i, st, s))
    chain.finish()
    secs = time.perf_counter() - t0
    gt = np.column_stack([data["stamps"], data["gt"]])
    write_tum(run_dir / "groundtruth.tum", gt)
    write_tum(run_dir / "odometry.tum", integrate_odometry(data["stamps"], data["odom"]))
    ev = evaluate_run(run_dir, plot=False)
    lc = ev["loop_closures"]
    # the final (relaxed) map: each experience at the true position of the frame that created it
    from neoslam_stream.evaluation import ape, associate

    mp = json.loads((run_dir / "map.json").read_text())
    nodes = np.array([[n["stamp"], n["x"], n["y"]] for n in mp["nodes"]])
    ne, ng = associate(nodes[:, 0], gt[:, 0], max_dt=1.0)
    map_ape = ape(nodes[ne, 1:3], gt[ng, 1:3])  # ape aligns (SE(2)) itself
    # precision by the matched template's first frame too (the rule before closures.csv existed,
    # under which the entries made before it were computed)
    by_template = loop_closure_quality(run_dir / "templates.csv", gt, lc["radius_m"])
    return {"ape_mean_m": ev["trajectory_ape"]["mean_m"], "ape_max_m": ev["trajectory_ape"]["max_m"],
            "odometry_mean_m": ev["odometry_ape"]["mean_m"], "closures": lc["closures"],
            "final_map_ape_mean_m": map_ape["mean_m"],
            "map_trajectory_ape_mean_m": ev.get("map_trajectory_ape", {}).get("mean_m"), "precision": lc["precision"], "recall": lc["recall"], "radius_m": lc["radius_m"],
            "matched_by": lc.get("matched_by"), "precision_by_template": by_template["precision"],
            "recall_by_template": by_template["recall"],
            "d_and_backend_s": round(secs, 1)}


# ---------------------------------------------------------------- Nordland summer -> winter

NORDLAND = dict(step=8, min_std=10.0, tolerance=150)  # tests/test_frontend_nordland.py's protocol


def nordland_inputs(backbone: str = "efficientnet_lite0", offset: int = 0) -> dict[str, Any]:
    """A's features of the summer then winter frames (8 at a time, as the nodes batch), cached.
    ``offset``: every step-th thumbnail from the offset-th on (4: the validation subset, disjoint
    from the test protocol's offset 0)."""
    from neoslam_stream.datasets.nordland import stream_features

    path = CACHE / f"nordland_{_key([backbone, NORDLAND] + ([offset] if offset else []))}.npz"
    if path.exists():
        z = np.load(path)
        return {"features": z["features"], "ids": z["ids"].tolist(), "n": int(z["n"])}
    CACHE.mkdir(parents=True, exist_ok=True)
    feats, ids, n, _ = stream_features(backbone, NORDLAND["step"], None, NORDLAND["min_std"], offset)
    np.savez(path, features=feats.astype(np.float32), ids=np.array(ids), n=n)
    return {"features": feats, "ids": list(ids), "n": n}


def run_nordland(proj: dict, svc_list: list[dict], data: dict[str, Any]) -> list[dict]:
    """B (``proj`` on top of the defaults), the real C and D (each of ``svc_list``; theta_sigma None:
    calibrated on summer as in the Nordland test) on the cached features; precision / recall."""
    from neoslam_stream.datasets.nordland import spatial_view_runs

    bits, sdr = nordland_sdrs(proj, data)
    ids, n = data["ids"], data["n"]
    out = []
    for svc, _, _, r, _ in spatial_view_runs(bits, sdr, ids, n, svc_list, NORDLAND["tolerance"]):
        r.update({"svc": svc, "proj": proj, "places": n})
        out.append(r)
    return out


def nordland_sdrs(proj: dict, data: dict[str, Any]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """B's bits (``proj`` on top of the defaults) and the real C's winner cells of every frame, cached."""
    from neoslam_stream.algorithms.neocortex import Neocortex
    from neoslam_stream.datasets.nordland import stream_codes

    feats = data["features"]
    path = CACHE / f"nordland_sdr_{_key([proj, feats.shape, float(feats.sum(dtype=np.float64))])}.npz"
    if path.exists():
        z = np.load(path)
        bits = np.split(z["bits"], z["bptr"][1:-1])
        sdr = np.split(z["cells"], z["cptr"][1:-1])
    else:
        bits, sdr = stream_codes(feats, Neocortex().compute, **{"projection": "gaussian", "seed": 42, **proj})
        np.savez(path, bits=np.concatenate(bits), bptr=np.cumsum([0] + [len(b) for b in bits]),
                 cells=np.concatenate(sdr), cptr=np.cumsum([0] + [len(c) for c in sdr]))
    return bits, sdr


def _precision_at_recall(scores: np.ndarray, correct: np.ndarray, recall: float = 0.2) -> dict[str, float]:
    """Each winter frame's best match ranked by its confidence (best score, or margin to the
    runner-up): recall@1, the precision at ``recall`` and the largest recall at precision 0.9."""
    top = np.sort(scores, axis=1)
    res: dict[str, float] = {"recall_at_1": float(correct.mean())}
    for name, conf in (("score", top[:, -1]), ("margin", top[:, -1] - top[:, -2])):
        hits = np.cumsum(correct[np.argsort(-conf, kind="stable")])
        prec, rec = hits / np.arange(1, len(hits) + 1), hits / len(hits)
        res[f"precision_at_recall_{recall}_by_{name}"] = float(prec[min(np.searchsorted(rec, recall), len(prec) - 1)])
        res[f"recall_at_precision_0.9_by_{name}"] = float(rec[prec >= 0.9].max()) if (prec >= 0.9).any() else 0.0
    return res


def nordland_d_closures(data: dict[str, Any], proj: dict) -> dict[str, Any]:
    """D's winter closures when a winter frame can only match summer (``min_gap_frames`` 395 of the
    417 places): how many, how many correct, and which intervals the wrong ones went to (their
    union's size |Y_k| and frame count; a single frame has ~512 cells)."""
    from neoslam_stream.datasets.nordland import overlaps, spatial_view_runs

    bits, sdr = nordland_sdrs(proj, data)
    ids, n = np.asarray(data["ids"]), data["n"]
    svc = [dict(_SVC, theta_sigma=None, sequence={"min_gap_frames": 395})]
    ((params, _, out, res, _),) = list(spatial_view_runs(bits, sdr, list(ids), n, svc, NORDLAND["tolerance"]))
    members: dict[int, list[int]] = {}
    for i, m in enumerate(out):
        members.setdefault(int(m["interval"]), []).append(i)
    created = {}
    for i in range(n):
        created.setdefault(int(out[i]["id"]), int(ids[i]))
    wrong: dict[int, int] = {}
    for j in range(n, len(out)):
        if out[j]["is_loop_closure"] and abs(created.get(int(out[j]["id"]), -10**9) - ids[j - n]) > NORDLAND["tolerance"]:
            k = int(out[j]["best_interval"])
            wrong[k] = wrong.get(k, 0) + 1
    top = sorted(wrong.items(), key=lambda kv: -kv[1])[:5]
    # the same threshold on single frames: winter frames whose best summer frame overlaps > theta_sigma
    sim = overlaps(sdr, int(max(c.max() for c in sdr)) + 1)[n:, :n]
    above = sim.max(1) > params["theta_sigma"]
    right = np.abs(ids[sim.argmax(1)] - ids) <= NORDLAND["tolerance"]
    return {"proj": proj, "svc": params, **res,
            "single_frames_above_theta": int(above.sum()), "single_frames_above_theta_correct": int((above & right).sum()),
            "wrong_by_interval": [{"interval": k, "wrong_closures": c, "frames": len(members[k]),
                                   "union_cells": len(np.unique(np.concatenate([sdr[i] for i in members[k]])))}
                                  for k, c in top],
            "summer_intervals": sum(1 for v in members.values() if v[0] < n),
            "summer_intervals_of_several_frames": sum(1 for v in members.values() if v[0] < n and len(v) > 1)}


def nordland_ceiling(data: dict[str, Any]) -> dict[str, Any]:
    """Where Nordland's place information is lost: each winter frame's best match by similarity
    alone (A: cosine of the features; B: overlap of the bits, raw and centred), against the summer
    frames only and against what D searches in a stream (summer and the earlier winter frames, less
    the last 3); a match is correct when it is a summer frame within the tolerance (a winter frame is
    a template the winter pass created: wrong)."""
    from neoslam_stream.datasets.nordland import overlaps

    feats, ids, n = data["features"], np.asarray(data["ids"]), data["n"]
    m = len(feats) - n

    def both(sim: np.ndarray) -> dict[str, Any]:
        summer = sim[:, :n]
        ok = np.abs(ids[summer.argmax(1)] - ids) <= NORDLAND["tolerance"]
        stream = sim.copy()
        for i in range(m):
            stream[i, n + max(0, i - 3):] = -np.inf
        best = stream.argmax(1)
        ok_stream = (best < n) & (np.abs(ids[np.minimum(best, n - 1)] - ids) <= NORDLAND["tolerance"])
        return {"summer_only": _precision_at_recall(summer, ok),
                "stream": _precision_at_recall(np.where(np.isfinite(stream), stream, -1e9), ok_stream),
                "stream_best_is_winter": float((best >= n).mean())}

    unit = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    res: dict[str, Any] = {"A_cosine": both(unit[n:] @ unit.T)}
    for name, proj in (("B_bits", {}), ("B_bits_centred", {"centre_window": 100}),
                       ("B_bits_centred_30", {"centre_window": 30})):
        bits, _ = nordland_sdrs(proj, data)
        res[name] = both(overlaps(bits)[n:].astype(np.float64))
    res["d_summer_only"] = nordland_d_closures(data, {"centre_window": 30})
    res["about"] = ("winter frame -> best match by similarity alone; summer_only: the summer frames; stream: "
                    "what D searches (summer + earlier winter frames, less the last 3); correct: a summer frame "
                    f"within {NORDLAND['tolerance']} source frames; precision at recall 0.2 ranking the frames by "
                    "their best score or by the margin to the runner-up")
    return res


def _nordland_stream(svcs: list[dict], offset: int, centre: int) -> list[dict]:
    """The real A, B (centred over ``centre`` frames), C and D per parameter set on one subset."""
    from neoslam_stream.datasets.nordland import run_frontend

    return run_frontend("efficientnet_lite0", NORDLAND["step"], svcs, tolerance=NORDLAND["tolerance"],
                        neocortex="tm", centre_window=centre, min_std=NORDLAND["min_std"], offset=offset)


def nordland_target() -> dict[str, Any]:
    """Issue #14's Nordland target with ``datasets.nordland.MAP_SETTINGS`` through the real A, B, C
    (Temporal Memory) and D, on the test protocol's subset (every 8th thumbnail, offset 0) and on the
    validation subset the settings were chosen on (offset 4: other thumbnails of the same route);
    each part of the settings left out in turn, and the neighbouring settings (calibration
    quantile, margin, sequence length) on both subsets."""
    from neoslam_stream.datasets.nordland import MAP_SETTINGS

    pr = ("closures", "correct", "precision", "recall")
    sv, centre = MAP_SETTINGS["spatial_view"], MAP_SETTINGS["centre_window"]
    without = {"union_normalised": {**sv, "union_normalised": False}, "theta_margin": {**sv, "theta_margin": 0.0},
               "sequence": {**sv, "sequence": {**sv["sequence"], "length": 0}},
               "min_gap": {k: v for k, v in sv.items() if k != "min_gap_fraction"},
               "calibration_quantile_98": {k: v for k, v in sv.items() if k != "calibration_quantile"}}
    grid = [(q, m, n) for q in (95.0, 98.0, 99.0) for m in (0.0, 5.0, 10.0) for n in (0, 1, 2)]
    grid_svcs = [{**sv, "calibration_quantile": q, "theta_margin": m, "sequence": {**sv["sequence"], "length": n}}
                 for q, m, n in grid]
    target = {"precision_min": 0.9, "recall_min": 0.2}
    res: dict[str, Any] = {"settings": MAP_SETTINGS, "target": target}
    for name, offset in (("test", 0), ("validation", 4)):
        main, *rest = _nordland_stream([sv, *without.values(), *grid_svcs], offset, centre)
        res[name] = {**{k: main[k] for k in (*pr, "places", "theta_sigma_calibrated")}, "svc": main["svc"],
                     "neocortex": main["neocortex"],
                     "reached": bool((main["precision"] or 0) >= target["precision_min"]
                                     and main["recall"] >= target["recall_min"])}
        res[f"{name}_without"] = {k: {kk: r[kk] for kk in pr}
                                  for k, r in zip(without, rest[:len(without)], strict=True)}
        (centred_100,) = _nordland_stream([sv], offset, 100)
        res[f"{name}_without"]["centre_window_30 (100 instead)"] = {kk: centred_100[kk] for kk in pr}
        res[f"{name}_grid"] = [{"calibration_quantile": q, "theta_margin": m, "sequence_length": n,
                                **{kk: r[kk] for kk in pr}}
                               for (q, m, n), r in zip(grid, rest[len(without):], strict=True)]
        print(name, json.dumps(res[name]), flush=True)
    # the rule MAP_SETTINGS was chosen by: the highest precision on the validation subset among the
    # grid's settings that reach recall 0.2 there
    best = max((g for g in res["validation_grid"] if g["recall"] >= target["recall_min"]),
               key=lambda g: g["precision"] or 0)
    res["validation_choice"] = {k: best[k] for k in ("calibration_quantile", "theta_margin", "sequence_length")}
    res["validation_choice_is_map_settings"] = res["validation_choice"] == {
        "calibration_quantile": sv["calibration_quantile"], "theta_margin": sv["theta_margin"],
        "sequence_length": sv["sequence"]["length"]}
    return res


def e2e_with_nordland_target(e2e: dict[str, Any], target: dict[str, Any]) -> dict[str, Any]:
    """e2e.json's ``targets_issue14`` with the Nordland row (from maps.json ``nordland_target``)."""
    t = e2e.setdefault("targets_issue14", {})
    t["nordland_precision_min"], t["nordland_recall_min"] = target["target"]["precision_min"], target["target"]["recall_min"]
    t["nordland"] = {k: target["test"][k] for k in ("precision", "recall", "closures", "correct", "places")}
    t["nordland"]["measured_by"] = "bench/maps.py --nordland-target (maps.json nordland_target)"
    t.setdefault("reached", {})["nordland"] = target["test"]["reached"]
    return e2e


_SVC = dict(theta_alpha=384, theta_rho=3, exclude_recent_intervals=3)
_SEQ = {"max_step": 2.0, "slack": 4}
#: (B settings, D settings...) of the Nordland study (theta_sigma None: calibrated on summer)
NORDLAND_LEVERS = [
    (proj, [dict(_SVC, theta_sigma=None), dict(_SVC, theta_sigma=470)]
     + [dict(_SVC, theta_sigma=None, sequence={"length": n, **_SEQ}) for n in (2, 3, 5, 10)]
     + [dict(_SVC, theta_sigma=None, sequence={"min_gap_frames": 200}),
        dict(_SVC, theta_sigma=None, sequence={"length": 3, **_SEQ, "min_gap_frames": 200}),
        # 395 of the 417 places: a winter frame can only match summer frames (the place's own
        # summer frame lies 417 frames back), i.e. D against the summer-only database
        dict(_SVC, theta_sigma=None, sequence={"min_gap_frames": 395})]
     # theta_sigma scaled to the matched union's size (spatial_view.union_normalised)
     + [dict(_SVC, theta_sigma=None, union_normalised=True, **({"sequence": {"min_gap_frames": g}} if g else {}))
        for g in (0, 200, 395)])
    for proj in ({}, {"centre_window": 100}, {"centre_window": 30})]

#: TUC corridor levers: (name, pose-cell overrides, experience-map overrides, sequence filter)
TUC_LEVERS = [("none", {}, {}, None)] + [
    (f"robust_{k}", {}, {"exp_robust_m": k}, None) for k in (1.0, 3.0, 10.0)] + [
    (f"gate_5_{c}", {"odometry_gate": {"radius_m": 5.0, "drift": c}}, {}, None) for c in (0.05, 0.1, 0.2, 0.3, 0.5)] + [
    ("pc_cell_2m", {"pc_cell_x_size": 2.0}, {}, None), ("pc_inject_0.3", {"pc_vt_inject_energy": 0.3}, {}, None)] + [
    (f"sequence_{n}", {}, {}, {"length": n, "max_step": 2.0, "slack": 2}) for n in (2, 3, 5)] + [
    ("odometry_bias", {"odometry_bias": {"enabled": True}}, {}, None)] + [
    # issue #14, second round: the bias sampled from every recognition, modulo half a turn
    (name, {"odometry_bias": {"enabled": True, **bias}}, {}, None) for name, bias in (
        ("bias_templates", {"samples_from": "templates"}),
        ("bias_bidirectional", {"bidirectional": True}),
        ("bias_templates_bidirectional", {"samples_from": "templates", "bidirectional": True}))] + [
    ("gate_20_0.1", {"odometry_gate": {"radius_m": 20.0, "drift": 0.1}}, {}, None),
    ("bias_templates_gate_20_0.1", {"odometry_bias": {"enabled": True, "samples_from": "templates"},
                                    "odometry_gate": {"radius_m": 20.0, "drift": 0.1}}, {}, None),
    ("bias_bidirectional_gate_20_0.1", {"odometry_bias": {"enabled": True, "bidirectional": True},
                                        "odometry_gate": {"radius_m": 20.0, "drift": 0.1}}, {}, None)] + [
    (f"bias_templates_bidirectional_gate_{r}_{c}",
     {"odometry_bias": {"enabled": True, "samples_from": "templates", "bidirectional": True},
      "odometry_gate": {"radius_m": float(r), "drift": c}}, {}, None)
    for r, c in ((2, 0.1), (5, 0.05), (5, 0.1), (10, 0.05), (10, 0.1), (20, 0.02), (20, 0.05), (20, 0.1),
                 (20, 0.15), (20, 0.2), (20, 0.3), (30, 0.1), (40, 0.2))]


def tuc_levers() -> dict[str, Any]:
    """Each TUC lever alone on the corridor's paper settings (positions-only ground truth)."""
    from neoslam_stream.datasets import tuc
    from neoslam_stream.datasets.tuc import TUC_PAPER_SETTINGS as S

    res = {}
    for name, pc, em, seq in TUC_LEVERS:
        r = tuc.run({**S["pc"], **pc}, {**S["em"], **em}, S["threshold"], S["min_gap_s"], sequence=seq)
        res[name] = {k: r[k] for k in ("map_mean_m", "map_on_final_mean_m", "odometry_mean_m", "recognised_frames",
                                       "gate_refused", "yaw_bias_rad_s", "yaw_bias_samples")}
        print("tuc", name, res[name], flush=True)
    return res


def base_config_dict() -> dict:
    """The paper profile's settings (configs/paper.yaml when it ships, else the settings the
    default had before issue #14)."""
    from neoslam_stream.config import ConfigError
    from neoslam_stream.config import load_config as load

    try:
        return load("paper").model_dump()
    except ConfigError:  # the paper profile comes with another part of issue #14
        return load(None, PAPER_FALLBACK).model_dump()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", default=None, help="lever names to run")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--out", default=str(RESULTS / "maps.json"))
    ap.add_argument("--nordland", action="store_true", help="the Nordland levers instead")
    ap.add_argument("--tuc", action="store_true", help="the TUC corridor levers instead")
    ap.add_argument("--nordland-ceiling", action="store_true",
                    help="where Nordland's place information is lost (A, B; summer only vs the stream)")
    ap.add_argument("--nordland-target", action="store_true",
                    help="issue #14's Nordland target with datasets.nordland.MAP_SETTINGS (also into e2e.json)")
    args = ap.parse_args()
    from neoslam_stream.config import FullRunConfig

    results: dict[str, Any] = {}
    out = Path(args.out)
    if out.exists():
        results = json.loads(out.read_text())
    if args.nordland or args.tuc or args.nordland_ceiling or args.nordland_target:
        if args.nordland_target:
            results["nordland_target"] = nordland_target()
            e2e_path = RESULTS / "e2e.json"
            if e2e_path.exists():
                e2e_path.write_text(json.dumps(e2e_with_nordland_target(json.loads(e2e_path.read_text()),
                                                                        results["nordland_target"]), indent=2))
        if args.nordland_ceiling:
            results["nordland_ceiling"] = nordland_ceiling(nordland_inputs())
            print(json.dumps(results["nordland_ceiling"], indent=1))
        if args.nordland:
            data_n = nordland_inputs()
            results["nordland"] = [
                {k: r[k] for k in ("closures", "correct", "precision", "recall", "svc", "proj")}
                for proj, svcs in NORDLAND_LEVERS for r in run_nordland(proj, svcs, data_n)]
        if args.tuc:
            results["tuc_levers"] = tuc_levers()
        out.write_text(json.dumps(results, indent=2))
        return
    data = synthetic_inputs(args.frames)
    base = base_config_dict()
    for name, over in LEVERS.items():
        if args.only is not None and name not in args.only:
            continue
        cfg = FullRunConfig.model_validate(merge_dicts(base, over))
        t0 = time.perf_counter()
        r = run_synthetic(cfg, data, CACHE / "runs" / name)
        r["wall_s"] = round(time.perf_counter() - t0, 1)
        results.setdefault("synthetic", {})[name] = {"settings": over, **r}
        print(name, json.dumps(r), flush=True)
        out.write_text(json.dumps(results, indent=2))


#: the default config's settings before issue #14 (what configs/paper.yaml freezes)
PAPER_FALLBACK: dict = {
    "run": {"pipeline": "neoslam", "topology": "pipeline", "mode": "lossless", "live": True},
    "source": {"kind": "synthetic", "params": {"seed": 0}},
    "features": {"backbone": "auto", "frame_stride": 1},
    "projector": {"projection": "gaussian", "seed": 42},
    "neocortex": {"tie_break": "lowest"},
    "spatial_view": {"theta_alpha": 384, "theta_rho": 3, "theta_sigma": 470, "exclude_recent_intervals": 3},
    "pose_cells": {"pc_dim_xy": 21, "pc_cell_x_size": 0.25, "pc_vt_inject_energy": 0.15,
                   "exp_delta_pc_threshold": 2.0},
    "experience_map": {"exp_loops": 20, "exp_initial_em_deg": 0},
}

#: lever name -> config overrides on the paper profile (each alone; "default" = all kept)
LEVERS: dict[str, dict] = {
    "paper": {},
    "sequence_3": {"spatial_view": {"sequence": {"length": 3, "max_step": 2.0, "slack": 4}}},
    "sequence_5": {"spatial_view": {"sequence": {"length": 5, "max_step": 2.0, "slack": 4}}},
    "sequence_10": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}}},
    "robust_0.5": {"experience_map": {"exp_robust_m": 0.5}},
    "robust_1": {"experience_map": {"exp_robust_m": 1.0}},
    "robust_2": {"experience_map": {"exp_robust_m": 2.0}},
    "pc_inject_0.3": {"pose_cells": {"pc_vt_inject_energy": 0.3}},
    "pc_torus_15m": {"pose_cells": {"pc_dim_xy": 30, "pc_cell_x_size": 0.5}},
    "centre_100": {"projector": {"centre_window": 100}},
    "gate_1_0.1": {"pose_cells": {"odometry_gate": {"radius_m": 1.0, "drift": 0.1}}},
    "gate_1_0.2": {"pose_cells": {"odometry_gate": {"radius_m": 1.0, "drift": 0.2}}},
    "gap_100": {"spatial_view": {"sequence": {"min_gap_frames": 100}}},
    "seq5_gap100": {"spatial_view": {"sequence": {"length": 5, "max_step": 2.0, "slack": 4, "min_gap_frames": 100}}},
    "seq5_gap100_gate": {"spatial_view": {"sequence": {"length": 5, "max_step": 2.0, "slack": 4,
                                                       "min_gap_frames": 100}},
                         "pose_cells": {"odometry_gate": {"radius_m": 1.0, "drift": 0.1}}},
    "seq10_gap100": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4, "min_gap_frames": 100}}},
    "seq10_sigma440": {"spatial_view": {"theta_sigma": 440,
                                        "sequence": {"length": 10, "max_step": 2.0, "slack": 4}}},
    "seq10_inject0.3": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                        "pose_cells": {"pc_vt_inject_energy": 0.3}},
    "centre_seq5": {"projector": {"centre_window": 100},
                    "spatial_view": {"sequence": {"length": 5, "max_step": 2.0, "slack": 4}}},
    "centre_seq10": {"projector": {"centre_window": 100},
                     "spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}}},
    "seq10_robust1": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                      "experience_map": {"exp_robust_m": 1.0}},
    "seq10_gate_3_0.3": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                         "pose_cells": {"odometry_gate": {"radius_m": 3.0, "drift": 0.3}}},
    "seq10_loops100": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                       "experience_map": {"exp_loops": 100}},
    "seq5_gate_1_0.1": {"spatial_view": {"sequence": {"length": 5, "max_step": 2.0, "slack": 4}},
                        "pose_cells": {"odometry_gate": {"radius_m": 1.0, "drift": 0.1}}},
    "odometry_bias": {"pose_cells": {"odometry_bias": {"enabled": True}}},
    "seq10_odometry_bias": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                            "pose_cells": {"odometry_bias": {"enabled": True}}},
    **{f"seq10_bias_forget{f}": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                                 "pose_cells": {"odometry_bias": {"enabled": True, "forget_s": float(f)}}}
       for f in (0, 60, 300)},
    **{f"seq10_bias_{name}": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                              "pose_cells": {"odometry_bias": {"enabled": True}, **pc},
                              "experience_map": em}
       for name, pc, em in (("torus_30x0.5", {"pc_dim_xy": 30, "pc_cell_x_size": 0.5}, {}),
                            ("torus_41x0.25", {"pc_dim_xy": 41}, {}),
                            ("inject0.3", {"pc_vt_inject_energy": 0.3}, {}),
                            ("loops100", {}, {"exp_loops": 100}),
                            *((f"loops{n}", {}, {"exp_loops": n}) for n in (50, 200, 300, 400, 500, 700)),
                            ("loops1000", {}, {"exp_loops": 1000}),
                            ("loops300_robust1", {}, {"exp_loops": 300, "exp_robust_m": 1.0}),
                            ("robust1", {}, {"exp_robust_m": 1.0}))},
    "union_normalised": {"spatial_view": {"union_normalised": True}},
    "default_union_normalised": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4},
                                                  "union_normalised": True},
                                 "pose_cells": {"odometry_bias": {"enabled": True}},
                                 "experience_map": {"exp_loops": 300}},
    # a closure's margin over the runner-up (spatial_view.theta_margin; Nordland's settings use 5)
    "margin_5": {"spatial_view": {"theta_margin": 5}},
    **{f"default_margin_{m}": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4},
                                               "theta_margin": m},
                              "pose_cells": {"odometry_bias": {"enabled": True}},
                              "experience_map": {"exp_loops": 300}} for m in (2, 5, 10, 20, 40)},
    "seq10_bias_templates": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                             "pose_cells": {"odometry_bias": {"enabled": True, "samples_from": "templates"}}},
    **{f"seq10_bias_gate_{r}_{c}": {"spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
                                    "pose_cells": {"odometry_bias": {"enabled": True},
                                                   "odometry_gate": {"radius_m": float(r), "drift": c}}}
       for r, c in ((1, 0.1), (2, 0.1), (5, 0.1))},
    **{f"seq10_bias_templates_gate_{r}_{c}": {
        "spatial_view": {"sequence": {"length": 10, "max_step": 2.0, "slack": 4}},
        "pose_cells": {"odometry_bias": {"enabled": True, "samples_from": "templates"},
                       "odometry_gate": {"radius_m": float(r), "drift": c}}}
       for r, c in ((1, 0.1), (2, 0.1), (5, 0.1))},
}


if __name__ == "__main__":
    main()
