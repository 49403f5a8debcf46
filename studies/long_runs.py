"""What bounds the default's growth on a route it knows, and what each bound costs -> studies/results/long_runs.json.

C's winner cells of a synthetic world's route (driven ``laps`` times over, the same images every
lap, so A's cached features of one route serve every lap; C keeps learning, so each lap's cells are
its own) are recorded once through the default's B and C; D and the back end are then replayed
in-process (``NeoSLAM.step_cells``) with each variant: the default, and the default without one of
the mechanisms of docs/long_runs.md (``experience_map.prune: false``; ``spatial_view.merge_revisits:
false``; both). Per lap: new templates, templates kept, D's intervals (made, stored, indexed),
experiences, links, loop closures, the map's solve time and each lap's frames on the final map
against ground truth (APE after SE(2) alignment); per run: ``neoslam evaluate``'s closure precision
/ recall and APE online / on the final map of the first route (worlds 0 and 2 held out, 1, 3, 4
validation).

Run: ``.venv/bin/python studies/long_runs.py [--worlds 1,3,4,0,2] [--laps 1] [--day-laps 8] [--out studies/results/long_runs.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import numpy as np
from bench_settings import cache_key

from neoslam_stream.config import load_config

CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_generalisation"))
VALIDATION, TEST = (1, 3, 4), (0, 2)


def cells_path(seed: int, laps: int) -> Path:
    cfg = load_config("default")
    sections = [cfg.features.model_dump(), cfg.projector.model_dump(), cfg.neocortex.model_dump()]
    return CACHE / f"long_runs_cells_w{seed}_{laps}_{cache_key(sections)}.pkl"


def record(seed: int, laps: int) -> dict[str, Any]:
    """C's cells of ``laps`` routes of world ``seed`` (B 8 frames a batch, as its node), cached."""
    path = cells_path(seed, laps)
    if path.is_file():
        return pickle.loads(path.read_bytes())
    from streams import synthetic_stream

    from neoslam_stream.algorithms.frontend import FrontEnd
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default", {"source": {"params": {"seed": seed}}})
    stream = synthetic_stream(seed, CACHE)
    feats = stream.features(cfg.features.photometric, cfg.features.input_size)
    route = feats.shape[0]
    fe = FrontEnd(cfg.front_end())
    cells, t0 = [], time.time()
    for k in range(0, laps * route, 8):
        idx = np.arange(k, min(k + 8, laps * route)) % route
        for code in fe.codes(feats[idx]):
            cells.append(fe.cells(code.bits))
        if k % 2000 < 8:
            print(f"world {seed}: C's cells of frame {k} of {laps * route} ({time.time() - t0:.0f} s)", flush=True)
    src = SyntheticWorldSource(seed=seed, width=8, height=8)
    rec = {"seed": seed, "route": route, "laps": laps, "cells": cells, "gt": src.gt.copy(),
           "odometry": src.odometry(laps * route), "rate_hz": src.rate_hz}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(rec))
    return rec


def state_bytes(state: dict[str, Any]) -> int:
    """A stage's state as `neoslam map export` packs it (msgpack, arrays as raw bytes)."""
    import msgpack

    from neoslam_stream.runtime.messages import _default

    return len(msgpack.packb(state, default=_default, use_bin_type=True))


