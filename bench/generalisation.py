"""One shipped default on every data set, its constants chosen on other parts of the data.

Each data set runs the single default (configs/default.yaml, with only the data set's physical
quantities under ``platform``), the paper profile (configs/paper.yaml) and RatSLAM's local view
with the default's calibrated decision, side by side. The calibrated decision's constants (z_min,
rho) are chosen on validation parts by ``CHOICE_RULE`` at each of A's input sizes and the size by
``INPUT_RULE``, A's light setting (``features.photometric``) by ``LIGHT_RULE``, and all are
reported on held-out parts; the validation and test parts are
disjoint (``PARTS``). Front-end figures: loop-closure precision and recall through the real
A -> B -> C -> D (docs/mapping.md defines them per data set); the synthetic route also runs the
back end (trajectory errors), and the TUC corridor the back end alone. Writes
bench/results/generalisation.json; ``--table`` prints the README's table.
Run: ``.venv/bin/python bench/generalisation.py [--only input,light,choice,nordland,synthetic,proxies,gardens,tuc,route,route2]
[--jobs N] [--table]``; ``input`` runs the calibrated decision's grid at every input size and so
includes ``choice``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_settings import load_settings  # noqa: E402
from streams import MissingData, Stream, nordland_stream, proxy_stream, synthetic_stream, traversals_stream  # noqa: E402

from neoslam_stream.algorithms.frontend import FrontEnd, LocalViewFrontEnd  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_generalisation"))

#: which part of each data set chooses the constants and which reports; every kind reported has
#: validation parts of its own, the stand-ins under other light ("hard") in worlds 9-11, which no
#: other part uses; Gardens Point Walking (gardens:PAIR:HALF, bench/settings/gardens.yaml): the
#: first half of each pair of walks validates, the second half is held out (a part whose data is
#: absent is left out with its reason)
PARTS = {"validation": ["nordland:2", "nordland:4", "nordland:6", "synthetic:1", "synthetic:3", "synthetic:4",
                        "sparse:1", "sparse:2", "hard:9", "hard:10", "hard:11",
                        "gardens:hard:a", "gardens:night:a", "gardens:view:a"],
         "test": ["nordland:0", "synthetic:0", "synthetic:2", "sparse:0", "sparse:3", "sparse:4", "sparse:5",
                  "hard:0", "hard:1", "hard:2", "hard:3", "gardens:hard:b", "gardens:night:b", "gardens:view:b"]}
#: the validation parts that choose the decision's constants (z_min, rho), A's light setting and its
#: input size: all but Gardens Point's. There no grid point of the decision reaches the bar (a lateral
#: shift of the view closes wrong places, precision 0.80-0.83 at z_min 3.5), and z_min 4.0, the one
#: point that reaches every bar with them, costs Nordland a quarter of its recall; Gardens Point's
#: parts validate the chain's representations instead (bench/stages.py: B's descriptors and D's
#: re-ranking, docs/mapping.md) and report what the decision keeps of them
DECISION_PARTS = [p for p in PARTS["validation"] if not p.startswith("gardens")]
GRID = {"z_min": [3.0, 3.5, 4.0, 4.5], "rho": [0.7, 0.9, 1.0, 1.1, 1.2, 1.3]}
#: precision each kind of validation part must reach, with a margin over the targets (Nordland's
#: 0.9, the synthetic world's 0.99, the stand-ins' 0.9 with or without other light); among the grid
#: points that reach every one, the highest mean recall over the validation parts wins (up to TIE)
BARS = {"nordland": 0.93, "synthetic": 0.99, "sparse": 0.95, "hard": 0.95, "gardens": 0.95}
#: grid points whose mean recall is within this of the best feasible one are ties, and a tie goes to
#: the larger z_min, then the larger rho: the more conservative decision, whose precision keeps room
#: over the bars (at z_min 3 Nordland's subset 4 sits at 0.933 against its 0.93)
TIE = 0.005
CHOICE_RULE = ("highest mean recall over the validation parts among the grid points whose precision reaches "
               f"{BARS} on every validation part; points within {TIE} of it are ties, won by the larger z_min, "
               "then the larger rho")


def default_config(platform: dict[str, Any] | None = None, **calibration: Any) -> Any:
    over: dict[str, Any] = {"platform": platform or {}}
    if calibration:
        over["spatial_view"] = {"calibration": calibration}
        over["local_view"] = {"calibration": calibration}
    return load_config("default", over)


# ------------------------------------------------------------------------------ front ends
def neoslam_templates(stream: Stream, cfg: Any, cells: list[Any] | None = None) -> tuple[list[dict], Any]:
    """D's output per frame (C's result through ``cfg``'s B and C unless given: its cells and B's
    descriptor), and the FrontEnd."""
    fe = FrontEnd(cfg.front_end())
    if cells is None:
        cells = stream.sdrs(fe)
    out = [fe.template_of(c, s) for c, s in zip(cells, stream.stamps, strict=True)]
    return out, fe


def matched_frames(out: list[dict], starts: list[int] | None) -> list[tuple[int, int]]:
    """(frame, matched frame) of every closure: the first frame of D's matched interval, or (local
    view) the frame that created the matched template."""
    first: dict[int, int] = {}
    pairs = []
    for t, o in enumerate(out):
        first.setdefault(int(o["id"]), t)
        if o["is_loop_closure"]:
            pairs.append((t, starts[o["best_interval"]] if starts is not None else first[int(o["id"])]))
    return pairs


def frontend_figures(stream: Stream, cfg: Any, cells: list[Any] | None = None) -> dict[str, Any]:
    out, fe = neoslam_templates(stream, cfg, cells)
    res = stream.score(matched_frames(out, fe.spatial_view.interval_start))
    if cfg.spatial_view.calibration.enabled:
        res["calibration"] = fe.spatial_view.calibration.report()
    return res


def ratslam_figures(stream: Stream, cfg: Any) -> dict[str, Any]:
    lv = LocalViewFrontEnd(cfg.local_view, cfg.platform)
    out = [lv.template(img, s) for img, s in zip(stream.pixels(), stream.stamps, strict=True)]
    res = stream.score(matched_frames(out, None))
    if cfg.local_view.calibration.enabled:
        res["calibration"] = lv.calibration.report()
    return res


def part_stream(part: str) -> Stream:
    """The stream of a part name (``PARTS``); :class:`MissingData` when its data is absent."""
    kind, index = part.split(":", 1)
    if kind == "gardens":
        return traversals_stream("gardens", *index.split(":"), CACHE)
    if kind == "nordland":
        return nordland_stream(int(index), CACHE)
    if kind == "synthetic":
        return synthetic_stream(int(index), CACHE)
    return proxy_stream(int(index), CACHE, hard=kind == "hard")


def present(parts: list[str]) -> list[str]:
    """``parts`` less those whose data is absent, each left out with its reason."""
    out = []
    for part in parts:
        try:
            part_stream(part)
        except MissingData as exc:
            print(f"{part}: skipped: {exc}", flush=True)
        else:
            out.append(part)
    return out


# ------------------------------------------------------------------------------ choice and report
def _judge(row: dict[str, Any], parts: list[str]) -> None:
    """A candidate's verdict on the validation parts: whether its precision reaches BARS on every
    one (``reaches_bars``) and its mean recall over them (``mean_recall``)."""
    row["reaches_bars"] = all((row[p]["precision"] or 0) >= BARS[p.split(":")[0]] for p in parts)
    row["mean_recall"] = float(np.mean([row[p]["recall"] for p in parts]))


def choose(valid: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The grid on the validation parts (the default's cells, D once per grid point) and the
    point ``CHOICE_RULE`` picks."""
    grid = []
    for z, rho in itertools.product(GRID["z_min"], GRID["rho"]):
        row: dict[str, Any] = {"z_min": z, "rho": rho}
        for part, (stream, cells) in valid.items():
            row[part] = frontend_figures(stream, default_config(stream.platform, enabled=True, z_min=z, rho=rho),
                                         cells)
            row[part].pop("calibration", None)
        _judge(row, list(valid))
        grid.append(row)
        print("grid", z, rho, row["reaches_bars"], round(row["mean_recall"], 3), flush=True)
    feasible = [g for g in grid if g["reaches_bars"]]
    best = None
    if feasible:
        top = max(g["mean_recall"] for g in feasible)
        best = max((g for g in feasible if g["mean_recall"] >= top - TIE), key=lambda g: (g["z_min"], g["rho"]))
    shipped = default_config().spatial_view.calibration
    choice = None if best is None else {"z_min": best["z_min"], "rho": best["rho"]}
    return {"rule": CHOICE_RULE, "grid": grid, "choice": choice,
            "choice_is_the_default": choice == {"z_min": shipped.z_min, "rho": shipped.rho}}


