"""The experience map's relaxation: OpenRatSLAM's sweeps per action, the least-squares solve and the
pose graph with a wandering bias (``bias_walk`` on a grid of its two constants), chosen by a rule
-> studies/results/relaxation.json.

The pose cells never read the map, so one run of the default per synthetic world gives the map's
whole input (every odometry step and pose-cell action with the bias's measured wander, and each
frame's ground truth); that stream is replayed through an ExperienceMap with each relaxation:
``exp_loops`` 20 ... 1000 sweeps per action, ``relaxation: least_squares``, and ``bias_walk`` at
every point of WALK_POSITION_REL x WALK_HEADING_VAR. Figures: APE of the per-frame pose (online)
and of every frame on the final map, after the same SE(2) alignment as ``neoslam evaluate``, and
the seconds the map took. The TUC corridor (bench/tuc_corridor.py, the default's back end) runs
its two halves alone. Chosen by :func:`choose` on the validation parts (synthetic worlds 1, 3, 4;
the TUC run's first half), reported on the held-out ones (worlds 0 and 2; the second half):
docs/mapping.md.

Run: ``.venv/bin/python studies/relaxation.py [--worlds 1,3,4,0,2] [--out studies/results/relaxation.json] [--table]``;
``--scale`` times one solve of each on larger maps (-> studies/results/relaxation_scale.json).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import numpy as np

from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.map_poses import poses_on_map
from neoslam_stream.evaluation import ape

SWEEPS = (20, 50, 100, 200, 300, 500, 1000)
#: bias_walk's grid: a link's position sd per metre of it, its heading variance per second (rad^2/s)
WALK_POSITION_REL = (0.015, 0.05, 0.15, 0.5, 1.5)
WALK_HEADING_VAR = (2e-5, 2e-4, 2e-3, 2e-2)
#: the rule: online error within this factor of the incumbent's (the relaxation shipped before the
#: run) on every validation part
ONLINE_SLACK = 1.05
INCUMBENT = "least_squares"
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

    def record_action(*a: Any) -> None:
        # the bias's wander as integrate() set it before the action (the map's bias_walk reads it)
        calls.append(("wander", (em.bias_wander,)))
        calls.append(("act", a))
        on_action(*a)

    em.on_action = record_action
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
        elif kind == "wander":
            em.bias_wander = args[0]
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
        [("least_squares", {"relaxation": "least_squares"})] + \
        [(f"bias_walk_{rho:g}_{var:g}", {"relaxation": "bias_walk", "walk_position_rel": rho, "walk_heading_var": var})
         for rho in WALK_POSITION_REL for var in WALK_HEADING_VAR]


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


def choose(res: dict[str, Any]) -> dict[str, Any]:
    """The rule (docs/mapping.md): among the relaxations whose online error is within ONLINE_SLACK
    of the incumbent's on every validation part, the lowest mean final-map error over those parts.
    Also what the rule's first wording (within ONLINE_SLACK of the best candidate's online error
    on every part) leaves eligible."""
    parts = [res["parts"][p] for p in res["validation"]]
    names = list(parts[0])
    mean = {n: float(np.mean([rows[n]["final_map_m"] for rows in parts])) for n in names}

    def eligible(ref: list[float]) -> list[str]:
        return [n for n in names if all(rows[n]["online_m"] <= ONLINE_SLACK * r for rows, r in zip(parts, ref, strict=True))]

    by_incumbent = eligible([rows[INCUMBENT]["online_m"] for rows in parts])
    by_best = eligible([min(rows[n]["online_m"] for n in names) for rows in parts])
    return {"chosen": min(by_incumbent, key=mean.__getitem__), "incumbent": INCUMBENT, "eligible": by_incumbent,
            "eligible_within_best_online": by_best, "mean_final_map_m": mean}


def table(res: dict[str, Any]) -> str:
    """studies/mapping_choices.md's table: online / final-map error and the map's seconds per part."""
    chosen = res["rule"]["chosen"]
    cols = ("sweeps_20", "sweeps_300", "sweeps_1000", "least_squares", chosen)
    lines = [f"| part | | 20 sweeps | 300 sweeps | 1000 sweeps | least squares | {chosen} (chosen) |",
             "|---|---|---|---|---|---|---|"]
    for role in ("validation", "test"):
        for part in res[role]:
            rows = res["parts"][part]
            secs = "map_seconds" if part.startswith("synthetic") else "run_seconds"
            cells = [f"{rows[c]['online_m']:.2f} / {rows[c]['final_map_m']:.2f} m, {rows[c][secs]:.2f} s" for c in cols]
            label = part.replace("synthetic:", "synthetic world ").replace("tuc:", "TUC run, ") + " half" * part.startswith("tuc")
            lines.append(f"| {label} | {role} | {' | '.join(cells)} |")
    return "\n".join(lines)


def solve_cost(sizes: tuple[int, ...] = (1000, 5000, 20000)) -> list[dict[str, Any]]:
    """Seconds of one solve of each relaxation on a map of n experiences: a route around a 40-m
    loop, lap after lap, an experience every 0.1 m and 0.2 s, each link off by 1 cm and 0.01 rad
    (seeded), and every 50th experience after the first lap linked back onto it."""
    from neoslam_stream.algorithms.ratslam.graph_solve import relax_least_squares
    from neoslam_stream.algorithms.ratslam.pose_graph import bias_walk_weights, relax_pose_graph

    cfg, rng, rows = ExperienceMap().config, np.random.default_rng(0), []
    for n in sizes:
        ang = np.arange(n) * 0.1 / 40 * 2 * np.pi
        x, y, th = 6.4 * np.cos(ang), 6.4 * np.sin(ang), ang + np.pi / 2
        back = np.arange(400, n, 50)
        lf, lt = np.r_[np.arange(n - 1), back], np.r_[np.arange(1, n), back % 400]
        m = lf.shape[0]
        ld = np.r_[np.full(n - 1, 0.1), np.full(m - n + 1, 0.01)] + rng.normal(0, 0.01, m)
        lh = rng.normal(0, 0.01, m)
        lface = np.r_[np.full(n - 1, 2 * np.pi * 0.1 / 40), np.zeros(m - n + 1)] + rng.normal(0, 0.01, m)
        ldt = np.full(m, 0.2)
        t0 = time.perf_counter()
        relax_least_squares(x, y, th, lf, lt, ld, lh, lface)
        t1 = time.perf_counter()
        w = bias_walk_weights(ld, ldt, cfg.walk_position_rel, cfg.walk_heading_var, 1e-6)
        info = relax_pose_graph(x, y, th, lf, lt, ld, lh, lface, ldt, w[0], w[1], np.arange(m), w[2])[3]
        rows.append({"experiences": n, "links": m, "least_squares_s": t1 - t0,
                     "bias_walk_s": time.perf_counter() - t1, "bias_walk_steps": info["steps"]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", default="1,3,4,0,2", help="synthetic worlds (seeds), comma-separated")
    ap.add_argument("--out", default=str(_paths.RESULTS / "relaxation.json"))
    ap.add_argument("--table", action="store_true", help="print studies/mapping_choices.md's table from --out and stop")
    ap.add_argument("--scale", action="store_true",
                    help="only time one solve of each on maps of 1000-20000 experiences -> relaxation_scale.json")
    args = ap.parse_args()
    if args.table:
        print(table(json.loads(Path(args.out).read_text())))
        return
    if args.scale:
        out = Path(args.out).with_name("relaxation_scale.json")
        out.write_text(json.dumps({"solves": solve_cost(), "cores": "one"}, indent=1))
        print(f"wrote {out}")
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
    res["rule"] = choose(res)
    print("the rule chooses", res["rule"]["chosen"], flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
