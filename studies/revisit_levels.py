"""What a revisit under other light scores against the level D's decision asks of it, and what B's
re-ranking could keep of A's score: the two stage targets docs/mapping.md reports as not reached.

D closes a loop when its winner stands out from the unrelated places (z >= z_min) and reaches
rho of the way from their mean mu to the level of the view a moment ago (s_recent), over a stretch
of consistent frames (algorithms/calibration.py). This study records, on every validation part
(bench/generalisation.py ``PARTS["validation"]``, Gardens Point's ``a`` halves among them), each
frame's assessment as the shipped default makes it, then replays the decision with other rules on
those assessments (a fresh ``RunCalibration.accept`` per rule; the replay leaves out what a
closure changes downstream, D's merges and templates, and reproduces the shipped figures):

* ``grid``: z_min x rho, the evidence's stretch at least 1-4 frames, and the level taken from the
  view ``lag_m`` of travel ago instead of the view a moment ago;
* ``ratios``: z / z_recent of the winners that stand out (z >= z_min), right and wrong, per part;
* ``condition_shift``: how the places seen recently (under the query's own light) but outside its
  neighbourhood score against the old unrelated places, in the old places' sd: a sign of a change
  of light that a run could use to lower the level;
* ``heading_oracle``: on the single routes (their truth has headings), the rules at the shipped
  z_min with and without a gate no run has, the truth's heading: a forward camera sees a place
  again facing the same way, so a winner seen facing more than a quarter turn away is refused;
* ``heading_visual``: the same gate on every part with the heading a run could have without
  odometry, the default's visual odometry (``visual_odometry``) on the images, integrated from the
  run's first frame (across the junction of two walks streamed one after the other too);
* ``rerank``: B's recall@1 with its bits' shortlist re-ranked by the descriptors (as shipped), by
  A's own score (cosine less the run's mean up to the query), or by both standardised and summed.

Nothing is chosen from it; no held-out part is run. Writes studies/results/revisit_levels.json.
Run: ``.venv/bin/python studies/revisit_levels.py [--parts nordland:2,gardens:night:a,...]``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import generalisation as G
import numpy as np

from neoslam_stream.algorithms.backend import CameraOdometry
from neoslam_stream.algorithms.calibration import RunCalibration
from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.config import load_config
from neoslam_stream.evaluation.recognition import (
    causal_centred_cosine,
    cosine,
    overlaps,
    ranking_curve,
    shortlisted,
)

#: travel back to the view whose score sets the level (0: the view a moment ago, as shipped)
LAGS_M = (0.0, 2.0, 4.0)
GRID = {"z_min": (3.0, 3.5, 4.0), "rho": (0.5, 0.7, 0.9), "min_frames": (1, 4), "lag_m": LAGS_M}
#: the shipped rule's point of the grid (its z_min and rho read from the default)
_CALIBRATION = load_config("default").spatial_view.calibration
SHIPPED = {"z_min": _CALIBRATION.z_min, "rho": _CALIBRATION.rho, "min_frames": 1, "lag_m": 0.0}
SHORTLIST = 20


def _score_of(sv: Any, k: int, y_bm: Any) -> float | None:
    """Interval k's union-normalised score against the frame's cells (None: k is not kept)."""
    try:
        union = sv.unions[k]
    except (KeyError, IndexError):
        return None
    n = len(y_bm)
    return union.intersection_cardinality(y_bm) * (n / max(len(union), n))


def _lagged(sv: Any, y_bm: Any, stamp: float, seconds: float) -> float | None:
    """The score of the newest interval opened at least ``seconds`` before ``stamp``."""
    for k in range(sv.n_intervals - 1, -1, -1):
        try:
            opened = sv.interval_stamps[k]
        except (KeyError, IndexError):
            continue
        if opened <= stamp - seconds:
            return _score_of(sv, k, y_bm)
    return None


def record(part: str) -> dict[str, Any]:
    """Every assessed frame of the shipped default on ``part``: z, score, the null's mean and sd, the
    recent view's score, the lagged views' scores, the recent unrelated places' mean, the winner's
    place (first frame of its template) and matched frame."""
    stream = G.part_stream(part)
    cfg = G.default_config(stream.platform)
    fe = FrontEnd(cfg.front_end())
    sv, cal = fe.spatial_view, fe.spatial_view.calibration
    rows: dict[int, dict[str, Any]] = {}
    assess, calibrated = cal.assess, sv._calibrated

    def on_assess(scores: np.ndarray, times: np.ndarray, recent: float | None, best: int | None = None):
        a = assess(scores, times, recent, best)
        if a is not None:
            rows[sv.t] = {"frame": sv.t, "z": a.z, "s": a.score, "mean": a.mean, "sd": a.sd, "recent": recent}
        return a

    def on_calibrated(y: np.ndarray, y_bm: Any, stamp: float, descriptor: np.ndarray | None = None):
        lags = {d: _lagged(sv, y_bm, stamp, cal.seconds(d)) for d in LAGS_M if d > 0}
        limit = sv.n_intervals - sv.config.exclude_recent_intervals
        shift = None
        n_idx = int(np.searchsorted(sv.indexed, limit)) if limit > 0 else 0
        if n_idx:
            scores, times = sv.index.normalised_scores(y, n_idx), sv.place_stamps[:n_idx]
            young = (times > stamp - cal.min_gap_s) & (times < stamp - cal.seconds(cal.config.neighbourhood_m))
            shift = float(scores[young].mean()) if young.sum() >= 5 else None
        out = calibrated(y, y_bm, stamp, descriptor)
        best = out[1]
        if sv.t in rows and best >= 0:
            rows[sv.t].update(lags=lags, young_mean=shift, matched=int(sv.interval_start[best]),
                              place=int(sv.template_start[sv.interval_template[best]]))
        return out

    cal.assess, sv._calibrated = on_assess, on_calibrated
    sdrs = stream.sdrs(fe)
    out = [fe.template_of(c, s) for c, s in zip(sdrs, stream.stamps, strict=True)]
    shipped = stream.score(G.matched_frames(out, sv.interval_start))
    return {"stream": stream, "config": cfg, "rows": {t: r for t, r in rows.items() if "place" in r},
            "intervals": list(cal.intervals), "shipped": shipped}


def confidence_rule(z_min: float, rho: float, lag_m: float) -> Callable[[dict[str, Any]], float]:
    """The calibrated decision's per-frame confidence, min(z - z_min, (s - level) / sd), with the
    level from the view a moment ago (``lag_m`` 0) or from the view ``lag_m`` of travel ago."""
    def confidence(r: dict[str, Any]) -> float:
        ref = r["recent"] if not lag_m else r["lags"].get(lag_m)
        level = r["mean"] if ref is None else r["mean"] + rho * max(ref - r["mean"], 0.0)
        return min(r["z"] - z_min, (r["s"] - level) / r["sd"])
    return confidence


def replay(rec: dict[str, Any], confidence: Callable[[dict[str, Any]], float], min_frames: int = 1) -> dict[str, Any]:
    """The closures a rule gives on the recorded assessments: each frame through a fresh
    ``RunCalibration.accept`` (its stretch at least ``min_frames`` frames), scored as the benches score."""
    stream, cfg = rec["stream"], rec["config"]
    cal = RunCalibration(cfg.spatial_view.calibration, cfg.platform)
    cal.intervals = deque(rec["intervals"], maxlen=64)
    derived = cal.sequence_frames
    if min_frames > derived:  # the stretch's length for this replay only
        cal = _with_frames(cal, min_frames)
    pairs = []
    for t in range(len(stream.stamps)):
        r = rec["rows"].get(t)
        if r is None:
            cal.accept(t, -1, -math.inf)
        elif cal.accept(t, r["place"], confidence(r)):
            pairs.append((t, r["matched"]))
    return stream.score(pairs)


def _with_frames(cal: RunCalibration, frames: int) -> RunCalibration:
    class Longer(RunCalibration):
        sequence_frames = property(lambda self: frames)  # type: ignore[assignment]
    longer = Longer(cal.config, cal.platform)
    longer.intervals = cal.intervals
    return longer


def visual_heading(rec: dict[str, Any]) -> np.ndarray:
    """Each frame's heading as the default's visual odometry integrates it from the images (rad,
    0 at the first frame), with the part's stamps and platform."""
    stream, cfg = rec["stream"], rec["config"]
    vo = CameraOdometry(cfg.visual_odometry, cfg.platform.speed_mps)
    turns = [vrot * dt for vrot, dt in (vo.on_frame(img, s)[1:] for img, s in
                                         zip(stream.pixels(), stream.stamps, strict=True))]
    return np.cumsum(turns)


