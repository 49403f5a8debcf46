"""Stage by stage: how well each stage's representation of a frame recognises its place.

Every part of bench/generalisation.py (``PARTS``: its validation and held-out parts, Gardens Point
Walking's among them when its copy is present) streams through the shipped default (configs/
default.yaml with the part's platform): A's features, B's bits, C's winner cells, D's decisions, and
RatSLAM's local view (its view templates and its decisions). Each representation is judged the same
way (neoslam_stream/evaluation/recognition.py): each query frame's best match among its candidate
frames, and the precision-recall curve of sweeping a threshold over the best matches' scores. Scores:

* A: cosine after removing the run's mean so far (causal: at query q, the mean of every feature up to
  q, subtracted from the query and the candidates);
* B, C: the overlap count |S_q & S_r| of the on-bits, of the winner cells;
* D: the closures D decided, each with the evidence it was decided on (the calibrated decision's mean
  confidence over its stretch of travel; D's best_score when the calibration is off); its recall@1 is
  decided-and-right / queries with a place, where its curve ends;
* local view: the mean absolute difference of its view templates at their best shift, as OpenRatSLAM
  matches them (lower is more alike), and its decided closures as for D;
* and a diagnostic, ``A_as_B``: A's features centred as B centres them (each frame less B's running
  mean at its own time), by cosine: B's input, so that A_as_B -> B is what B's projection and sLSBH
  lose, A -> A_as_B what centring by the recent frames instead of the run's mean changes;
* and ``B_sequence``: B's best matches given the evidence D's decision takes (a query scored only
  when the best matches of the frames of the last sequence_m of travel follow on consistently, by
  their mean score: recognition.py ``sequence_curve``), to set D's recall at precision 0.95 against.

Queries and candidates (bench/streams.py ``recognition_truth``): on a two-traversal part (Nordland
summer then winter, Gardens Point's reference walk then its query walk) the second traversal's frames
against the first's, right within the part's tolerance; on a single route (the synthetic worlds and
stand-ins) every frame against the frames at least REVISIT_TRAVEL_M of travel earlier, right within
RADIUS_M with the same facing, recall over the revisiting frames. A's features are cached as
bench/streams.py does ($NEOSLAM_CACHE). Writes bench/results/stages.json (per part and stage:
recall_at_1, pr_area, recall_at_precision at 0.9, 0.95, 1.0, the curve in at most 50 points;
``summary``: per part the recall@1 of each stage, whether B's keeps A's, and whether D's recall at
precision 0.95 keeps B's, alone and given D's evidence; ``b_below_a``, ``d_below_b``,
``d_below_b_sequence``: the parts where one does not) and bench/results/
stages.png (one panel per part). docs/mapping.md, "Reading bench/stages.py", says how to read them.
Run: ``.venv/bin/python bench/stages.py [--parts nordland:0,gardens:hard:a,...] [--out FILE]``
(the default: every part; about 9 minutes on 2 cores, 5.5 with A's features cached); ``--plot``
redraws the figure from --out.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import generalisation as G  # noqa: E402
from streams import MissingData, Stream  # noqa: E402

from neoslam_stream.algorithms.frontend import FrontEnd, LocalViewFrontEnd  # noqa: E402
from neoslam_stream.algorithms.ratslam.local_view import LocalViewCells  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.evaluation.recognition import (  # noqa: E402
    causal_centred_cosine,
    cosine,
    decision_curve,
    figures,
    overlaps,
    ranking_curve,
    sequence_curve,
    shortlisted,
)

RESULTS = Path(__file__).resolve().parent / "results"
STAGES = ("A", "B", "C", "D", "local_view_templates", "local_view")
#: diagnostics beside the stages: A's features centred as B centres them (each frame less B's running
#: mean at its own time, ``projector.centre_window``), by cosine: B's input before its projection and
#: sLSBH, so that A_as_B -> B is what the projection and binarisation lose, A -> A_as_B what the
#: centring changes; and B's bits and C's cells alone, where B and C give descriptors that re-rank
#: the bits' (cells') shortlist (``spatial_view.rerank``)
DIAGNOSTICS = ("A_as_B", "B_bits", "C_cells", "B_sequence")
LABELS = {"A": "A features (centred cosine)", "A_as_B": "A centred as B centres (cosine)",
          "B": "B (bits shortlist, descriptor re-rank)", "C": "C (cells shortlist, descriptor re-rank)",
          "B_bits": "B bits alone (overlap)", "C_cells": "C cells alone (overlap)",
          "B_sequence": "B with D's evidence (a consistent stretch)", "D": "D decisions",
          "local_view_templates": "local view templates (error)", "local_view": "local view decisions"}
COLOURS = {"A": "tab:blue", "A_as_B": "tab:cyan", "B": "tab:orange", "C": "tab:green", "D": "tab:red",
           "B_bits": "tab:brown", "C_cells": "tab:olive", "B_sequence": "tab:purple",
           "local_view_templates": "tab:grey", "local_view": "black"}


@njit(cache=True, fastmath=True)
def _l1_min(a, b, allowed, out):  # pragma: no cover - compiled
    """out[i, j] = min(out[i, j], sum_k |a[i, k] - b[j, k]|) for every allowed (i, j)."""
    for i in range(a.shape[0]):
        ai = a[i]
        for j in range(b.shape[0]):
            if not allowed[i, j]:
                continue
            bj = b[j]
            cd = 0.0
            for k in range(a.shape[1]):
                cd += abs(ai[k] - bj[k])
            out[i, j] = min(out[i, j], cd)


def _shift_errors(tq: np.ndarray, tc: np.ndarray, allowed: np.ndarray, shift: int, step: int) -> np.ndarray:
    """OpenRatSLAM's match error of every allowed (query, candidate) pair of view templates: the
    query's columns [S, X-S) against the candidate's [o, o+X-2S), o = 0, step, .., 2S, the mean
    absolute difference at the best o (LocalViewCells.errors for many queries); inf where not allowed."""
    nq, Y, X = tq.shape
    W = X - 2 * shift
    a = np.ascontiguousarray(tq[:, :, shift:shift + W]).reshape(nq, -1)
    out = np.full((nq, tc.shape[0]), np.inf)
    for o in range(0, 2 * shift + 1, step):
        _l1_min(a, np.ascontiguousarray(tc[:, :, o:o + W]).reshape(tc.shape[0], -1), allowed, out)
    return out / (Y * W)


def view_errors(templates: np.ndarray, queries: np.ndarray, candidates: np.ndarray, allowed: np.ndarray,
                cfg: Any) -> np.ndarray:
    """The local view's match error of each query's view template against each allowed candidate's,
    checked against ``LocalViewCells.errors`` on a few queries."""
    if cfg.vt_panoramic:
        raise NotImplementedError("the bench compares non-panoramic view templates only")
    tq, tc = templates[queries], templates[candidates]
    err = _shift_errors(tq, tc, allowed, cfg.vt_shift_match, cfg.vt_step_match)
    cells = LocalViewCells(cfg)
    for t in tc:
        cells.add_template(t)
    for i in np.linspace(0, len(queries) - 1, 3).astype(int):
        ok = allowed[i]
        assert np.allclose(err[i, ok], cells.errors(tq[i])[0][ok], atol=1e-9), "view errors differ"
    return err


def run_part(part: str) -> dict[str, Any]:
    """Every stage of the shipped default on one part: the representations, the decisions, the
    figures."""
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    stream: Stream = G.part_stream(part)
    cfg = load_config("default", {"platform": stream.platform})
    fe = FrontEnd(cfg.front_end())
    fc = fe.config.features
    feats = stream.features(fc.photometric, fc.input_size)
    times["A_features"] = time.perf_counter() - t0

    t = time.perf_counter()
    codes = [c for k in range(0, len(feats), 8) for c in fe.codes(feats[k:k + 8])]
    bits = [c.bits for c in codes]
    times["B"] = time.perf_counter() - t
    t = time.perf_counter()
    sdrs = [fe.winner_cells(c) for c in codes]
    cells = [w.cells for w in sdrs]
    times["C"] = time.perf_counter() - t
    t = time.perf_counter()
    sv = fe.spatial_view
    calibrated = cfg.spatial_view.calibration.enabled
    d_out, d_score = [], []
    for w, s in zip(sdrs, stream.stamps, strict=True):
        o = fe.template_of(w, s)
        d_out.append(o)
        d_score.append(sv.calibration.evidence if calibrated else float(o["best_score"]))
    d_pairs = G.matched_frames(d_out, sv.interval_start)
    times["D"] = time.perf_counter() - t

    t = time.perf_counter()
    lv = LocalViewFrontEnd(cfg.local_view, cfg.platform)
    lv_calibrated = cfg.local_view.calibration.enabled
    templates, lv_out, lv_score = [], [], []
    for img, s in zip(stream.pixels(), stream.stamps, strict=True):
        templates.append(lv.cells.view_template(img))
        o = lv.template(img, s)
        lv_out.append(o)
        lv_score.append(lv.calibration.evidence if lv_calibrated else -float(o["best_score"]))
    lv_pairs = G.matched_frames(lv_out, None)
    times["local_view"] = time.perf_counter() - t

    t = time.perf_counter()
    queries, candidates, allowed, right = stream.recognition_truth()
    ix = np.ix_(queries, candidates)
    allowed, right = allowed.astype(bool), right.astype(bool)
    res: dict[str, Any] = {"frames": len(stream.stamps), "queries": len(queries),
                           "platform": stream.platform}
    b_overlaps, c_overlaps = overlaps(bits)[ix], overlaps(cells)[ix]
    curves = {"A": ranking_curve(causal_centred_cosine(feats)[ix], allowed, right),
              "A_as_B": ranking_curve(cosine(FrontEnd(fe.config, resolve=False).projector.centre(feats))[ix],
                                      allowed, right),
              "B_bits": ranking_curve(b_overlaps, allowed, right),
              "C_cells": ranking_curve(c_overlaps, allowed, right)}
    k = cfg.spatial_view.rerank
    if k and codes[0].descriptor is not None:
        # B's and C's output: the bits (cells) shortlist k candidates, the descriptors decide (as D does)
        fine = cosine(np.stack([c.descriptor for c in codes]).astype(np.float64))[ix]
        b_scores = shortlisted(b_overlaps, fine, allowed, k)
        curves["B"] = ranking_curve(b_scores, allowed, right)
        curves["C"] = ranking_curve(shortlisted(c_overlaps, fine, allowed, k), allowed, right)
    else:
        b_scores = b_overlaps
        curves["B"], curves["C"] = curves["B_bits"], curves["C_cells"]
    # B given the evidence D decides on: the frames of the last sequence_m of travel consistent
    cal = sv.calibration
    curves["B_sequence"] = sequence_curve(b_scores, allowed, right, queries, candidates,
                                          cal.sequence_frames, cal.max_step, cal.slack)
    res["sequence_frames"] = cal.sequence_frames
    err = view_errors(np.asarray(templates), queries, candidates, allowed, cfg.local_view)
    curves["local_view_templates"] = ranking_curve(-err, allowed, right)
    qpos = {int(f): i for i, f in enumerate(queries)}
    cpos = {int(f): j for j, f in enumerate(candidates)}
    for name, pairs, score in (("D", d_pairs, d_score), ("local_view", lv_pairs, lv_score)):
        decided = np.zeros(len(queries), bool)
        matched = np.full(len(queries), -1)
        scores = np.full(len(queries), np.nan)
        for f, m in pairs:
            if f in qpos:
                decided[qpos[f]], matched[qpos[f]], scores[qpos[f]] = True, cpos.get(m, -1), score[f]
        curves[name] = decision_curve(decided, matched, scores, right)
        res[f"{name}_closures"] = {**stream.score(pairs), "scored_by": "evidence" if (
            calibrated if name == "D" else lv_calibrated) else "best_score"}
    for name in STAGES + DIAGNOSTICS:
        res[name] = figures(curves[name])
    times["figures"] = time.perf_counter() - t
    res["seconds"] = {k: round(v, 2) for k, v in times.items()}
    res["seconds"]["total"] = round(time.perf_counter() - t0, 2)
    return res


def summary(parts: dict[str, Any]) -> dict[str, Any]:
    """Per part: each stage's recall@1, whether B's is at least A's, and D's recall at precision 0.95
    against B's, alone and given D's evidence."""
    out = {}
    for part, r in parts.items():
        if "skipped" in r:
            out[part] = {"skipped": r["skipped"]}
            continue
        row = {name: round(r[name]["recall_at_1"], 4) for name in STAGES + DIAGNOSTICS}
        row["b_keeps_a"] = r["B"]["recall_at_1"] >= r["A"]["recall_at_1"]
        row["b_keeps_a_as_b"] = r["B"]["recall_at_1"] >= r["A_as_B"]["recall_at_1"]
        # D's recall at precision 0.95 against B's: alone, and with the evidence D takes
        d95 = r["D"]["recall_at_precision"]["0.95"]
        row["D_at_p95"], row["B_at_p95"] = round(d95, 4), round(r["B"]["recall_at_precision"]["0.95"], 4)
        row["B_sequence_at_p95"] = round(r["B_sequence"]["recall_at_precision"]["0.95"], 4)
        row["d_keeps_b"] = d95 >= r["B"]["recall_at_precision"]["0.95"]
        row["d_keeps_b_sequence"] = d95 >= r["B_sequence"]["recall_at_precision"]["0.95"]
        out[part] = row
    return out


def plot(res: dict[str, Any], path: Path) -> bool:
    """One panel per part: the precision-recall curves of every stage (False: no part ran)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = [p for p, r in res["parts"].items() if "skipped" not in r]
    if not parts:
        return False
    cols = 6
    rows = max(1, -(-len(parts) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.1 * cols, 2.9 * rows), squeeze=False,
                             sharex=True, sharey=True)
    for ax, part in zip(axes.flat, parts, strict=False):
        r = res["parts"][part]
        role = "validation" if part in G.PARTS["validation"] else "held out"
        for name in STAGES + DIAGNOSTICS:
            c = r[name]["curve"]
            style = {"C": ":", "A_as_B": ":", "B_sequence": "-.", "local_view_templates": "--",
                     "local_view": "--"}.get(name, "-")
            ax.plot(c["recall"], c["precision"], style, color=COLOURS[name], lw=1.8 if name == "C" else 1.2,
                    label=LABELS[name])
            if c["recall"]:  # recall@1: where the curve ends
                ax.plot(c["recall"][-1], c["precision"][-1], "o", color=COLOURS[name], ms=3)
        ax.set_title(f"{part} ({role})", fontsize=9)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(parts):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("recall")
    for ax in axes[:, 0]:
        ax.set_ylabel("precision")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    top = 1 - 0.9 / fig.get_figheight()
    fig.suptitle("What each stage recognises: precision-recall of each query's best match, of each decision "
                 "(a dot: recall@1)", y=1 - 0.1 / fig.get_figheight(), fontsize=11)
    fig.legend(handles, labels, loc="upper center", ncol=-(-len(handles) // 2), fontsize=9, frameon=False,
               bbox_to_anchor=(0.5, 1 - 0.3 / fig.get_figheight()))
    fig.tight_layout(rect=(0, 0, 1, top))
    fig.savefig(path, dpi=70)
    plt.close(fig)
    return True


def dump(res: dict[str, Any]) -> str:
    """JSON, one key a line but each list of numbers on one line."""
    text = json.dumps(res, indent=1)
    return re.sub(r"\[\s+([^\[\]{}\"]*?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default=",".join(G.PARTS["validation"] + G.PARTS["test"]))
    ap.add_argument("--out", default=str(RESULTS / "stages.json"))
    ap.add_argument("--plot", action="store_true", help="redraw the figure from --out and stop")
    args = ap.parse_args()
    out = Path(args.out)
    png = out.with_suffix(".png")
    if args.plot:
        plot(json.loads(out.read_text()), png)
        return
    t0 = time.perf_counter()
    res: dict[str, Any] = {"config": "default", "parts": {}}
    for part in args.parts.split(","):
        try:
            res["parts"][part] = run_part(part)
        except MissingData as exc:
            res["parts"][part] = {"skipped": str(exc)}
            print(f"{part}: skipped: {exc}", flush=True)
            continue
        r = res["parts"][part]
        print(part, {n: round(r[n]["recall_at_1"], 3) for n in STAGES + DIAGNOSTICS}, r["seconds"], flush=True)
    res["roles"] = {p: "validation" if p in G.PARTS["validation"] else "held out" if p in G.PARTS["test"] else None
                    for p in res["parts"]}
    res["summary"] = summary(res["parts"])
    res["b_below_a"] = [p for p, s in res["summary"].items() if s.get("b_keeps_a") is False]
    res["b_below_a_as_b"] = [p for p, s in res["summary"].items() if s.get("b_keeps_a_as_b") is False]
    res["d_below_b"] = [p for p, s in res["summary"].items() if s.get("d_keeps_b") is False]
    res["d_below_b_sequence"] = [p for p, s in res["summary"].items() if s.get("d_keeps_b_sequence") is False]
    res["seconds"] = round(time.perf_counter() - t0, 1)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(dump(res))
    drawn = plot(res, png)
    print(f"wrote {out}{f' and {png}' if drawn else ''} in {res['seconds']} s; B below A on {res['b_below_a']}")


if __name__ == "__main__":
    main()
