"""The back end of a finished day, replayed: its recorded templates and the route's odometry through
today's back end -> bench/results/day_back_end.json, .png.

NeoSLAM's front end never reads the back end (D's templates depend on the images only), so a day's
templates.csv together with the synthetic route's odometry (a pure function of its seed, the same
numbers the run received) is the back end's whole input: replayed through ``BackEnd`` with the
run's own back-end config it gives the run's trajectory.tum frame for frame (checked on the first
lap: ``reproduces_run``), and with another setting it gives what a day with that setting would
have given, in minutes instead of hours. ``--set pose_cells.odometry_bias.reference=first`` (for
example) changes one setting of the run's config; each ``--variant NAME:SETTING[,SETTING]`` adds a
replay, run side by side; ``--as-recorded`` names the settings the run's code had that its
config.yaml does not name (a field added since, at the value that code used).

Per lap, for each variant: the online APE (the map's pose of each frame as the lap was driven, the
lap aligned alone, as bench/day.py's ``ape_online_m``), the final-map APE (every frame of the lap
on the map at the end of the replay, one alignment of the whole replay, as day.py's
``ape_final_map_m``), the yaw-rate bias the estimator holds and the route's true one (the synthetic
odometry's bias and random walk at that frame), experiences, links and the map's solve time.
Targets as day.py's: each lap's APE, online and on the final map, within 10 % of lap 2's.
``--export`` also packs, per variant, the run's saved front-end states with the replayed pose cells
and map (bench/results/day_runs/back_end_<variant>.neoslam, outside git): the map file such a day
would have left, for ``neoslam run --map``; the variant replaying the run's own back end must end
with the pose cells the run saved (``reproduces_run_end``).

``--odometry-seed N`` replays the variants with the odometry noise of seed N instead of the run's
(the synthetic source's ``odom_seed``): the same templates and route, another draw of the bias's
random walk, a day to choose a setting on without touching the day it is reported on.

Run: ``.venv/bin/python bench/day_back_end.py --run bench/results/day_runs/day
--as-recorded pose_cells.odometry_bias.reference=first --variant
first:pose_cells.odometry_bias.reference=first --variant latest:pose_cells.odometry_bias.reference=latest``
(about ten minutes for 240 laps; ``--laps 20`` for a short check).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from day import APE_SLACK, lap_ape  # noqa: E402

from neoslam_stream.algorithms.backend import BackEnd, BackEndConfig  # noqa: E402
from neoslam_stream.algorithms.ratslam.map_poses import poses_on_map  # noqa: E402
from neoslam_stream.nodes.ratslam import ExperienceMapNode, PoseCellsNode  # noqa: E402
from neoslam_stream.runtime.checkpoint import export_map, load_state_file, save_state_file  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402
from neoslam_stream.tum import read_tum  # noqa: E402


def back_end_config(run_dir: Path, settings: list[str]) -> dict[str, Any]:
    """The run's pose_cells and experience_map sections, with ``settings`` (dotted.key=YAML value)."""
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    out = {"pose_cells": cfg["pose_cells"], "experience_map": cfg["experience_map"]}
    for s in settings:
        key, _, value = s.partition("=")
        *path, last = key.split(".")
        node = out
        for k in path:
            node = node[k]
        node[last] = yaml.safe_load(value)
    return out


def route_input(run_dir: Path, laps: int | None, odom_seed: int | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, float]:
    """Per frame: template id, (vtrans, vrot, dt), the true yaw-rate bias; the route's ground truth,
    its length in frames and its frame rate. ``odom_seed``: the odometry of another seed than the
    run's (the same templates: a day the front end saw alike, driven with other odometry noise)."""
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    if cfg["source"]["kind"] != "synthetic":
        raise SystemExit(f"{run_dir}: a synthetic route's run is needed (its odometry is recomputed), "
                         f"not {cfg['source']['kind']!r}")
    params = {**cfg["source"]["params"], "width": 8, "height": 8}
    src = SyntheticWorldSource(**params, **({"odom_seed": odom_seed} if odom_seed is not None else {}))
    route = src.route_len
    rows = None if laps is None else laps * route
    tpl = np.loadtxt(run_dir / "templates.csv", delimiter=",", skiprows=1, usecols=(0, 2), max_rows=rows,
                     dtype=np.int64)
    if not np.array_equal(tpl[:, 0], np.arange(len(tpl))):
        raise SystemExit(f"{run_dir}/templates.csv misses frames: a lossless run is needed")
    n = len(tpl)
    odo = src.odometry(n)
    true_bias = odo[:, 1] - _true_yaw_rate(src, n)
    return tpl[:, 1], odo, true_bias, src.gt, route, src.rate_hz