def heading_gated(confidence: Callable[[dict[str, Any]], float], heading: np.ndarray) -> Callable[[dict[str, Any]], float]:
    """``confidence``, refused (-inf) when ``heading`` (rad, per frame) at the frame and at its
    winner's matched frame differ by more than a quarter turn."""
    def gated(r: dict[str, Any]) -> float:
        d = heading[r["frame"]] - heading[r["matched"]]
        return confidence(r) if abs(math.atan2(math.sin(d), math.cos(d))) < math.pi / 2 else -math.inf
    return gated


def heading_figures(rec: dict[str, Any], plain: dict[float, list[float | None]],
                    heading: np.ndarray) -> dict[str, dict[str, list[float | None]]]:
    """Per rho, the shipped z_min's figures without (``plain``, already replayed) and with the
    heading gate."""
    return {str(rho): {"plain": plain[rho], "gated": _figures(replay(rec, heading_gated(
        confidence_rule(SHIPPED["z_min"], rho, 0.0), heading)))} for rho in GRID["rho"]}


def labels(rec: dict[str, Any]) -> dict[int, str]:
    """Per assessed frame, whether closing it on its winner would be right, wrong or neither (a
    re-recognition, not scored)."""
    out = {}
    for t, r in rec["rows"].items():
        s = rec["stream"].score([(t, r["matched"])])
        out[t] = "right" if s["correct"] else "wrong" if s["closures"] else "neither"
    return out


