"""End-to-end benchmark: NeoSLAM (default and paper profiles) and RatSLAM on the full synthetic
route -> bench/results/e2e.json (discussed in docs/end_to_end.md and docs/mapping.md).

Per run {name} (neoslam, ratslam, paper_neoslam = configs/paper.yaml): {name}_mean_m / _max_m
(trajectory APE after SE(2) alignment), {name}_map_trajectory_mean_m (trajectory_map.tum: every
frame re-expressed on the final map), {name}_rpe_mean_m (the relative pose error over 1, 5 and
10 m of travel), {name}_precision / _recall / _closures (``neoslam evaluate``'s rule: a match is a
loop closure only when the robot travelled more than 5 m since the frame where what it matched was
first seen, and correct when that frame lies within ``closure_radius_m`` = 1 m of the frame's true
position), {name}_re_recognitions (the other matches: a place just passed), {name}_pr_area and
_recall_at_precision (the precision-recall curve over the closures' confidence),
{name}_precision_by_template (the matched template's first frame instead); odometry_mean_m, frames,
fps_lossless, per-stage tau, the ratios to odometry, and ``targets``: the mapping targets and
which this run reached (the Nordland row comes from the generalisation.json beside ``--out``, see
``bench/generalisation.py``). Also writes e2e_map.png (NeoSLAM's map) and e2e_pr.png (the three
precision-recall curves). ``--inprocess``: the in-process API's cores instead of the processes of
``neoslam run`` (no zenoh; the same templates and poses as a lossless run), for a loaded machine.
Run: ``.venv/bin/python bench/e2e.py [--frames N] [--inprocess] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.evaluation import evaluate_run, loop_closure_quality, read_tum  # noqa: E402
from neoslam_stream.evaluation.plots import plot_pr  # noqa: E402
from neoslam_stream.launch import run  # noqa: E402


def run_inprocess(cfg, run_dir: Path) -> dict:
    """Every frame of the config's source through the in-process API; the run folder as
    ``neoslam run`` writes it (templates.csv, trajectory.tum, map.json, groundtruth/odometry.tum)."""
    import numpy as np

    from neoslam_stream.api import NeoSLAM, RatSLAM
    from neoslam_stream.sources.synthetic import SyntheticWorldSource
    from neoslam_stream.tum import integrate_odometry, write_tum

    run_dir.mkdir(parents=True, exist_ok=True)
    slam = (NeoSLAM if cfg.run.pipeline == "neoslam" else RatSLAM)(cfg, run_dir=run_dir)
    gt, odo = [], []
    t0 = time.perf_counter()
    for f in SyntheticWorldSource(**cfg.source.params):
        slam.step(f.image, odometry=f.odom, stamp=f.stamp, frame=f.frame)
        gt.append((f.stamp, *f.groundtruth))
        odo.append(f.odom)
    slam.finish()
    secs = time.perf_counter() - t0
    write_tum(run_dir / "groundtruth.tum", np.array(gt))
    write_tum(run_dir / "odometry.tum", integrate_odometry([g[0] for g in gt], odo))
    (run_dir / "report.json").write_text(json.dumps({"source": {"kind": "synthetic"}}))
    info = slam.info()
    return {"frames_out": len(gt), "f_out": len(gt) / secs, "in_process": True,
            "backbone": info.get("A", {}).get("backbone")}


#: the mapping targets of the default NeoSLAM run on the synthetic world
TARGETS = {"precision_min": 0.99, "ape_mean_max_m": 0.5, "ape_vs_odometry_max": 0.25, "ape_below_ratslam": True}


def targets_reached(res: dict) -> dict:
    """The targets and which of them this run reached (APE: trajectory.tum's, per frame as online;
    ``ape_mean_on_final_map``: the same bound for trajectory_map.tum, every frame on the final map),
    and ``online_floor`` (evaluation.online_floor: the online APE of odometry until the first return
    to a place, exact from then on)."""
    t = TARGETS
    floor = res.get("neoslam", {}).get("evaluation", {}).get("online_floor", {})
    return {**t, "online_floor": floor, "reached": {"precision": (res["neoslam_precision"] or 0) >= t["precision_min"],
                             "ape_mean": res["neoslam_mean_m"] <= t["ape_mean_max_m"],
                             "ape_mean_on_final_map": res["neoslam_map_trajectory_mean_m"] <= t["ape_mean_max_m"],
                             "ape_vs_odometry": res["neoslam_ape_vs_odometry"] <= t["ape_vs_odometry_max"],
                             "below_ratslam": res["neoslam_mean_m"] < res["ratslam_mean_m"]}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=None, help="default: the whole route (2445 frames)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"))
    ap.add_argument("--inprocess", action="store_true", help="the in-process API instead of processes (no zenoh)")
    args = ap.parse_args()
    out = Path(args.out)
    work = out / "e2e_runs"
    res: dict = {"closure_radius_m": 1.0, "in_process": bool(args.inprocess)}
    curves: dict = {}
    for name, pipeline, profile in (("neoslam", "neoslam", "default"), ("ratslam", "ratslam", "default"),
                                    ("paper_neoslam", "neoslam", "paper")):
        params = {"seed": 0}
        if args.frames:
            params["frames"] = args.frames
        over = {"run": {"pipeline": pipeline, "live": False}, "source": {"kind": "synthetic", "params": params}}
        cfg = load_config(profile, over)
        if args.inprocess:
            report = run_inprocess(cfg, work / name)
            res[name] = {"report": report}
        else:
            r = run(cfg, work / name)
            report = {"frames_out": r.report["frames_out"], "f_out": r.report["f_out"],
                      "backbone": r.report["stages"].get("A", {}).get("info", {}).get("backbone")}
            res[name] = {"report": {k: r.report[k] for k in ("frames_in", "frames_out", "f_out", "loss",
                                                                "f_pipeline_predicted", "bottleneck")},
                         "tau_p50_ms": {s: v["tau_p50_ms"] for s, v in r.report["stages"].items()}}
        ev = evaluate_run(work / name, radius=res["closure_radius_m"])
        res[name]["evaluation"] = ev
        res[f"{name}_mean_m"] = ev["trajectory_ape"]["mean_m"]
        res[f"{name}_max_m"] = ev["trajectory_ape"]["max_m"]
        if "map_trajectory_ape" in ev:  # every frame re-expressed on the final map (trajectory_map.tum)
            res[f"{name}_map_trajectory_mean_m"] = ev["map_trajectory_ape"]["mean_m"]
        res[f"{name}_precision"] = ev["loop_closures"]["precision"]
        # the older criterion as well: the matched TEMPLATE's first frame within the radius (what
        # the pose cells act on) rather than the first frame of the matched interval (closures.csv)
        by_template = loop_closure_quality(work / name / "templates.csv", read_tum(work / name / "groundtruth.tum"),
                                           res["closure_radius_m"])
        res[f"{name}_precision_by_template"] = by_template["precision"]
        res[f"{name}_recall"] = ev["loop_closures"]["recall"]
        res[f"{name}_closures"] = ev["loop_closures"]["closures"]
        res[f"{name}_re_recognitions"] = ev["loop_closures"]["re_recognitions"]["count"]
        pr = ev["loop_closures"].get("precision_recall") or {}
        res[f"{name}_pr_area"] = pr.get("area")
        res[f"{name}_recall_at_precision"] = pr.get("recall_at_precision")
        res[f"{name}_rpe_mean_m"] = {k: v["mean_m"] for k, v in ev["trajectory_rpe"].items()}
        curves[name] = ev["loop_closures"]
        if name == "neoslam":
            res["odometry_mean_m"] = ev["odometry_ape"]["mean_m"]
            res["odometry_max_m"] = ev["odometry_ape"]["max_m"]
            res["frames"] = report["frames_out"]
            res["fps_lossless"] = report["f_out"]
            res["backbone"] = report["backbone"]
            shutil.copy(work / name / "map.png", out / "e2e_map.png")
        print(name, res[f"{name}_mean_m"], res[f"{name}_precision"], flush=True)
    res["neoslam_ape_vs_odometry"] = res["neoslam_mean_m"] / res["odometry_mean_m"]
    res["paper_neoslam_ape_vs_odometry"] = res["paper_neoslam_mean_m"] / res["odometry_mean_m"]
    if "neoslam_map_trajectory_mean_m" in res:
        res["neoslam_map_trajectory_vs_odometry"] = res["neoslam_map_trajectory_mean_m"] / res["odometry_mean_m"]
    res["targets"] = targets_reached(res)
    plot_pr({"NeoSLAM (default)": curves["neoslam"], "NeoSLAM (paper)": curves["paper_neoslam"],
             "RatSLAM": curves["ratslam"]}, out / "e2e_pr.png")
    gen = out / "generalisation.json"  # the Nordland row comes from bench/generalisation.py
    if gen.exists() and "nordland:0" in (g := json.loads(gen.read_text())).get("test", {}):
        nd = g["test"]["nordland:0"]["default"]
        t = res["targets"]
        t["nordland_precision_min"], t["nordland_recall_min"] = 0.9, 0.2
        t["nordland"] = {**{k: nd[k] for k in ("precision", "recall", "closures", "correct")},
                         "measured_by": "bench/generalisation.py (generalisation.json test nordland:0, the default)"}
        t["reached"]["nordland"] = bool((nd["precision"] or 0) >= 0.9 and nd["recall"] >= 0.2)
    (out / "e2e.json").write_text(json.dumps(res, indent=2))
    print(json.dumps({k: v for k, v in res.items() if not isinstance(v, dict)}, indent=2))


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    main()