#: A's input under each light setting (features.photometric); chosen by LIGHT_RULE on the validation
#: parts at the calibrated decision as shipped
LIGHT = ["none", "log_standardise"]
LIGHT_RULE = ("highest mean recall over the validation parts among the settings whose precision reaches "
              f"{BARS} on every validation part")


def choose_light(parts: list[str]) -> dict[str, Any]:
    """Each photometric setting of A's input through the default front end (its calibrated decision
    as shipped) on the validation parts, and the setting ``LIGHT_RULE`` picks."""
    rows = []
    streams = {part: part_stream(part) for part in parts}
    for light in LIGHT:
        row: dict[str, Any] = {"photometric": light}
        for part, stream in streams.items():
            cfg = load_config("default", {"platform": stream.platform, "features": {"photometric": light}})
            row[part] = frontend_figures(stream, cfg)
            row[part].pop("calibration", None)
        _judge(row, parts)
        rows.append(row)
        print("light", light, row["reaches_bars"], round(row["mean_recall"], 3), flush=True)
    feasible = [r for r in rows if r["reaches_bars"]]
    best = max(feasible, key=lambda r: r["mean_recall"])["photometric"] if feasible else None
    return {"rule": LIGHT_RULE, "rows": rows, "choice": best,
            "choice_is_the_default": best == load_config("default").features.photometric}


