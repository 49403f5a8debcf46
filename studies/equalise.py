"""Does equalising each frame's grey histogram before stage A keep places under other light?

A global, monotonic change of brightness (gain, gamma) leaves a frame's histogram-equalised grey
image nearly as it was, so equalising before the backbone is the classic way to make a front end
indifferent to light. Measured here through the default front end (A -> B -> C -> D) with A's
input as captured and the calibrated decision as it shipped then (``THEN``), with and without
cv2.equalizeHist on each frame's grey image (and with contrast-limited equalisation per tile,
CLAHE, as usually set), and with each frame's log intensity standardised instead
(``features.photometric: log_standardise``, which the default now ships),
on the perturbed sparse stand-ins of seeds 6-8 (their second lap under other light) and the plain
stand-in of seed 6, parts that neither choose a constant nor report one (bench/generalisation.py's
PARTS), and on Nordland's validation subsets 2 and 4 and synthetic world 1. Nothing is chosen from
it (the light setting the default ships was chosen by bench/generalisation.py's LIGHT_RULE).
Writes studies/results/equalise.json.

Run: ``.venv/bin/python studies/equalise.py``.
"""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any

import _paths  # the package and bench/ on sys.path
import cv2
import generalisation as G
import numpy as np

PARTS = ["hard:6", "hard:7", "hard:8", "sparse:6", "nordland:2", "nordland:4", "synthetic:1"]


#: contrast-limited equalisation as usually set (clip limit 2, 8 x 8 tiles), not tuned here
CLAHE = {"clipLimit": 2.0, "tileGridSize": (8, 8)}


def equalised(img: np.ndarray, limited: bool = False) -> np.ndarray:
    """The frame's grey image, histogram-equalised (over the whole frame, or contrast-limited per
    tile), in three channels (A takes grey frames so)."""
    grey = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    grey = cv2.createCLAHE(**CLAHE).apply(grey) if limited else cv2.equalizeHist(grey)
    return np.repeat(grey[:, :, None], 3, axis=2)


#: the front end these were measured with: A's input as captured and the calibrated decision as it
#: shipped then (z_min 4, rho 1); the default now standardises A's input itself (``log_standardised``
#: below, features.photometric) and decides at z_min 3.5, rho 1.1 (docs/mapping.md)
THEN = {"features": {"photometric": "none"}, "spatial_view": {"calibration": {"z_min": 4.0, "rho": 1.0}}}


def figures(part: str) -> dict[str, Any]:
    from neoslam_stream.config import load_config

    stream = G.part_stream(part)
    cfg = load_config("default", {"platform": stream.platform, **THEN})
    logstd = load_config("default", {"platform": stream.platform,
                                     **{**THEN, "features": {"photometric": "log_standardise"}}})
    plain = stream.frames
    eq = replace(stream, name=f"{stream.name}_equalised", frames=lambda: (equalised(i) for i in plain()))
    limited = replace(stream, name=f"{stream.name}_clahe", frames=lambda: (equalised(i, True) for i in plain()))
    out = {}
    for name, s, c in (("as_captured", stream, cfg), ("equalised", eq, cfg), ("contrast_limited", limited, cfg),
                       ("log_standardised", stream, logstd)):
        r = G.frontend_figures(s, c)
        out[name] = {k: r.get(k) for k in ("closures", "correct", "precision", "recall")}
    return out


def main() -> None:
    res = {"what": __doc__.split("\n\n")[0], "parts": {}}
    for part in PARTS:
        res["parts"][part] = figures(part)
        print(part, json.dumps(res["parts"][part]), flush=True)
    path = _paths.RESULTS / "equalise.json"
    path.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
