"""Where the default loses a revisit: each revisiting frame's decision, stage by stage.

The calibrated decision (docs/mapping.md, "Decisions from the run's own statistics") closes a
loop on frame t only when D's best candidate is the right place, stands out from the unrelated
ones (z >= z_min), reaches the level of the view a moment ago (rho), and the frames of the last
sequence_m of travel agree. For every frame that revisits a place (the stream's ground truth:
within 1 m of a place seen 5 m of travel earlier, with the same facing), this records where the
default's decision stopped: no assessment yet, the winner elsewhere, z below z_min, below the
recent view's level, the stretch's evidence refused, or closed (right or wrong).

Run on the perturbed sparse stand-ins of seeds 6-8 (their second lap under other light, blur, noise
and a drifting offset) and the plain ones of the same seeds: parts that neither choose a constant
nor report one (bench/generalisation.py's PARTS). Nothing is chosen from it. Writes
studies/results/revisit_decisions.json.

Run: ``.venv/bin/python studies/revisit_decisions.py [--parts hard:6,hard:7,hard:8,sparse:6,sparse:7,sparse:8]``.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import generalisation as G
import numpy as np
from streams import RADIUS_M

from neoslam_stream.algorithms.frontend import FrontEnd

PARTS = ["hard:6", "hard:7", "hard:8", "sparse:6", "sparse:7", "sparse:8"]
#: where a revisiting frame's decision stopped, in the order the decision takes its steps
STEPS = ("no assessment", "winner elsewhere", "z below z_min", "below the recent view's level",
         "stretch refused", "closed, right", "closed, wrong")


def recorded(fe: FrontEnd) -> dict[int, dict[str, Any]]:
    """Frame -> D's assessment and verdict, recorded by wrapping the front end's calibration."""
    cal = fe.spatial_view.calibration
    assess, accept = cal.assess, cal.accept
    last: dict[str, Any] = {}
    rows: dict[int, dict[str, Any]] = {}

    def on_assess(scores: np.ndarray, times: np.ndarray, recent: float | None, best: int | None = None):
        a = assess(scores, times, recent, best)
        last["a"] = a
        return a

    def on_accept(t: int, ref: int, confidence: float) -> bool:
        ok = accept(t, ref, confidence)
        a = last.pop("a", None)
        rows[t] = {"ref": ref, "confidence": confidence, "closed": ok,
                   "z": None if a is None else a.z}
        return ok

    cal.assess, cal.accept = on_assess, on_accept
    return rows


def step_of(row: dict[str, Any] | None, right: bool, z_min: float) -> str:
    """Where one revisiting frame's decision stopped (STEPS)."""
    if row is None or row["z"] is None:
        return "no assessment"
    if row["closed"]:
        return "closed, right" if right else "closed, wrong"
    if not right:
        return "winner elsewhere"
    if row["z"] < z_min:
        return "z below z_min"
    if row["confidence"] < 0:  # z passed, so the recent view's level is what failed
        return "below the recent view's level"
    return "stretch refused"


def part_decisions(part: str) -> dict[str, Any]:
    stream = G.part_stream(part)
    cfg = G.default_config(stream.platform)
    fe = FrontEnd(cfg.front_end())
    rows = recorded(fe)
    cells = stream.cells(fe)
    out = [fe.template(c, s) for c, s in zip(cells, stream.stamps, strict=True)]
    gt, revisit = stream.truth["gt"], stream.truth["revisit"]
    z_min = cfg.spatial_view.calibration.z_min
    steps: Counter[str] = Counter()
    for t in map(int, np.flatnonzero(revisit)):
        row = rows.get(t)
        ref = -1 if row is None else row["ref"]
        right = ref >= 0 and float(np.hypot(*(gt[t, :2] - gt[ref, :2]))) <= RADIUS_M
        steps[step_of(row, right, z_min)] += 1
    score = stream.score(G.matched_frames(out, fe.spatial_view.interval_start))
    return {"revisit_frames": int(revisit.sum()), "steps": {s: steps.get(s, 0) for s in STEPS},
            "precision": score["precision"], "recall": score["recall"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--out", default=str(_paths.RESULTS / "revisit_decisions.json"))
    args = ap.parse_args()
    res: dict[str, Any] = {"steps": list(STEPS), "parts": {}}
    for part in args.parts.split(","):
        print(f"{part} ...", flush=True)
        res["parts"][part] = part_decisions(part)
        print(f"  {res['parts'][part]}", flush=True)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
