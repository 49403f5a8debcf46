"""B's fast path against the default's B: do the loop closures stay the same?

The default's B (float32 Gaussian projection) against int8 storage with 7-bit features
(``projector.matrix_dtype: int8``, ``feature_bits: 7``: 0.29x its time per frame,
docs/performance.md), each on every part of bench/generalisation.py (validation and held-out),
with everything else the shipped default: loop-closure figures through B, C and D from the same
cached A features. Writes studies/results/projector_paths.json.

Run: ``.venv/bin/python studies/projector_paths.py [--out studies/results/projector_paths.json]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import _paths  # the package and bench/ on sys.path
import generalisation as G

from neoslam_stream.config import load_config

PATHS = {"float32": {}, "int8_7bit": {"matrix_dtype": "int8", "feature_bits": 7}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(_paths.RESULTS / "projector_paths.json"))
    args = ap.parse_args()
    res = {}
    for part in G.PARTS["validation"] + G.PARTS["test"]:
        stream = G.part_stream(part)
        row = {}
        for name, projector in PATHS.items():
            cfg = load_config("default", {"platform": stream.platform, "projector": projector})
            row[name] = G.frontend_figures(stream, cfg)
            row[name].pop("calibration", None)
        res[part] = row
        print(part, {k: (v["closures"], v["correct"], v["precision"], round(v["recall"], 3)) for k, v in row.items()},
              flush=True)
    Path(args.out).write_text(json.dumps({"paths": PATHS, "parts": res}, indent=1, default=float))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
