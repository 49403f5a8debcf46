"""Which visit a return's heading is compared with (``pose_cells.odometry_bias.reference``): the
place's first or its latest, checked on validation parts and reported on held-out ones ->
studies/results/bias_reference.json.

Why the question (docs/long_runs.md): on a day's run the estimator compared every return with the
place's first visit, hours before; such a sample averages a bias that has wandered since, and its
heading is known only modulo a turn, so it can move the estimate by at most pi / gap. The bias
slipped past the estimate, and the map bent. ``latest`` keeps the gap at one loop. On a one-route
part the two differ only from a place's third visit on.

``RULE`` (fixed before any held-out part was run): ``latest`` replaces ``first`` if on every
validation part (synthetic worlds 1, 3, 4 and the TUC run's first half, as the forgetting's) its
online and final-map APE are at most ``SLACK`` times ``first``'s. Held out: worlds 0 and 2, the TUC
run's second half, and the 240-lap day of world 0 (bench/day_back_end.py). The replays are
bias_forgetting.py's (the default's front end recorded once per world, cached), with the default's
forgetting.

Run: ``.venv/bin/python studies/bias_reference.py [--out studies/results/bias_reference.json]``.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import _paths  # the package and bench/ on sys.path
from bias_forgetting import default_back_end, front_end_stream, replay, tuc_half, validate_then_report
from relaxation import VALIDATION

REFERENCES = ("first", "latest")
SLACK = 1.05
RULE = (f"latest if its online and final-map APE are at most {SLACK:g} x first's on every one of "
        f"{', '.join(VALIDATION)}")


def part_rows(part: str) -> dict[str, dict[str, float]]:
    kind, which = part.split(":")
    rows = front_end_stream(int(which)) if kind == "synthetic" else None
    forget = default_back_end().pose_cells.odometry_bias.forget_s
    out = {}
    for ref in REFERENCES:
        out[ref] = replay(rows, forget, reference=ref) if rows is not None else tuc_half(which, forget, reference=ref)
        print(part, ref, json.dumps({k: round(v, 4) for k, v in out[ref].items()}), flush=True)
    return out


def choose(valid: dict[str, dict[str, dict[str, float]]]) -> dict[str, Any]:
    """``RULE`` over the validation parts' rows."""
    ratios = {part: {k: round(v["latest"][k] / v["first"][k], 4) for k in ("online_m", "final_map_m")}
              for part, v in valid.items()}
    ok = all(r <= SLACK for v in ratios.values() for r in v.values())
    return {"rule": RULE, "latest_vs_first": ratios, "reference": "latest" if ok else "first"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(_paths.RESULTS / "bias_reference.json"))
    args = ap.parse_args()
    validate_then_report({"references": list(REFERENCES)}, part_rows, choose, args.out)


if __name__ == "__main__":
    main()