def replay(rec: dict[str, Any], laps: int, overrides: dict[str, Any], run_dir: Path) -> dict[str, Any]:
    """D and the back end over ``laps`` routes of the recording, with ``overrides`` on the default;
    per lap the figures of the module docstring, per run ``neoslam evaluate``'s of the whole run."""
    from neoslam_stream.api import NeoSLAM
    from neoslam_stream.evaluation import evaluate_run
    from neoslam_stream.evaluation.poses import ape
    from neoslam_stream.tum import integrate_odometry, read_tum, write_tum

    route, dt = rec["route"], 1.0 / rec["rate_hz"]
    n = laps * route
    if len(rec["cells"]) < n:
        raise ValueError(f"the recording holds {len(rec['cells'])} frames, {n} needed")
    cfg = load_config("default", {"source": {"params": {"seed": rec["seed"]}}, **overrides})
    run_dir.mkdir(parents=True, exist_ok=True)
    slam = NeoSLAM(cfg, run_dir=run_dir)
    d, pc, em = slam.front_end.spatial_view, slam.back_end.pose_cells, slam.back_end.experience_map
    iterate, solve_s = em.iterate, [0.0]

    def timed() -> None:
        t0 = time.perf_counter()
        iterate()
        solve_s[0] += time.perf_counter() - t0

    em.iterate = timed
    odo = rec["odometry"][:n]
    rows, closures, t_lap, d_s = [], 0, time.perf_counter(), 0.0
    for i in range(n):
        t0 = time.perf_counter()
        r = slam.step_cells(rec["cells"][i], odometry=tuple(odo[i]), stamp=i * dt, frame=i)
        d_s += time.perf_counter() - t0
        closures += r.is_loop_closure
        if (i + 1) % route == 0:
            info = slam.info()
            rows.append({"lap": (i + 1) // route, "closures": int(closures), "templates_made": d.n_templates,
                         "merge": info["D"].get("revisit_merge"),
                         "intervals_made": d.n_intervals, "intervals_stored": info["D"]["intervals_stored"],
                         "indexed": len(d.indexed), "experiences": em.n_experiences, "links": em.n_links,
                         "pc_templates": len(pc.network.templates), "pc_experiences": info["pose_cells"]["experiences"],
                         "actions": dict(pc.actions), "solve_s": round(solve_s[0], 3),
                         "step_ms": round(1e3 * d_s / route, 3), "lap_s": round(time.perf_counter() - t_lap, 1),
                         "state_bytes": {"D": state_bytes(d.state_dict()), "pose_cells": state_bytes(pc.state_dict()),
                                         "experience_map": state_bytes(em.state_dict())}})
            print(json.dumps(rows[-1]), flush=True)
            closures, solve_s[0], d_s, t_lap = 0, 0.0, 0.0, time.perf_counter()
    slam.finish()
    gt = rec["gt"][np.arange(n) % route]
    stamps = np.arange(n) * dt
    write_tum(run_dir / "groundtruth.tum", np.column_stack([stamps, gt]))
    write_tum(run_dir / "odometry.tum", integrate_odometry(list(stamps), [tuple(o) for o in odo]))
    (run_dir / "report.json").write_text(json.dumps({"source": {"kind": "synthetic"}}))
    ev = evaluate_run(run_dir, radius=1.0, plot=False)
    on_map = read_tum(run_dir / "trajectory_map.tum")
    R_t = ape(on_map[:, 1:3], gt[:, :2])  # the whole run aligned once, then each lap's frames
    from neoslam_stream.evaluation.poses import umeyama_se2

    R, t = umeyama_se2(on_map[:, 1:3], gt[:, :2])
    err = np.linalg.norm(on_map[:, 1:3] @ R.T + t - gt[:, :2], axis=1)
    for k, row in enumerate(rows):
        row["ape_final_map_m"] = round(float(err[k * route:(k + 1) * route].mean()), 4)
    lc = ev["loop_closures"]
    return {"laps": rows, "ape_online_m": ev["trajectory_ape"]["mean_m"],
            "ape_final_map_m": ev.get("map_trajectory_ape", {}).get("mean_m"), "ape_final_map_whole_m": R_t["mean_m"],
            "closures": lc.get("closures"), "precision": lc.get("precision"), "recall": lc.get("recall"),
            "map_nodes": ev.get("map_nodes")}


#: the variants compared: the shipped default, and without each mechanism (the back end's sections
#: written out, since a section given in full replaces ``derived``)
def variants() -> dict[str, dict[str, Any]]:
    from neoslam_stream.algorithms.backend import derived_back_end

    em = derived_back_end(**load_config("default").platform.model_dump())["experience_map"]
    no_prune = {"experience_map": {**em, "prune_m": 0.0}}
    no_merge = {"spatial_view": {"merge_revisits": False}}
    return {"default": {}, "without_pruning": no_prune, "without_merge": no_merge,
            "without_either": {**no_prune, **no_merge}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", default="1,3,4,0,2")
    ap.add_argument("--day-laps", type=int, default=8, help="laps of world 0 for the per-lap figures (0: none)")
    ap.add_argument("--out", default=str(_paths.RESULTS / "long_runs.json"))
    ap.add_argument("--record", default="", help="only record: seed:laps,seed:laps")
    ap.add_argument("--replay", default="", help="seed:laps: replay the default (and --set) on it")
    ap.add_argument("--set", default="{}", help="JSON overrides of the default for --replay")
    args = ap.parse_args()
    if args.record or args.replay:
        for item in filter(None, args.record.split(",")):
            seed, laps = (int(v) for v in item.split(":"))
            print(f"world {seed}: {len(record(seed, laps)['cells'])} frames recorded", flush=True)
        if args.replay:
            seed, laps = (int(v) for v in args.replay.split(":"))
            have = [k for k in range(laps, 65) if cells_path(seed, k).is_file()]
            res = replay(record(seed, have[0] if have else laps), laps, json.loads(args.set),
                         CACHE / "long_runs" / f"w{seed}_{laps}")
            print(json.dumps({k: v for k, v in res.items() if k != "laps"}))
        return
    out: dict[str, Any] = {"validation": list(VALIDATION), "held_out": list(TEST), "routes": {}, "day": {}}
    for name, over in variants().items():
        for w in (int(v) for v in args.worlds.split(",")):
            res = replay(record(w, 1), 1, over, CACHE / "long_runs" / f"{name}_w{w}")
            lap = res.pop("laps")[0]
            res.update({k: lap[k] for k in ("experiences", "links", "templates_made", "indexed", "intervals_stored")})
            out["routes"].setdefault(name, {})[f"synthetic:{w}"] = res
            print(name, w, json.dumps(res), flush=True)
    if args.day_laps:
        have = [k for k in range(args.day_laps, 65) if cells_path(0, k).is_file()]
        rec = record(0, have[0] if have else args.day_laps)
        for name in ("default", "without_either"):
            out["day"][name] = replay(rec, args.day_laps, variants()[name], CACHE / "long_runs" / f"{name}_day")
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
