"""Solves of the experience map beside the least squares, measured before the default's
``bias_walk`` existed -> studies/results/relaxation_models.json (studies/mapping_choices.md: "A pose-graph solve",
"A wandering bias in the solve").

The least-squares solve (``relaxation: least_squares``, algorithms/ratslam/graph_solve.py) takes the
headings first and the positions after them. Each model here starts from that solution and runs
the Gauss-Newton solve on SE(2) that the default's ``bias_walk`` runs (algorithms/ratslam/
pose_graph.py) over the same links, with its own weights and rates:

* ``joint:L``: a link's position residual, in its from-experience's frame, weighted 1 per m² and
  its heading residual L per rad², so a closure's position error can turn headings;
* ``stretch:L``: as joint, plus one unknown heading rate per stretch of dead reckoning (the links
  from one loop link to the next, that loop link included), its heading residual + rate x dt;
* ``walk:L:M[:P]``: as joint, plus a heading rate per link that follows a random walk from link
  to link (each step weighted M per (rad/s)², each rate P, by default only enough to keep a rate
  no link constrains at 0), as a drifting yaw-rate bias does;
* ``walk_scaled:SW:SB``: the walk with a random walk's variances: position 1 / (d + median d),
  heading 1 / (SW (dt + median dt)), a bias step 1 / (SB (dt + median dt)).

Replayed on the inputs of studies/relaxation.py: the default's map input, recorded once per
synthetic world, and the TUC corridor's halves run alone with the default's back end. Nothing is
chosen here: the relaxation's rule (docs/mapping.md) never saw these candidates before it ran.

Run: ``.venv/bin/python studies/relaxation_models.py [--models joint:1,walk:10:100] [--worlds 1,3,4,0,2]
[--tuc first,second] [--out studies/results/relaxation_models.json]``.
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
from neoslam_stream.algorithms.ratslam.pose_graph import RATE_PRIOR, relax_pose_graph

DEFAULT_MODELS = ("joint:1,joint:3,stretch:1,walk:10:100,walk:10:100:1,walk_scaled:0.01:0.001,walk_scaled:0.1:0.01,"
                  "walk_scaled:0.1:0.001")


def parse_model(spec: str) -> dict[str, Any]:
    """``joint:L``, ``stretch:L``, ``walk:L:M[:P]`` or ``walk_scaled:SW:SB`` (module docstring)."""
    kind, *args = spec.split(":")
    need = {"joint": (1,), "stretch": (1,), "walk": (2, 3), "walk_scaled": (2,)}
    if kind not in need or len(args) not in need[kind]:
        raise ValueError(f"model {spec!r}: expected joint:L, stretch:L, walk:L:M[:P] or walk_scaled:SW:SB")
    return {"kind": kind, "args": [float(a) for a in args], "name": spec}


def _weights(model: dict[str, Any], ld: np.ndarray, ldt: np.ndarray) -> tuple[np.ndarray, ...]:
    """(position, heading, rate-step) weights per link (steps: one fewer than links)."""
    m = ld.shape[0]
    kind, a = model["kind"], model["args"]
    if kind == "walk_scaled":
        d0, t0 = np.median(ld) + 1e-9, np.median(ldt) + 1e-9
        return 1.0 / (ld + d0), 1.0 / (a[0] * (ldt + t0)), 1.0 / (a[1] * (ldt[1:] + t0))
    step = np.full(m - 1, a[1]) if kind == "walk" else np.zeros(0)
    return np.ones(m), np.full(m, a[0]), step


def pose_graph(x: np.ndarray, y: np.ndarray, th: np.ndarray, lf: np.ndarray, lt: np.ndarray, ld: np.ndarray,
               lh: np.ndarray, lface: np.ndarray, ldt: np.ndarray, closes: np.ndarray,
               model: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
    """New (x, y, th) of the experiences and the solve's figures, as the module docstring says:
    algorithms/ratslam/pose_graph.py's solve with the model's weights and rates.

    Links as ExperienceMap stores them: from, to, d, heading, facing, dt; ``closes``: whether each
    link closed a loop (the stretches' ends)."""
    m = lf.shape[0]
    kind = model["kind"]
    if kind == "stretch":  # a loop link ends its stretch: the links after it start the next
        rate_of = np.concatenate([[0], np.cumsum(closes[:-1])]).astype(np.int64)
    elif kind in ("walk", "walk_scaled"):
        rate_of = np.arange(m)
    else:
        rate_of = None
    wp, wt, wb = _weights(model, ld, ldt)
    prior = model["args"][2] if kind == "walk" and len(model["args"]) > 2 else RATE_PRIOR
    return relax_pose_graph(x, y, th, lf, lt, ld, lh, lface, ldt, wp, wt, rate_of, wb if wb.size else None, prior)


def map_class(model: dict[str, Any]) -> type:
    """An ExperienceMap whose loop links are followed by :func:`pose_graph` under ``model``."""

    class ModelMap(ExperienceMap):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.closes: list[bool] = []
            self.solves = 0

        def _link(self, a: int, b: int, rel_rad: float, closes_loop: bool = True) -> None:
            m0 = self._m
            super()._link(a, b, rel_rad, closes_loop)
            if self._m > m0:
                self.closes.append(closes_loop)

        def iterate(self) -> None:
            if self._m < 2 or not self._loop_linked:
                return
            self._loop_linked = False
            nodes, lf, lv = self._nodes, self._lf[: self._m], self._lv[: self._m]
            x, y, th, _ = pose_graph(nodes[: self._n, 0].copy(), nodes[: self._n, 1].copy(), nodes[: self._n, 2].copy(),
                                     lf[:, 0].astype(np.int64), lf[:, 1].astype(np.int64), lv[:, 0], lv[:, 1],
                                     lv[:, 2], lv[:, 3], np.array(self.closes), model)
            nodes[: self._n, 0], nodes[: self._n, 1], nodes[: self._n, 2] = x, y, th
            self.solves += 1

    return ModelMap


def main() -> None:
    from relaxation import map_input, replay

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=DEFAULT_MODELS, help="comma-separated model specs")
    ap.add_argument("--worlds", default="1,3,4,0,2", help="synthetic worlds (seeds), comma-separated")
    ap.add_argument("--tuc", default="first,second", help="TUC halves to run ('' for none)")
    ap.add_argument("--out", default=str(_paths.RESULTS / "relaxation_models.json"))
    args = ap.parse_args()
    models = [parse_model(s) for s in args.models.split(",") if s]
    cases: list[tuple[str, Any]] = [(f"synthetic:{s}", int(s)) for s in args.worlds.split(",") if s]
    cases += [(f"tuc:{h}", h) for h in args.tuc.split(",") if h]
    parts: dict[str, dict[str, Any]] = {}
    for part, arg in cases:
        parts[part] = {}
        if part.startswith("synthetic"):
            inp = map_input(arg)
        else:
            from bench_settings import back_end_sections
            from tuc_corridor import run_half

            inp, (pose_cells, em) = None, back_end_sections("tuc")
        for name, cls in [("least_squares", ExperienceMap)] + [(m["name"], map_class(m)) for m in models]:
            t0 = time.perf_counter()
            if inp is not None:
                r = replay(inp, map_cls=cls, relaxation="least_squares")
                row = {"online_m": r["online_m"], "final_map_m": r["final_map_m"]}
            else:
                r = run_half(arg, pose_cells, {**em, "relaxation": "least_squares"}, map_cls=cls)
                row = {"online_m": r["map_mean_m"], "final_map_m": r["map_on_final_mean_m"]}
            parts[part][name] = {**row, "seconds": time.perf_counter() - t0}
            print(part, name, json.dumps(parts[part][name]), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"models": [m["name"] for m in models], "parts": parts}, indent=1))
    print("wrote", out)


if __name__ == "__main__":
    main()
