"""The experience map's relaxation: OpenRatSLAM's sweeps per action against the least-squares solve
-> bench/results/relaxation.json.

The pose cells never read the map, so one run of the default per synthetic world gives the map's
whole input (every odometry step and pose-cell action, and each frame's ground truth); that stream
is replayed through an ExperienceMap with each relaxation: ``exp_loops`` 20 ... 1000 sweeps per
action, and ``relaxation: least_squares``. Figures: APE of the per-frame pose (online) and of every
frame on the final map, after the same SE(2) alignment as ``neoslam evaluate``, and the seconds the
map took. The TUC corridor (bench/tuc_corridor.py, the default's back end) runs its two halves
alone. Chosen on the validation parts (synthetic worlds 1, 3, 4; the TUC run's first half),
reported on the held-out ones (worlds 0 and 2; the second half): docs/mapping.md.

Run: ``.venv/bin/python bench/relaxation.py [--worlds 1,3,4,0,2] [--out bench/results/relaxation.json] [--table]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap, poses_on_map  # noqa: E402
from neoslam_stream.evaluation import ape  # noqa: E402

SWEEPS = (20, 50, 100, 200, 300, 500, 1000)
VALIDATION, TEST = ("synthetic:1", "synthetic:3", "synthetic:4", "tuc:first"), ("synthetic:0", "synthetic:2", "tuc:second")


def map_input(seed: int) -> dict[str, Any]:
    """The default on synthetic world ``seed`` in-process, recording what its map is given."""
    from neoslam_stream.api import NeoSLAM
    from neoslam_stream.config import load_config
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default", {"source": {"params": {"seed": seed}}})
    slam = NeoSLAM(cfg)
    em = slam.back_end.experience_map
    calls: list[tuple] = []
    on_odo, on_action = em.on_odo, em.on_action
    em.on_odo = lambda *a: (calls.append(("odo", a)), on_odo(*a))[1]
    em.on_action = lambda *a: (calls.append(("act", a)), on_action(*a))[1]
    gt = []
    for f in SyntheticWorldSource(**cfg.source.params):
        slam.step(f.image, odometry=f.odom, stamp=f.stamp, frame=f.frame)
        calls.append(("frame", ()))
        gt.append(f.groundtruth[:2])
    return {"calls": calls, "gt": np.array(gt), "config": cfg.experience_map.model_dump()}


def replay(inp: dict[str, Any], map_cls: type = ExperienceMap, **relaxation: Any) -> dict[str, float]:
    """The recorded map input through a fresh map (``map_cls``, with ``relaxation``'s settings)."""
    em = map_cls(**{**inp["config"], **relaxation})
    poses, local = [], []
    t0 = time.perf_counter()
    for kind, args in inp["calls"]:
        if kind == "odo":
            em.on_odo(*args)
        elif kind == "act":
            em.on_action(*args)
        else:
            poses.append(em.robot_pose()[:2])
            local.append(em.local_pose())
    secs = time.perf_counter() - t0
    loc = np.array(local)
    on_map = poses_on_map(em.node_poses(), loc[:, 0].astype(np.int64), loc[:, 1:])[:, :2]
    return {"online_m": ape(np.array(poses), inp["gt"])["mean_m"], "final_map_m": ape(on_map, inp["gt"])["mean_m"],
            "map_seconds": secs, "experiences": em.n_experiences, "links": em.n_links}


def variants() -> list[tuple[str, dict[str, Any]]]:
    return [(f"sweeps_{k}", {"relaxation": "sweeps", "exp_loops": k}) for k in SWEEPS] + \
        [("least_squares", {"relaxation": "least_squares"})]


def tuc_halves() -> dict[str, dict[str, Any]]:
    from bench_settings import back_end_sections
    from tuc_corridor import run_half

    pose_cells, em = back_end_sections("tuc")
    out: dict[str, dict[str, Any]] = {}
    for part in ("tuc:first", "tuc:second"):
        out[part] = {}
        for name, over in variants():
            t0 = time.perf_counter()
            r = run_half(part.split(":")[1], pose_cells, {**em, **over})
            out[part][name] = {"online_m": r["map_mean_m"], "final_map_m": r["map_on_final_mean_m"],
                               "odometry_m": r["odometry_mean_m"], "run_seconds": time.perf_counter() - t0,
                               "experiences": r["experiences"], "links": r["links"]}
            print(part, name, json.dumps(out[part][name]), flush=True)
    return out


def table(res: dict[str, Any]) -> str:
    """docs/mapping.md's table: online / final-map error and the map's seconds per part."""
    cols = ("sweeps_20", "sweeps_300", "sweeps_1000", "least_squares")
    lines = ["| part | | 20 sweeps | 300 sweeps | 1000 sweeps | least squares |", "|---|---|---|---|---|---|"]
    for role in ("validation", "test"):
        for part in res[role]:
            rows = res["parts"][part]
            secs = "map_seconds" if part.startswith("synthetic") else "run_seconds"
            cells = [f"{rows[c]['online_m']:.2f} / {rows[c]['final_map_m']:.2f} m, {rows[c][secs]:.2f} s" for c in cols]
            label = part.replace("synthetic:", "synthetic world ").replace("tuc:", "TUC run, ") + " half" * part.startswith("tuc")
            lines.append(f"| {label} | {role} | {' | '.join(cells)} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", default="1,3,4,0,2", help="synthetic worlds (seeds), comma-separated")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "relaxation.json"))
    ap.add_argument("--table", action="store_true", help="print docs/mapping.md's table from --out and stop")
    args = ap.parse_args()
    if args.table:
        print(table(json.loads(Path(args.out).read_text())))
        return
    parts: dict[str, dict[str, Any]] = {}
    for seed in (int(s) for s in args.worlds.split(",") if s):
        print(f"synthetic world {seed}: running the default ...", flush=True)
        inp = map_input(seed)
        parts[f"synthetic:{seed}"] = {}
        for name, over in variants():
            parts[f"synthetic:{seed}"][name] = r = replay(inp, **over)
            print(f"synthetic:{seed}", name, json.dumps(r), flush=True)
    parts.update(tuc_halves())
    res = {"validation": [p for p in VALIDATION if p in parts], "test": [p for p in TEST if p in parts],
           "parts": parts}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
