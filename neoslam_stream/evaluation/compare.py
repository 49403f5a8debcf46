"""NeoSLAM (the run's config), NeoSLAM (the paper's profile) and RatSLAM on the same stream: the
comparison table (compare.json) and figures (compare.png: the maps; compare_pr.png: the loop
closures' precision-recall curves on one plot)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from . import evaluate_run
from .plots import plot_compare, plot_pr

#: the branches of a ``neoslam compare`` run: compare.json key, label, sub-folder, node prefix
BRANCHES = (("neoslam", "NeoSLAM (default)", "", ""), ("neoslam_paper", "NeoSLAM (paper)", "paper", "pp_"),
            ("ratslam", "RatSLAM", "ratslam", "rs_"))
#: compare.json columns, with the short headers of the printed table
COLUMNS = (("frames_processed", "frames"), ("trajectory_ape_mean_m", "APE mean m"),
           ("trajectory_ape_max_m", "APE max m"), ("map_trajectory_ape_mean_m", "APE on map m"),
           ("map_paper_mean_m", "paper mean m"),
           ("map_nodes", "map nodes"), ("loop_closures", "closures"), ("loop_precision", "precision"),
           ("loop_recall", "recall"))
#: the stage whose processed count is a branch's frames (its template producer)
_TEMPLATE_STAGES = {"neoslam": "D", "neoslam_paper": "pp_D", "ratslam": "rs_local_view"}


def _branch_stages(key: str, stages: dict[str, Any]) -> dict[str, Any]:
    """The stages of a branch in the run's report: its own (by prefix); the paper branch also the
    default branch's stages it shares (those with no ``pp_`` twin)."""
    if key == "ratslam":
        return {s: v for s, v in stages.items() if s.startswith("rs_")}
    default = {s: v for s, v in stages.items() if not s.startswith(("rs_", "pp_"))}
    if key == "neoslam":
        return default
    own = {s: v for s, v in stages.items() if s.startswith("pp_")}
    return {**{s: v for s, v in default.items() if f"pp_{s}" not in own}, **own}


def compare_runs(out: Path, report: dict[str, Any], radius: float = 1.0) -> dict[str, Any]:
    """Evaluate a ``neoslam compare`` run folder (NeoSLAM in ``out``, the paper's profile in
    ``out/paper`` unless it equals the run's config, RatSLAM in ``out/ratslam``): returns the table
    (closure precision and recall at ``radius`` metres), and writes compare.json, compare.png and
    compare_pr.png into ``out``."""
    dirs: dict[str, Path] = {}
    for key, _label, sub, _prefix in BRANCHES:
        d = out / sub if sub else out
        if sub == "paper" and not d.is_dir():  # the paper's profile is the run's config: one branch
            d = out
        dirs[key] = d
    for name in ("groundtruth.tum", "odometry.tum", "report.json"):
        for d in dirs.values():
            if (out / name).exists() and d != out and d.is_dir():
                shutil.copy(out / name, d / name)
    stages = report.get("stages", {})
    table: dict[str, Any] = {}
    closures: dict[str, Any] = {}
    for key, label, _sub, _prefix in BRANCHES:
        d = dirs[key]
        ev = evaluate_run(d, radius=radius) if (d / "groundtruth.tum").exists() else {}
        mine = _branch_stages(key, stages)
        tpl = _TEMPLATE_STAGES[key] if _TEMPLATE_STAGES[key] in mine else "D"
        lc = ev.get("loop_closures", {})
        table[key] = {
            "label": label, "run_dir": str(d), "same_as_default": key == "neoslam_paper" and d == out,
            "frames_processed": mine.get(tpl, {}).get("processed"),
            "trajectory_ape_mean_m": ev.get("trajectory_ape", {}).get("mean_m"),
            "trajectory_ape_max_m": ev.get("trajectory_ape", {}).get("max_m"),
            "map_trajectory_ape_mean_m": ev.get("map_trajectory_ape", {}).get("mean_m"),
            "map_paper_mean_m": ev.get("map_paper", {}).get("mean_m"),
            "map_paper_max_m": ev.get("map_paper", {}).get("max_m"),
            "map_nodes": ev.get("map_nodes"),
            "loop_closures": lc.get("closures"),
            "loop_correct": lc.get("correct"),
            "loop_precision": lc.get("precision"),
            "loop_recall": lc.get("recall"),
            "loop_re_recognitions": (lc.get("re_recognitions") or {}).get("count"),
            "loop_pr_area": (lc.get("precision_recall") or {}).get("area"),
            "loop_recall_at_precision": (lc.get("precision_recall") or {}).get("recall_at_precision"),
            "loop_radius_m": radius,
            "stage_tau_p50_ms": {s: v.get("tau_p50_ms") for s, v in mine.items()},
        }
        closures[label] = {} if table[key]["same_as_default"] else lc  # one curve per distinct branch
        if key == "neoslam" and "odometry_ape" in ev:
            table["odometry"] = {"label": "odometry", "trajectory_ape_mean_m": ev["odometry_ape"]["mean_m"],
                                 "trajectory_ape_max_m": ev["odometry_ape"]["max_m"]}
    (out / "compare.json").write_text(json.dumps(table, indent=2))
    plot_compare({table[k]["label"]: dirs[k] for k, *_ in BRANCHES}, out / "compare.png",
                 {table[k]["label"]: table[k]["trajectory_ape_mean_m"] for k, *_ in BRANCHES})
    plot_pr({k: v for k, v in closures.items() if v}, out / "compare_pr.png")
    return table
