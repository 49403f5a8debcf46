"""A run's first frames: how B centres the frames it codes before its window holds W frames, and
what that costs the first return to the start -> studies/results/first_frames.json.

B subtracts the mean of the last ``projector.centre_window`` W frames (docs/mapping.md, "Keeping what
A sees"). Frame k < W - 1 of a run is centred by the mean of the k + 1 frames seen so far (frame 0
by itself: nothing is left), while a frame that comes back to it later is centred by the W frames
of its approach. On a route that returns to its start (a lap that ends where it began, the usual
first loop closure of a robot) the return's first frames are the ones B ranks wrong
(bench/stages.py: every query B loses to A on the sparse stand-ins).

Two measurements, nothing chosen:

* **Centring variants** (B's input, A's features centred, ranked by cosine as ``A_as_B`` in
  bench/stages.py): recall@1 over all queries and over those whose right place is among the first
  W - 1 frames. ``causal``: as shipped. ``hold``: the first W frames wait and are centred by their
  common mean. ``blur_prior``: the missing part of an early frame's window filled with A's features
  of the first frame blurred (sigma 5 % of its width), a prior for the scene's light without its
  detail. ``completed``: an early frame's missing part filled, at comparison, with the context of
  the frame it is compared with (k m_r + (W - k) m_q) / W: not a coding B can send (it differs per
  query), the bound of what a completion would give.
* **Through D on a lap that returns to its start** (the sparse stand-ins' first lap and the first
  ten frames of the second, no stamps, as the held-out lab frames): the returning frames D closes
  right, with B as shipped, with ``hold``, and with the early frames coded with the true context of
  the start, the mean of the lap's last W frames (``oracle``: what no causal B knows).

Parts: the validation parts of bench/generalisation.py that hold revisits of a run's first frames
(sparse stand-ins 1, 2; synthetic worlds 1, 3; Nordland 2; the perturbed stand-ins 9, 10; Gardens
Point's night and view pairs, ``a`` halves), A's features cached as bench/stages.py caches them.

Run: ``.venv/bin/python studies/first_frames.py`` (about 3 minutes with A's features cached).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import generalisation as G
import numpy as np

import neoslam_stream.algorithms.projector as projector
from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.config import load_config
from neoslam_stream.evaluation.recognition import best_matches, cosine

PARTS = ["sparse:1", "sparse:2", "synthetic:1", "synthetic:3", "nordland:2", "hard:9", "hard:10",
         "gardens:night:a", "gardens:view:a"]
RETURN_PARTS = ["sparse:1", "sparse:2"]
#: returning frames after the first lap that the lap-shaped run keeps
RETURN_FRAMES = 10
BLUR = 0.05


def filled(means: np.ndarray, prior: np.ndarray, w: int) -> np.ndarray:
    """The early frames' means with their missing W - k frames taken from ``prior``."""
    out = means.copy()
    for t in range(w - 1):
        out[t] = ((t + 1) * means[t] + (w - t - 1) * prior) / w
    return out


def recall(scores: np.ndarray, allowed: np.ndarray, right: np.ndarray, rows: np.ndarray) -> float:
    """recall@1 over ``rows``: how often the best allowed match is a right one."""
    best, _ = best_matches(scores, allowed)
    ok = (best >= 0) & right[np.arange(len(right)), np.maximum(best, 0)]
    return round(float(ok[rows].mean()), 4) if rows.any() else float("nan")