def _true_yaw_rate(src: SyntheticWorldSource, n: int) -> np.ndarray:
    """The route's true yaw rate at each of ``n`` frames (what the odometry's yaw rate would be
    without bias, walk and noise)."""
    gt = src.gt
    k = np.arange(n) % src.route_len
    dth = np.remainder(gt[k, 2] - gt[(k - 1) % src.route_len, 2] + np.pi, 2 * np.pi) - np.pi
    out = dth * src.rate_hz
    out[0] = 0.0
    return out


def replay(run_dir: str, settings: list[str], laps: int | None, states: bool = False,
           odom_seed: int | None = None) -> dict[str, Any]:
    """One variant over the day's input: per-lap rows, the per-frame online poses of lap 1 and,
    with ``states``, the pose-cell and experience-map nodes' states at the end (what the run's
    workers would have saved); ``odom_seed``: route_input's."""
    tpl, odo, true_bias, gt, route, rate_hz = route_input(Path(run_dir), laps, odom_seed)
    sections = back_end_config(Path(run_dir), settings)
    be = BackEnd(BackEndConfig(**sections))
    em, bias = be.experience_map, be.pose_cells.bias
    n = len(tpl)
    online = np.zeros((n, 2))
    first_lap = np.zeros((min(route, n), 3))
    local = np.zeros((n, 4))
    rows, t0, solve0 = [], time.perf_counter(), 0.0
    dt = 1.0 / rate_hz
    for i in range(n):
        p = be.step(int(tpl[i]), 0.0, *odo[i], stamp=i * dt)  # the source's stamps, to the bit
        online[i] = p.pose[:2]
        local[i] = (p.exp_id, *p.local)
        if i < route:
            first_lap[i] = p.pose
        if i % route == route - 1:
            rows.append({"lap": i // route + 1,
                         # the bias the odometry had over the lap (its mean), and the estimate at its end
                         "bias_true_rad_s": round(float(true_bias[i - route + 1:i + 1].mean()), 5),
                         "bias_estimate_rad_s": round(bias.bias, 5),
                         "experiences": em.n_experiences, "links": em.n_links,
                         "solve_s": round(em.solve_s_total - solve0, 3),
                         "wall_s": round(time.perf_counter() - t0, 1)})
            solve0 = em.solve_s_total
            print(run_dir, settings, json.dumps(rows[-1]), flush=True)
    on_map = poses_on_map(em.node_poses(), local[:, 0].astype(np.int64), local[:, 1:])[:, :2]
    ref, lap = gt[np.arange(n) % route, :2], np.arange(n) // route
    # as day.py reads a run: each lap aligned alone online, one alignment of the whole on the final map
    for r, on, fin in zip(rows, lap_ape(online, ref, lap, True), lap_ape(on_map, ref, lap, False), strict=False):
        r["ape_online_m"], r["ape_final_map_m"] = on, fin
    out = {"settings": settings, "laps": rows, "first_lap_poses": first_lap, "frames": n}
    if states:
        pc = PoseCellsNode(**sections["pose_cells"])
        pc.stage = be.pose_cells
        pc.last_template_frame = pc.max_odom_frame = pc.last_odom_frame = n - 1
        emn = ExperienceMapNode(**sections["experience_map"])
        emn.em, emn.last_frame, emn.last_stamp = em, n - 1, (n - 1) * dt
        out["states"] = {"pose_cells": pc.state_dict(), "experience_map": emn.state_dict()}
    return out


def export_with(run_dir: Path, states: dict[str, dict[str, Any]], frames: int, out: Path) -> None:
    """``neoslam map export`` of the run's saved front-end states with the replayed back end's
    ``states``: the file the run would have exported with that back end (its front end is the
    same). Packed from a run folder of its own beside ``out``."""
    folder = out.with_suffix("")
    shutil.rmtree(folder, ignore_errors=True)
    (folder / "state").mkdir(parents=True)
    for f in (run_dir / "state").glob("*.state"):
        if f.stem not in states:
            shutil.copy2(f, folder / "state" / f.name)
    for name, st in states.items():
        save_state_file(folder / "state" / f"{name}.state", st)
    shutil.copy2(run_dir / "config.yaml", folder / "config.yaml")
    (folder / "report.json").write_text(json.dumps({"pipeline": "neoslam", "frames_out": frames}))
    export_map(folder, out)
    shutil.rmtree(folder)