def _quantiles(values: list[float]) -> list[float] | None:
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)])
    return [round(float(q), 3) for q in np.percentile(v, [10, 50, 90])] if v.size else None


def ratios(rec: dict[str, Any], lab: dict[int, str], z_min: float) -> dict[str, Any]:
    """z / z_recent and the recent unrelated places' shift ((young mean - mu) / sd), p10/50/90,
    for the standing-out winners, right and wrong."""
    out: dict[str, Any] = {}
    for kind in ("right", "wrong"):
        rows = [r for t, r in rec["rows"].items() if lab[t] == kind and r["z"] >= z_min and r["recent"] is not None]
        z_recent = [(r["recent"] - r["mean"]) / r["sd"] for r in rows]
        out[kind] = {"frames": len(rows),
                     "z_over_z_recent": _quantiles([r["z"] / zr if zr > 0 else None for r, zr in zip(rows, z_recent, strict=True)]),
                     "condition_shift": _quantiles([None if r["young_mean"] is None else
                                                    (r["young_mean"] - r["mean"]) / r["sd"] for r in rows])}
    return out


def rerank(part: str) -> dict[str, float]:
    """B's recall@1: its bits' shortlist re-ranked by the descriptors (shipped), by A's score, or by
    both standardised over the shortlist and summed; and A's own."""
    stream = G.part_stream(part)
    fe = FrontEnd(G.default_config(stream.platform).front_end())
    fc = fe.config.features
    feats = stream.features(fc.photometric, fc.input_size)
    codes = [c for k in range(0, len(feats), 8) for c in fe.codes(feats[k:k + 8])]
    queries, candidates, allowed, right = stream.recognition_truth()
    ix = np.ix_(queries, candidates)
    allowed, right = allowed.astype(bool), right.astype(bool)
    bits = overlaps([c.bits for c in codes])[ix].astype(np.float64)
    descriptors = cosine(np.stack([c.descriptor for c in codes]).astype(np.float64))[ix]
    a_score = causal_centred_cosine(feats)[ix]

    def recall(scores: np.ndarray) -> float:
        return round(ranking_curve(scores, allowed, right).final_recall, 4)

    return {"A": recall(a_score), "B_descriptors": recall(shortlisted(bits, descriptors, allowed, SHORTLIST)),
            "B_A_score": recall(shortlisted(bits, a_score, allowed, SHORTLIST)),
            "B_both": recall(_voted(bits, (descriptors, a_score), allowed, SHORTLIST))}


