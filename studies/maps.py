"""The lever study of the mapping settings -> studies/results/maps.json (studies/levers.md).

Each lever of studies/settings/levers.yaml is measured ALONE against the paper profile
(``configs/paper.yaml``) and the kept levers together (the default), on:

* the synthetic world (the full default route, 2445 frames, three laps) through the in-process
  API's cores (the same templates and poses as a lossless ``neoslam run``): APE of the
  experience-map trajectory after SE(2) alignment, odometry's APE, closure precision / recall;
* the TU Chemnitz corridor (bench/tuc_corridor.py, back end only): map error vs odometry's;
* Nordland summer -> winter (bench/nordland.py) through B, C, D (the levers of the round before the
  calibrated default; the default itself is measured by bench/generalisation.py).

A's features are computed once per data set and cached in ``$NEOSLAM_CACHE`` (default
``/tmp/neoslam_maps``), never in the repository; C's cells are cached per (B, C) configuration.
Run: ``.venv/bin/python studies/maps.py [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import nordland
import numpy as np
import tuc_corridor
import yaml
from bench_settings import cache_key, check_sections, load_settings

from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.config import FullRunConfig, load_config
from neoslam_stream.evaluation import evaluate_run, loop_closure_quality
from neoslam_stream.runtime.config import merge_dicts
from neoslam_stream.tum import integrate_odometry, write_tum

CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_maps"))
RESULTS = _paths.RESULTS


def levers() -> dict[str, Any]:
    """studies/settings/levers.yaml, every lever's sections checked by the run config's models."""
    lv = yaml.safe_load((_paths.SETTINGS / "levers.yaml").read_text())
    for name, over in lv["synthetic"].items():
        check_sections(over, f"levers.yaml synthetic.{name}")
    for i, sv in enumerate(lv["nordland"]["spatial_view"]):
        check_sections({"spatial_view": sv}, f"levers.yaml nordland.spatial_view[{i}]")
    for i, proj in enumerate(lv["nordland"]["projector"]):
        check_sections({"projector": proj}, f"levers.yaml nordland.projector[{i}]")
    for name, over in lv["tuc"].items():
        check_sections({k: v for k, v in over.items() if k != "protocol"}, f"levers.yaml tuc.{name}")
    return lv


def synthetic_inputs(frames: int | None = None) -> dict[str, np.ndarray]:
    """A's features (the default config's front end, one frame at a time), odometry, stamps and
    ground truth of the synthetic route, computed once and cached."""
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default")
    fe = FrontEnd(cfg.front_end())
    path = CACHE / f"synthetic_{cache_key([fe.config.features.model_dump(), frames])}.npz"
    if path.exists():
        return dict(np.load(path))
    CACHE.mkdir(parents=True, exist_ok=True)
    params = dict(cfg.source.params)
    if frames:
        params["frames"] = frames
    F, odo, gt, st = [], [], [], []
    for sf in SyntheticWorldSource(**params):
        F.append(fe.features([sf.image])[0])
        odo.append(sf.odom)
        gt.append(sf.groundtruth)
        st.append(sf.stamp)
    data = {"features": np.stack(F).astype(np.float32), "odom": np.array(odo), "gt": np.array(gt),
            "stamps": np.array(st), "backbone": np.array(fe.extractor.backbone)}
    np.savez(path, **data)
    return data


def front_end(cfg: Any, backbone: str) -> FrontEnd:
    """``cfg``'s front end on features of A's ``backbone`` (B's input size follows it)."""
    return FrontEnd(cfg.front_end(), features=cfg.features.model_copy(update={"backbone": backbone}))


def sdrs(cfg: Any, data: dict[str, np.ndarray]) -> list[np.ndarray]:
    """C's cells per frame for B and C of ``cfg`` (cached per their parameters); B gets one frame
    at a time, as its node does in a lossless run."""
    fe = front_end(cfg, str(data["backbone"]))
    c = fe.config
    path = CACHE / f"sdr_{cache_key([c.projector.model_dump(), c.neocortex.model_dump(), len(data['stamps'])])}.npz"
    if path.exists():
        z = np.load(path)
        return np.split(z["cells"], z["ptr"][1:-1])
    out = [fe.cells(fe.bits(f[None])[0]) for f in data["features"]]
    np.savez(path, cells=np.concatenate(out), ptr=np.concatenate([[0], np.cumsum([len(o) for o in out])]))
    return out


def run_synthetic(cfg: Any, data: dict[str, np.ndarray], run_dir: Path) -> dict[str, Any]:
    """D and the back end on the cached cells of ``cfg``'s B and C, as the in-process API runs
    them; writes the run folder and evaluates it."""
    from neoslam_stream.api import NeoSLAM

    seq = sdrs(cfg, data)
    run_dir.mkdir(parents=True, exist_ok=True)
    slam = NeoSLAM(cfg, run_dir=run_dir)
    t0 = time.perf_counter()
    for i, cells in enumerate(seq):
        st = float(data["stamps"][i])
        v, w, dt = data["odom"][i]
        slam.step_cells(cells, odometry=(float(v), float(w), float(dt)), stamp=st, frame=i)
    slam.finish()
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

#: the Nordland protocol of bench/settings/nordland.yaml (tests/test_frontend_nordland.py's subset)
NORDLAND = {k: load_settings("nordland")["protocol"][k] for k in ("step", "min_std", "tolerance")}


def nordland_inputs(backbone: str = "efficientnet_lite0", offset: int = 0) -> dict[str, Any]:
    """A's features of the summer then winter frames (8 at a time, as the nodes batch), cached.
    ``offset``: every step-th thumbnail from the offset-th on (4: the validation subset, disjoint
    from the test protocol's offset 0)."""
    path = CACHE / f"nordland_{cache_key([backbone, NORDLAND] + ([offset] if offset else []))}.npz"
    if path.exists():
        z = np.load(path)
        return {"features": z["features"], "ids": z["ids"].tolist(), "n": int(z["n"]), "backbone": str(z["backbone"])}
    CACHE.mkdir(parents=True, exist_ok=True)
    feats, ids, n, ran = nordland.stream_features(backbone, NORDLAND["step"], None, NORDLAND["min_std"], offset)
    np.savez(path, features=feats.astype(np.float32), ids=np.array(ids), n=n, backbone=np.array(ran))
    return {"features": feats, "ids": list(ids), "n": n, "backbone": ran}


def run_nordland(proj: dict, svc_list: list[dict], data: dict[str, Any]) -> list[dict]:
    """B (``proj`` on top of the defaults), the real C and D (each of ``svc_list``; theta_sigma None:
    calibrated on summer as in the Nordland test) on the cached features; precision / recall."""
    bits, sdr = nordland_sdrs(proj, data)
    ids, n = data["ids"], data["n"]
    out = []
    for svc, _, _, r, _ in nordland.spatial_view_runs(bits, sdr, ids, n, svc_list, NORDLAND["tolerance"]):
        r.update({"svc": svc, "proj": proj, "places": n})
        out.append(r)
    return out


def nordland_sdrs(proj: dict, data: dict[str, Any]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """B's bits (``proj`` on top of the defaults) and the real C's winner cells of every frame, cached."""
    feats = data["features"]
    path = CACHE / f"nordland_sdr_{cache_key([proj, feats.shape, float(feats.sum(dtype=np.float64))])}.npz"
    if path.exists():
        z = np.load(path)
        bits = np.split(z["bits"], z["bptr"][1:-1])
        sdr = np.split(z["cells"], z["cptr"][1:-1])
    else:
        fe = FrontEnd(features={"backbone": data["backbone"]}, projector={"projection": "gaussian", "seed": 42, **proj})
        bits, sdr = nordland.stream_codes(feats, fe)
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
    bits, sdr = nordland_sdrs(proj, data)
    ids, n = np.asarray(data["ids"]), data["n"]
    svc = [{"theta_sigma": None, "sequence": {"min_gap_frames": 395}}]
    ((params, _, out, res, _),) = list(nordland.spatial_view_runs(bits, sdr, list(ids), n, svc, NORDLAND["tolerance"]))
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
    sim = nordland.overlaps(sdr, int(max(c.max() for c in sdr)) + 1)[n:, :n]
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
        res[name] = both(nordland.overlaps(bits)[n:].astype(np.float64))
    res["d_summer_only"] = nordland_d_closures(data, {"centre_window": 30})
    res["about"] = ("winter frame -> best match by similarity alone; summer_only: the summer frames; stream: "
                    "what D searches (summer + earlier winter frames, less the last 3); correct: a summer frame "
                    f"within {NORDLAND['tolerance']} source frames; precision at recall 0.2 ranking the frames by "
                    "their best score or by the margin to the runner-up")
    return res


def tuc_levers(tuc_levers: dict[str, Any]) -> dict[str, Any]:
    """Each TUC lever (sections on top of bench/settings/tuc_paper.yaml) alone on the corridor."""
    paper = load_settings("tuc_paper")
    res = {}
    for name, over in tuc_levers.items():
        s = merge_dicts(paper, over)
        r = tuc_corridor.run(s["pose_cells"], s["experience_map"], **s["protocol"])
        res[name] = {k: r[k] for k in ("map_mean_m", "map_on_final_mean_m", "odometry_mean_m", "recognised_frames",
                                       "gate_refused", "yaw_bias_rad_s", "yaw_bias_samples")}
        print("tuc", name, res[name], flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", default=None, help="lever names to run")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--out", default=str(RESULTS / "maps.json"))
    ap.add_argument("--nordland", action="store_true", help="the Nordland levers instead")
    ap.add_argument("--tuc", action="store_true", help="the TUC corridor levers instead")
    ap.add_argument("--nordland-ceiling", action="store_true",
                    help="where Nordland's place information is lost (A, B; summer only vs the stream)")
    args = ap.parse_args()
    lv = levers()

    results: dict[str, Any] = {}
    out = Path(args.out)
    if out.exists():
        results = json.loads(out.read_text())
    if args.nordland or args.tuc or args.nordland_ceiling:
        if args.nordland_ceiling:
            results["nordland_ceiling"] = nordland_ceiling(nordland_inputs())
            print(json.dumps(results["nordland_ceiling"], indent=1))
        if args.nordland:
            data_n = nordland_inputs()
            results["nordland"] = [
                {k: r[k] for k in ("closures", "correct", "precision", "recall", "svc", "proj")}
                for proj in lv["nordland"]["projector"]
                for r in run_nordland(proj, [{"theta_sigma": None, **sv} for sv in lv["nordland"]["spatial_view"]], data_n)]
        if args.tuc:
            results["tuc_levers"] = tuc_levers(lv["tuc"])
        out.write_text(json.dumps(results, indent=2))
        return
    data = synthetic_inputs(args.frames)
    base = load_config("paper").model_dump()
    for name, over in lv["synthetic"].items():
        if args.only is not None and name not in args.only:
            continue
        cfg = FullRunConfig.model_validate(merge_dicts(base, over))
        t0 = time.perf_counter()
        r = run_synthetic(cfg, data, CACHE / "runs" / name)
        r["wall_s"] = round(time.perf_counter() - t0, 1)
        results.setdefault("synthetic", {})[name] = {"settings": over, **r}
        print(name, json.dumps(r), flush=True)
        out.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