def _same(a: Any, b: Any) -> bool:
    """The state ``b`` holds every value the saved state ``a`` holds (arrays compared exactly); keys
    ``b`` has beyond ``a``'s are state added to the code since the run saved ``a``."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() <= b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    return a == b


def targets(laps: list[dict[str, Any]]) -> dict[str, Any]:
    if len(laps) < 3:
        return {"reached": None, "why": "fewer than three laps"}
    out: dict[str, Any] = {"ape_slack": APE_SLACK}
    for key in ("ape_online_m", "ape_final_map_m"):
        out[f"{key}_worst_vs_lap2"] = round(max(r[key] for r in laps[2:]) / laps[1][key], 4)
    out["reached"] = {k: out[f"{k}_m_worst_vs_lap2"] <= 1 + APE_SLACK for k in ("ape_online", "ape_final_map")}
    return out


def plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.5))
    for name, v in res["variants"].items():
        k = [r["lap"] for r in v["laps"]]
        ax[0].plot(k, [r["ape_online_m"] for r in v["laps"]], ".-", ms=3, label=f"{name}: online")
        ax[0].plot(k, [r["ape_final_map_m"] for r in v["laps"]], "--", label=f"{name}: final map")
        ax[1].plot(k, [r["bias_estimate_rad_s"] for r in v["laps"]], ".-", ms=3, label=f"{name}: estimate")
        ax[2].plot(k, [r["links"] for r in v["laps"]], ".-", ms=3, label=f"{name}: links")
        ax[2].plot(k, [r["experiences"] for r in v["laps"]], "--", label=f"{name}: experiences")
    first = next(iter(res["variants"].values()))["laps"]
    ax[1].plot([r["lap"] for r in first], [r["bias_true_rad_s"] for r in first], "k-", lw=1, label="true (the lap's mean)")
    ax[0].set(title="APE of each lap's frames (m)", xlabel="lap", yscale="log")
    ax[1].set(title="Yaw-rate bias (rad/s)", xlabel="lap")
    ax[2].set(title="The map", xlabel="lap")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.suptitle(f"The back end replayed on {res['run']}: {res['frames']} frames, {res['laps']} laps")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=str(Path(__file__).parent / "results" / "day_runs" / "day"),
                    help="a finished lossless run of the synthetic route (bench/day.py's)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE[,KEY=VALUE]",
                    help="a replay with these settings of the run's config (repeatable; none: the run's own)")
    ap.add_argument("--as-recorded", action="append", default=[], metavar="KEY=VALUE",
                    help="settings the run's code had without its config.yaml naming them (a field added "
                         "since): the replay of its own config, which must give its trajectory.tum, uses them")
    ap.add_argument("--laps", type=int, help="the first N laps only")
    ap.add_argument("--odometry-seed", type=int,
                    help="replay the variants with the odometry of this seed instead of the run's (the "
                         "same templates, other odometry noise: days to choose a setting on)")
    ap.add_argument("--export", action="store_true",
                    help="also write bench/results/day_runs/back_end_<variant>.neoslam (outside git): the run's "
                         "front-end states with the variant's back end")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "day_back_end.json"))
    args = ap.parse_args()
    if args.export and (args.laps is not None or args.odometry_seed is not None):
        ap.error("--export packs the run's end: the whole run's back end with its own odometry is needed "
                 "(leave out --laps and --odometry-seed)")
    run_dir = Path(args.run)
    variants = {}
    for v in args.variant:
        name, _, settings = v.partition(":")
        variants[name] = [s for s in settings.split(",") if s]
    with ProcessPoolExecutor(max_workers=max(1, len(variants))) as pool:
        futures = {name: pool.submit(replay, str(run_dir), s, args.laps, args.export, args.odometry_seed) for name, s in variants.items()}
        own = replay(str(run_dir), args.as_recorded, 1)["first_lap_poses"]  # one lap, beside the others
        done = {name: f.result() for name, f in futures.items()}
    recorded = read_tum(run_dir / "trajectory.tum")
    m = min(len(own), len(recorded))
    res: dict[str, Any] = {
        "run": str(run_dir), "as_recorded": args.as_recorded, "odometry_seed": args.odometry_seed,
        "laps": len(next(iter(done.values()))["laps"]) if done else 0, "frames": 0,
        # the run's own config replayed gives its recorded online poses (trajectory.tum) on lap 1
        "reproduces_run": bool(np.allclose(own[:m, :2], recorded[:m, 1:3], atol=1e-6)),
        "variants": {}}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for name, v in done.items():
        res["variants"][name] = {"settings": v["settings"], "targets": targets(v["laps"]), "laps": v["laps"]}
        res["frames"] = v["frames"]
        if "states" in v:
            path = out.parent / "day_runs" / f"back_end_{name}.neoslam"  # beside day.py's exports, outside git
            export_with(run_dir, v["states"], res["frames"], path)
            res["variants"][name]["export"] = str(path)
            # the run's own back end, replayed whole: its pose cells end as the run's saved ones
            if v["settings"] == args.as_recorded and (run_dir / "state" / "pose_cells.state").exists() \
                    and args.laps is None:
                saved = load_state_file(run_dir / "state" / "pose_cells.state")
                res["reproduces_run_end"] = _same(saved, v["states"]["pose_cells"])
    out.write_text(json.dumps(res, indent=1))
    plot(res, out.with_suffix(".png"))
    print(json.dumps({"reproduces_run": res["reproduces_run"], "reproduces_run_end": res.get("reproduces_run_end"),
                      **{n: v["targets"] for n, v in res["variants"].items()}}, indent=1))


if __name__ == "__main__":
    main()
