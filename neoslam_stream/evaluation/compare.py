"""NeoSLAM and RatSLAM on the same stream: the comparison table (compare.json) and figure."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from . import evaluate_run
from .plots import plot_compare

#: compare.json columns, with the short headers of the printed table
COLUMNS = (("frames_processed", "frames"), ("trajectory_ape_mean_m", "APE mean m"),
           ("trajectory_ape_max_m", "APE max m"), ("map_paper_mean_m", "paper mean m"),
           ("map_paper_max_m", "paper max m"), ("loop_closures", "loops"), ("loop_precision", "precision"))


def compare_runs(out: Path, report: dict[str, Any]) -> dict[str, Any]:
    """Evaluate a ``neoslam compare`` run folder (NeoSLAM in ``out``, RatSLAM in ``out/ratslam``):
    returns the table, and writes compare.json and compare.png into ``out``."""
    dirs = {"neoslam": out, "ratslam": out / "ratslam"}
    for name in ("groundtruth.tum", "odometry.tum"):
        if (out / name).exists() and dirs["ratslam"].is_dir():
            shutil.copy(out / name, dirs["ratslam"] / name)
    stages = report.get("stages", {})
    table: dict[str, Any] = {}
    for pipeline, d in dirs.items():
        ev = evaluate_run(d) if (d / "groundtruth.tum").exists() else {}
        mine = {s: v for s, v in stages.items() if s.startswith("rs_") == (pipeline == "ratslam")}
        table[pipeline] = {
            "frames_processed": max((v.get("processed", 0) for s, v in mine.items()
                                     if s in ("A", "rs_local_view")), default=None),
            "trajectory_ape_mean_m": ev.get("trajectory_ape", {}).get("mean_m"),
            "trajectory_ape_max_m": ev.get("trajectory_ape", {}).get("max_m"),
            "map_paper_mean_m": ev.get("map_paper", {}).get("mean_m"),
            "map_paper_max_m": ev.get("map_paper", {}).get("max_m"),
            "loop_closures": ev.get("loop_closures", {}).get("closures"),
            "loop_precision": ev.get("loop_closures", {}).get("precision"),
            "stage_tau_p50_ms": {s: v.get("tau_p50_ms") for s, v in mine.items()},
        }
        if pipeline == "neoslam" and "odometry_ape" in ev:
            table["odometry"] = {"trajectory_ape_mean_m": ev["odometry_ape"]["mean_m"],
                                 "trajectory_ape_max_m": ev["odometry_ape"]["max_m"]}
    (out / "compare.json").write_text(json.dumps(table, indent=2))
    plot_compare(dirs, out / "compare.png")
    return table