def centring_variants(part: str) -> dict[str, Any]:
    import cv2

    stream = G.part_stream(part)
    cfg = load_config("default", {"platform": stream.platform})
    fc, w = cfg.front_end().features, cfg.front_end().projector.centre_window
    x = np.asarray(stream.features(fc.photometric, fc.input_size), np.float64)
    q, c, allowed, right = stream.recognition_truth()
    allowed, right = allowed.astype(bool), right.astype(bool)
    has = right.any(1)
    early = np.array([r.any() and c[r].min() < w - 1 for r in right])
    fe = FrontEnd(cfg.front_end())
    means = x - fe.projector.centre(x)  # B's running mean after each frame, as B keeps it
    hold = means.copy()
    hold[:w] = x[:w].mean(0)
    img = next(iter(stream.frames()))
    prior = np.asarray(fe.features([cv2.GaussianBlur(img, (0, 0), BLUR * img.shape[1])]), np.float64)[0]
    ix = np.ix_(q, c)
    scores = {"causal": cosine(x - means)[ix], "hold": cosine(x - hold)[ix],
              "blur_prior": cosine(x - filled(means, prior, w))[ix]}
    done = scores["causal"].copy()
    for j in np.flatnonzero(c < w - 1):
        k = c[j] + 1
        ref = x[c[j]] - (k * means[c[j]] + (w - k) * means[q]) / w  # one row per query
        qv = x[q] - means[q]
        done[:, j] = (ref * qv).sum(1) / (np.linalg.norm(ref, axis=1) * np.linalg.norm(qv, axis=1) + 1e-12)
    scores["completed"] = done
    out = {"queries": int(has.sum()), "early_queries": int(early.sum())}
    for name, s in scores.items():
        out[name] = {"recall_at_1": recall(s, allowed, right, has), "early_recall_at_1": recall(s, allowed, right, early)}
    return out


def returning(part: str, mode: str) -> dict[str, Any]:
    """D's right closures on the returning frames of a lap-shaped run (module docstring)."""
    stream = G.part_stream(part)
    cfg = load_config("default", {"platform": stream.platform})
    fe = FrontEnd(cfg.front_end())
    fc, w = fe.config.features, fe.config.projector.centre_window
    feats = np.asarray(stream.features(fc.photometric, fc.input_size))
    q, c, allowed, right = stream.recognition_truth()
    first_return = int(q[right.astype(bool).any(1)].min())
    n = first_return + RETURN_FRAMES
    context = {"hold": feats[:w].astype(np.float64).mean(0),
               "oracle": feats[first_return - w:first_return].astype(np.float64).mean(0)}.get(mode)
    plain = projector.RunningCentre.__call__

    def early(self: Any, row: Any) -> Any:  # the early frames centred with ``context``
        out = plain(self, row)
        if context is None or self.n_seen > w - 1:
            return out
        k = self.n_seen
        mean = self.mean.cpu().numpy() if hasattr(self.mean, "cpu") else np.asarray(self.mean)
        m = context if mode == "hold" else (k * mean + (w - k) * context) / w
        if hasattr(row, "cpu"):  # the torch path: the row lives on the device
            import torch

            return row - torch.as_tensor(m, dtype=row.dtype, device=row.device)
        return row - m

    projector.RunningCentre.__call__ = early
    try:
        codes = [cd for k in range(0, n, 8) for cd in fe.codes(feats[k:min(k + 8, n)])]
    finally:
        projector.RunningCentre.__call__ = plain
    out = [fe.template_of(fe.winner_cells(cd), s) for cd, s in zip(codes, stream.stamps[:n], strict=True)]
    qpos = {int(f): i for i, f in enumerate(q)}
    cpos = {int(f): j for j, f in enumerate(c)}
    closed = [f for f, m in G.matched_frames(out, fe.spatial_view.interval_start)
              if f in qpos and m in cpos and right[qpos[f], cpos[m]]]
    return {"returning_frames": RETURN_FRAMES, "closed_right": len(closed), "closed_frames": closed,
            "first_return_frame": first_return}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(_paths.RESULTS / "first_frames.json"))
    args = ap.parse_args()
    res: dict[str, Any] = {"centring": {}, "returning": {}}
    for part in PARTS:
        res["centring"][part] = centring_variants(part)
        print(part, json.dumps(res["centring"][part]), flush=True)
    for part in RETURN_PARTS:
        res["returning"][part] = {mode: returning(part, mode) for mode in ("causal", "hold", "oracle")}
        print(part, json.dumps({m: r["closed_right"] for m, r in res["returning"][part].items()}), flush=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