def _voted(coarse: np.ndarray, fines: tuple[np.ndarray, ...], allowed: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` best by ``coarse`` scored by the sum of ``fines``, each standardised over the k."""
    c = np.where(allowed, coarse, -np.inf)
    top = np.argsort(-c, axis=1, kind="stable")[:, :k]
    rows = np.arange(c.shape[0])[:, None]
    total = np.zeros(top.shape)
    for f in fines:
        v = f[rows, top]
        total += (v - v.mean(axis=1, keepdims=True)) / (v.std(axis=1, keepdims=True) + 1e-9)
    out = np.full(c.shape, -np.inf)
    out[rows, top] = np.where(np.isfinite(c[rows, top]), total, -np.inf)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default=",".join(G.present(G.PARTS["validation"])))
    ap.add_argument("--out", default=str(_paths.RESULTS / "revisit_levels.json"))
    args = ap.parse_args()
    parts = args.parts.split(",")
    res: dict[str, Any] = {"parts": parts, "grid": [], "ratios": {}, "rerank": {}, "shipped": {},
                           "heading_oracle": {}, "heading_visual": {}}
    records = {}
    for part in parts:
        print(f"{part} ...", flush=True)
        rec = records[part] = record(part)
        z_min = rec["config"].spatial_view.calibration.z_min
        res["shipped"][part] = {k: rec["shipped"][k] for k in ("precision", "recall")}
        res["ratios"][part] = ratios(rec, labels(rec), z_min)
        res["rerank"][part] = rerank(part)
        plain = {rho: _figures(replay(rec, confidence_rule(SHIPPED["z_min"], rho, 0.0))) for rho in GRID["rho"]}
        if rec["stream"].truth["kind"] == "world":
            res["heading_oracle"][part] = heading_figures(rec, plain, rec["stream"].truth["gt"][:, 2])
        res["heading_visual"][part] = heading_figures(rec, plain, visual_heading(rec))
        print(f"  heading: {res['heading_oracle'].get(part)} {res['heading_visual'][part]}", flush=True)
        print(f"  {res['shipped'][part]} {res['ratios'][part]} {res['rerank'][part]}", flush=True)
    for point in itertools.product(*GRID.values()):
        p = dict(zip(GRID, point, strict=True))
        rule = confidence_rule(p["z_min"], p["rho"], p["lag_m"])
        figs = {part: replay(records[part], rule, p["min_frames"]) for part in parts}
        res["grid"].append({**p, "parts": {k: _figures(v) for k, v in figs.items()}})
    res["summary"] = summarise(res)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res["summary"], indent=1))
    print(f"wrote {args.out}")


def _figures(score: dict[str, Any]) -> list[float | None]:
    """[precision, recall] of a stream's score, rounded."""
    return [None if score["precision"] is None else round(score["precision"], 4), round(score["recall"], 4)]


def summarise(res: dict[str, Any]) -> dict[str, Any]:
    """Of the grid points whose precision reaches 0.99 on every synthetic world, the best recall on
    each Gardens Point part; and the shipped point's figures from the replay."""
    def synthetic_ok(g: dict[str, Any]) -> bool:
        return all((v[0] or 0) >= 0.99 for k, v in g["parts"].items() if k.startswith("synthetic"))

    feasible = [g for g in res["grid"] if synthetic_ok(g)]
    out: dict[str, Any] = {"points": len(res["grid"]), "synthetic_precision_0.99": len(feasible)}
    for part in (p for p in res["parts"] if p.startswith("gardens")):
        best = max(feasible, key=lambda g: g["parts"][part][1], default=None)
        top = max(res["grid"], key=lambda g: g["parts"][part][1])
        out[part] = {"best_recall_keeping_synthetic": None if best is None else
                     {**{k: best[k] for k in GRID}, "figures": best["parts"][part]},
                     "best_recall_at_all": {**{k: top[k] for k in GRID}, "figures": top["parts"][part],
                                            "synthetic": {k: v for k, v in top["parts"].items()
                                                          if k.startswith("synthetic")}}}
    shipped = next(g for g in res["grid"] if all(g[k] == v for k, v in SHIPPED.items()))
    out["shipped_replayed"] = shipped["parts"]
    return out


if __name__ == "__main__":
    main()