#: sides of the square A sees (features.input_size), the reference's 224 first; chosen with the
#: calibrated decision by INPUT_RULE on the validation parts, with the light setting as shipped
INPUT_SIZES = [224, 192, 160, 128]
INPUT_RULE = ("at each input size the grid point CHOICE_RULE picks; the smallest size whose pick's mean "
              f"recall over the validation parts is at least the 224 pick's less {TIE}; its pick is the decision")


def _grid_at(size: int, parts: list[str]) -> dict[str, Any]:
    """CHOICE_RULE's grid on the validation parts with A's input at ``size``."""
    valid = {}
    for part in parts:
        stream = part_stream(part)
        cfg = load_config("default", {"platform": stream.platform, "features": {"input_size": size}})
        valid[part] = (stream, stream.sdrs(FrontEnd(cfg.front_end())))
    print("input", size, flush=True)
    return choose(valid)


def choose_input(parts: list[str], jobs: int = 1) -> dict[str, Any]:
    """The grid of the calibrated decision at each input size of A, and the size and decision
    ``INPUT_RULE`` picks: A's cost falls with the square of the side, and the smallest side whose
    best decision keeps what the front end recognises at the reference's 224 wins. One choice over
    both, so that neither depends on which was chosen first."""
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs) as pool:
        grids = list(pool.map(_grid_at, INPUT_SIZES, [parts] * len(INPUT_SIZES)))
    rows = []
    for size, grid in zip(INPUT_SIZES, grids, strict=True):
        pick = grid["choice"]
        point = None if pick is None else next(g for g in grid["grid"]
                                               if (g["z_min"], g["rho"]) == (pick["z_min"], pick["rho"]))
        rows.append({"input_size": size, "pick": pick, "mean_recall": None if point is None else point["mean_recall"],
                     "grid": grid})
        print("input", size, pick, None if point is None else round(point["mean_recall"], 4), flush=True)
    floor = None if rows[0]["mean_recall"] is None else rows[0]["mean_recall"] - TIE
    keep = [r for r in rows if r["mean_recall"] is not None and floor is not None and r["mean_recall"] >= floor]
    best = min(keep, key=lambda r: r["input_size"]) if keep else None
    shipped = default_config()
    choice = None if best is None else best["input_size"]
    return {"rule": INPUT_RULE, "rows": [{k: v for k, v in r.items() if k != "grid"} for r in rows],
            "choice": choice, "choice_is_the_default": choice == shipped.features.input_size,
            "grids": {r["input_size"]: r["grid"] for r in rows}}


def frontends(parts: list[str]) -> dict[str, Any]:
    """The three front ends on each held-out part."""
    out = {}
    for part in parts:
        stream = part_stream(part)
        cfg = default_config(stream.platform)
        paper = load_config("paper", {"platform": stream.platform})
        out[part] = {"default": frontend_figures(stream, cfg), "paper": frontend_figures(stream, paper),
                     "ratslam": ratslam_figures(stream, cfg), "frames": len(stream.stamps),
                     "platform": stream.platform}
        print(part, json.dumps({k: v for k, v in out[part].items() if k in ("default", "paper", "ratslam")},
                               default=str)[:400], flush=True)
    return out


