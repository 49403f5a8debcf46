"""End-to-end benchmark: NeoSLAM and RatSLAM on the full synthetic route -> bench/results/e2e.json.

Keys: neoslam_mean_m, neoslam_max_m, ratslam_mean_m, ratslam_max_m (trajectory APE after SE(2)
alignment), odometry_mean_m, frames, fps_lossless (NeoSLAM, pipeline topology, lossless), plus
the paper's per-node metric, loop closures and per-stage tau. Also writes e2e_map.png.
Run: ``.venv/bin/python bench/e2e.py [--frames N]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.evaluation import evaluate_run  # noqa: E402
from neoslam_stream.launch import run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=None, help="default: the whole route (2472 frames)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"))
    args = ap.parse_args()
    out = Path(args.out)
    work = out / "e2e_runs"
    res: dict = {}
    for pipeline in ("neoslam", "ratslam"):
        params = {"seed": 0}
        if args.frames:
            params["frames"] = args.frames
        cfg = load_config("default", {"run": {"pipeline": pipeline, "live": False},
                                      "source": {"kind": "synthetic", "params": params}})
        r = run(cfg, work / pipeline)
        ev = evaluate_run(work / pipeline)
        res[pipeline] = {"report": {k: r.report[k] for k in ("frames_in", "frames_out", "f_out", "loss",
                                                             "f_pipeline_predicted", "bottleneck")},
                         "tau_p50_ms": {s: v["tau_p50_ms"] for s, v in r.report["stages"].items()},
                         "evaluation": ev}
        res[f"{pipeline}_mean_m"] = ev["trajectory_ape"]["mean_m"]
        res[f"{pipeline}_max_m"] = ev["trajectory_ape"]["max_m"]
        if pipeline == "neoslam":
            res["odometry_mean_m"] = ev["odometry_ape"]["mean_m"]
            res["odometry_max_m"] = ev["odometry_ape"]["max_m"]
            res["frames"] = r.report["frames_out"]
            res["fps_lossless"] = r.report["f_out"]
            res["backbone"] = r.report["stages"]["A"]["info"].get("backbone")
            shutil.copy(work / pipeline / "map.png", out / "e2e_map.png")
        print(pipeline, res[f"{pipeline}_mean_m"], res[f"{pipeline}_max_m"], flush=True)
    (out / "e2e.json").write_text(json.dumps(res, indent=2))
    print(json.dumps({k: v for k, v in res.items() if not isinstance(v, dict)}, indent=2))


if __name__ == "__main__":
    main()
