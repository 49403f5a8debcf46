"""The default's spatial-view cells on a route driven again and again -> studies/results/passes.json.

A robot that patrols revisits each place many times: the map should stop growing once the route is
known (loop closures, few new templates), and D's index and cost should grow with new places only,
not with frames. C's winner cells over ten passes of the looped synthetic route are recorded once
through the default's A, B and C (cached beside the generalisation cache: about 20 minutes; C keeps
learning, so each pass's SDRs are its own); D is then replayed over ``--passes`` passes, any after
the tenth repeating the tenth's SDRs. Per pass (frames 800-2400 of each, the stretch every pass
revisits, and the whole pass): loop closures, new templates, intervals and the intervals in D's
index, and D's time per frame with every score counted posting by posting and bit-sliced (the same
decisions, checked); the ``*_every_interval_indexed`` figures replay the default with
``spatial_view.index_revisits: true`` (every interval a candidate, as before revisits stayed out).
One core, one run: the ratio is the figure.

Run: ``.venv/bin/python studies/passes.py [--passes 10] [--out studies/results/passes.json]``;
``--lost-from bench/results/soak_default.json`` replays without the frames that soak lost.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import pickle
import time
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
from bench_settings import cache_key
from streams import STRETCH

from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.config import load_config

CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_generalisation"))
RECORDED = 10


def cache_path() -> Path:
    """Where the recorded cells are kept: named by the default's A, B and C settings, so that a
    change to any of them records the passes anew instead of replaying another front end's cells."""
    cfg = load_config("default")
    sections = [cfg.features.model_dump(), cfg.projector.model_dump(), cfg.neocortex.model_dump()]
    return CACHE / f"passes_cells_{RECORDED}_{cache_key(sections)}.pkl"


def record(path: Path | None = None) -> dict[str, Any]:
    """C's cells and the stamps of RECORDED passes of the default's looped route."""
    path = path or cache_path()
    if path.is_file():
        return pickle.loads(path.read_bytes())
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    cfg = load_config("default", {"source": {"params": {"loop": True}}})
    src = SyntheticWorldSource(**cfg.source.params)  # the route over and over
    route = src.route_len
    fe = FrontEnd(cfg.front_end())
    cells, stamps, t0 = [], [], time.time()
    for f in itertools.islice(src, RECORDED * route):  # the in-process API's front end, frame by frame
        res = fe.step(f.image, f.frame, f.stamp)
        cells.append(res.cells)
        stamps.append(f.stamp)
        if f.frame % 1000 == 0:
            print(f"recording C's cells: frame {f.frame} of {RECORDED * route} ({time.time() - t0:.0f} s)", flush=True)
    rec = {"route": route, "cells": cells, "stamps": stamps}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(rec))
    return rec


def replay(rec: dict[str, Any], passes: int, rows: bool, index_revisits: bool = False,
           lost: frozenset[int] = frozenset()) -> list[dict[str, Any]]:
    """D over ``passes`` passes; ``rows`` False: every score counted posting by posting;
    ``index_revisits`` True: every interval enters D's index (not the default); ``lost``: frames
    (numbered over all passes) that D does not see, as a live run that lost them."""
    fe = FrontEnd(load_config("default", {"spatial_view": {"index_revisits": index_revisits}}).front_end())
    sv = fe.spatial_view
    sv.index.sliced = None if rows else False
    route, cells = rec["route"], rec["cells"]
    dt = rec["stamps"][1] - rec["stamps"][0]
    out = []
    for p in range(passes):
        src = min(p, RECORDED - 1) * route
        closures = stretch = 0
        templates, t0 = sv.n_templates, time.perf_counter()
        ids = []
        for i in range(route):
            if p * route + i in lost:
                continue
            r = fe.template(cells[src + i], (p * route + i) * dt)
            closures += r["is_loop_closure"]
            stretch += STRETCH[0] <= i < STRETCH[1] and r["is_loop_closure"]
            ids.append(r["id"])
        out.append({"pass": p + 1, "closures": int(closures), "closures_800_2400": int(stretch),
                    "new_templates": sv.n_templates - templates, "intervals": sv.n_intervals,
                    "indexed": len(sv.indexed),
                    "d_ms_per_frame": 1e3 * (time.perf_counter() - t0) / route, "ids": ids})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--passes", type=int, default=RECORDED)
    ap.add_argument("--out", default=str(_paths.RESULTS / "passes.json"))
    ap.add_argument("--lost-from", help="a soak's JSON (bench/soak.py): D does not see the frames that run lost "
                                        "(its passes' lost_frames)")
    args = ap.parse_args()
    rec = record()
    lost: frozenset[int] = frozenset()
    if args.lost_from:
        lost = frozenset(f for p in json.loads(Path(args.lost_from).read_text())["passes"] for f in p["lost_frames"])
    sliced = replay(rec, args.passes, rows=True, lost=lost)
    counted = replay(rec, args.passes, rows=False, lost=lost)
    same = all(a["ids"] == b["ids"] for a, b in zip(sliced, counted, strict=True))
    every = replay(rec, args.passes, rows=True, index_revisits=True, lost=lost)
    res = {"route_frames": rec["route"], "recorded_passes": RECORDED, "stretch": list(STRETCH),
           "same_decisions": same, "lost_from": args.lost_from, "frames_lost": len(lost), "passes": []}
    for a, b, e in zip(sliced, counted, every, strict=True):
        row = {k: v for k, v in a.items() if k not in ("ids", "d_ms_per_frame")}
        row.update({"d_ms_per_frame_sliced": round(a["d_ms_per_frame"], 3),
                    "d_ms_per_frame_postings": round(b["d_ms_per_frame"], 3)})
        row.update({f"{k}_every_interval_indexed": e[k] for k in ("closures", "closures_800_2400", "new_templates",
                                                                 "indexed")})
        row["d_ms_per_frame_every_interval_indexed"] = round(e["d_ms_per_frame"], 3)
        res["passes"].append(row)
        print(json.dumps(row), flush=True)
    print("same decisions with both counts:", same)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