def tuc() -> dict[str, Any]:
    """The corridor with the default's back end (its platform under tuc.yaml's protocol) and with
    the paper's settings (tuc_paper.yaml): the whole run, and its second half run alone
    (``*_second_half``), the held-out part: the back end's constants were chosen on the first half."""
    from bench_settings import back_end_sections
    from tuc_corridor import halfway_s, run

    half = halfway_s()
    res = {}
    for name in ("default", "paper"):
        settings = "tuc" if name == "default" else "tuc_paper"
        proto = load_settings(settings)["protocol"]
        for key, start in ((name, None), (f"{name}_second_half", half)):
            r = run(*back_end_sections(settings), proto["threshold"], proto["min_gap_s"], start_s=start)
            res[key] = {k: v for k, v in r.items() if not hasattr(v, "shape")}
            res[key]["map_vs_odometry"] = r["map_mean_m"] / r["odometry_mean_m"]
            res[key]["from_s"] = start
            print("tuc", key, json.dumps({k: res[key][k] for k in ("map_mean_m", "odometry_mean_m",
                                                                   "map_vs_odometry")}), flush=True)
    return res


def route(seed: int = 0) -> dict[str, Any]:
    """A synthetic world's route (world 0: the default route; world 2: the other held-out world) with
    its back end, through the in-process API (bench/e2e.py's runner): trajectory errors, the online
    floor, closures."""
    from e2e import run_inprocess

    from neoslam_stream.evaluation import evaluate_run

    res = {}
    for name, pipeline, profile in (("default", "neoslam", "default"), ("paper", "neoslam", "paper"),
                                    ("ratslam", "ratslam", "default")):
        cfg = load_config(profile, {"run": {"pipeline": pipeline}, "source": {"params": {"seed": seed}}})
        run_dir = CACHE / ("route" if seed == 0 else f"route{seed}") / name
        run_inprocess(cfg, run_dir)
        ev = evaluate_run(run_dir, radius=1.0, plot=False)
        res[name] = {"ape_mean_m": ev["trajectory_ape"]["mean_m"],
                     "ape_on_final_map_m": ev.get("map_trajectory_ape", {}).get("mean_m"),
                     "online_floor_m": ev.get("online_floor", {}).get("ape_mean_m"),
                     "odometry_mean_m": ev["odometry_ape"]["mean_m"], **ev["loop_closures"]}
        print(f"route{seed}", name, json.dumps(res[name], default=str)[:300], flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default="input,light,nordland,synthetic,proxies,gardens,tuc,route,route2")
    ap.add_argument("--out", default=str(RESULTS / "generalisation.json"))
    ap.add_argument("--table", action="store_true", help="print the README table from --out and stop")
    ap.add_argument("--jobs", type=int, default=1, help="processes for the input sizes' grids")
    args = ap.parse_args()
    out_path = Path(args.out)
    res: dict[str, Any] = json.loads(out_path.read_text()) if out_path.exists() else {}
    if args.table:
        from generalisation_table import table

        print(table(res))
        return
    only = set(args.only.split(","))
    res["parts"] = PARTS
    valid = present(DECISION_PARTS) if only & {"input", "light", "choice"} else []
    if "input" in only:
        res["input"] = choose_input(valid, args.jobs)
        res["choice"] = res["input"].pop("grids").get(res["input"]["choice"])
    if "light" in only:
        res["light"] = choose_light(valid)
    if "choice" in only and "input" not in only:
        res["choice"] = _grid_at(default_config().features.input_size, valid)
    kinds = {"nordland": "nordland", "synthetic": "synthetic", "proxies": ("sparse", "hard"), "gardens": "gardens"}
    for key, prefix in kinds.items():
        if key in only:
            parts = present([p for p in PARTS["test"] if p.startswith(prefix)])
            res.setdefault("test", {}).update(frontends(parts))
    if "tuc" in only:
        res["tuc"] = tuc()
    if "route" in only:
        res["route"] = route(0)
    if "route2" in only:
        res["route_2"] = route(2)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=1, default=float))
    print(f"wrote {out_path}")


if __name__ == "__main__":
    main()
