"""Place recognition of a frame's representation: best matches, the precision-recall curve, its
area and the recall at a precision, defined once for every stage (bench/stages.py; docs/mapping.md,
"Reading bench/stages.py").

Each query frame has candidate frames it may match (``allowed``), and some of them are right
(``right``); a query with a right candidate is a *positive*. Its best match is the allowed
candidate of highest score, kept with that score. Sweeping a threshold down over the scores accepts
the queries whose score reaches it: precision = right accepted / accepted, recall = right accepted /
positives. A decision (D's closures, the local view's) is the same with one match per decided query
and no score for the others, which are never accepted: its curve ends at the decision's recall.
``recall_at_1`` is the curve's last recall (every query with a score accepted).

Scores: higher is more alike (negate an error). Representations: :func:`causal_centred_cosine`
(A's features, the run's mean so far removed), :func:`cosine` (features centred by the caller) and
:func:`overlaps` (|S_i & S_j| of index sets: B's bits, C's winner cells). :func:`sequence_curve`
gives a ranking the evidence D's decision takes: a stretch of consistent best matches.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..algorithms.sequence import refs_consistent

PRECISIONS = (0.9, 0.95, 1.0)


def causal_centred_cosine(features: np.ndarray) -> np.ndarray:
    """(n, n): row q holds cos(f_r - mu_q, f_q - mu_q) for every r, mu_q the mean of f_0 .. f_q
    (what was seen up to the query). From the Gram matrix G = F F^T and P = F M^T (M: the running
    means): (f_q - mu)·(f_r - mu) = G_qr - P_rq - P_qq + |mu|^2, without centring n times."""
    f = np.asarray(features, dtype=np.float64)
    n = f.shape[0]
    mu = np.cumsum(f, axis=0) / np.arange(1, n + 1)[:, None]
    g = f @ f.T
    p = f @ mu.T  # p[r, q] = f_r · mu_q
    m2 = np.einsum("ij,ij->i", mu, mu)
    pqq = np.diagonal(p)
    dots = g - p.T - pqq[:, None] + m2[:, None]
    norm_q = np.sqrt(np.maximum(np.diagonal(g) - 2 * pqq + m2, 0.0))
    norm_r = np.sqrt(np.maximum(np.diagonal(g)[None, :] - 2 * p.T + m2[:, None], 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = dots / (norm_q[:, None] * norm_r)
    return np.where(np.isfinite(cos), cos, 0.0)


def cosine(features: np.ndarray) -> np.ndarray:
    """(n, n) cosine similarity of the rows as given (a zero row: 0)."""
    f = np.asarray(features, dtype=np.float64)
    norm = np.linalg.norm(f, axis=1)
    f = f / np.where(norm > 0, norm, 1.0)[:, None]
    return f @ f.T


def overlaps(sets: Sequence[np.ndarray]) -> np.ndarray:
    """(n, n) int64: |S_i & S_j| of index sets (B's on-bits, C's winner cells), as one product of
    0/1 matrices over the indices that occur at all."""
    if not len(sets):
        return np.zeros((0, 0), dtype=np.int64)
    rows = np.repeat(np.arange(len(sets)), [len(np.unique(s)) for s in sets])
    used, cols = np.unique(np.concatenate([np.unique(s) for s in sets]), return_inverse=True)
    m = np.zeros((len(sets), len(used)), dtype=np.float32)  # counts below 2**24 are exact
    m[rows, cols] = 1.0
    return np.rint(m @ m.T).astype(np.int64)


def best_matches(scores: np.ndarray, allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each row's allowed column of highest score (the first on ties) and that score; -1 and NaN
    for a row with no allowed column."""
    s = np.asarray(scores, dtype=np.float64)
    ok = np.ones(s.shape, bool) if allowed is None else np.asarray(allowed, bool)
    masked = np.where(ok, s, -np.inf)
    idx = np.argmax(masked, axis=1) if s.shape[1] else np.zeros(s.shape[0], np.int64)
    has = ok.any(axis=1)
    best = np.where(has, idx, -1)
    score = np.where(has, masked[np.arange(s.shape[0]), np.maximum(idx, 0)] if s.shape[1] else np.nan, np.nan)
    return best, score


@dataclass
class PRCurve:
    """One point per distinct score, from the highest: accepting the queries whose score reaches
    ``threshold``."""

    threshold: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    positives: int

    def area(self) -> float:
        """Sum over the points of (recall gained) x precision: the step-wise area under the curve
        (average precision), 0 with no point."""
        gained = np.diff(np.concatenate([[0.0], self.recall]))
        return float(np.sum(gained * self.precision))

    def recall_at(self, precision: float) -> float:
        """The highest recall of a point whose precision is at least ``precision``; 0 when none."""
        ok = self.precision >= precision - 1e-12
        return float(self.recall[ok].max()) if ok.any() else 0.0

    @property
    def final_recall(self) -> float:
        """The recall with every scored query accepted (recall@1 of a best match, a decision's recall)."""
        return float(self.recall[-1]) if self.recall.size else 0.0


def pr_curve(scores: np.ndarray, right: np.ndarray, positives: int) -> PRCurve:
    """``scores`` per query (NaN: never accepted), ``right``: whether its match is right,
    ``positives``: the queries that have a right candidate. Equal scores are accepted together."""
    s = np.asarray(scores, dtype=np.float64)
    r = np.asarray(right, bool)
    keep = ~np.isnan(s)
    s, r = s[keep], r[keep]
    order = np.argsort(-s, kind="stable")
    s, r = s[order], r[order]
    last = np.flatnonzero(np.append(s[1:] != s[:-1], True)) if s.size else np.zeros(0, np.int64)
    accepted = last + 1
    hits = np.cumsum(r)[last] if s.size else np.zeros(0)
    return PRCurve(s[last], hits / accepted, hits / positives if positives else np.zeros(len(last)), int(positives))


def downsample(curve: PRCurve, points: int = 50) -> dict[str, list[float]]:
    """At most ``points`` of the curve (the first and the last kept), as lists for a JSON file."""
    n = curve.recall.size
    idx = np.unique(np.linspace(0, n - 1, min(points, n)).round().astype(int)) if n else np.zeros(0, int)
    return {"threshold": [round(float(v), 5) if np.isfinite(v) else None for v in curve.threshold[idx]],
            "precision": [round(float(v), 4) for v in curve.precision[idx]],
            "recall": [round(float(v), 4) for v in curve.recall[idx]]}


def figures(curve: PRCurve, precisions: Sequence[float] = PRECISIONS, points: int = 50) -> dict[str, Any]:
    """recall_at_1, pr_area, recall_at_precision {p: recall} and the curve (at most ``points``)."""
    return {"recall_at_1": curve.final_recall, "pr_area": curve.area(),
            "recall_at_precision": {str(p): curve.recall_at(p) for p in precisions},
            "positives": curve.positives, "curve": downsample(curve, points)}


def shortlisted(coarse: np.ndarray, fine: np.ndarray, allowed: np.ndarray, k: int) -> np.ndarray:
    """Two-stage retrieval: of each query's allowed candidates, the ``k`` best by ``coarse`` (ties:
    the lower column) keep their ``fine`` score, every other candidate -inf (never the best)."""
    c = np.where(np.asarray(allowed, bool), np.asarray(coarse, dtype=np.float64), -np.inf)
    top = np.argsort(-c, axis=1, kind="stable")[:, :k]
    rows = np.arange(c.shape[0])[:, None]
    out = np.full(c.shape, -np.inf)
    keep = np.isfinite(c[rows, top])
    out[rows, top] = np.where(keep, np.asarray(fine, dtype=np.float64)[rows, top], -np.inf)
    return out


def ranking_curve(scores: np.ndarray, allowed: np.ndarray, right: np.ndarray) -> PRCurve:
    """The curve of each query's best match: ``scores``, ``allowed``, ``right`` are (queries,
    candidates)."""
    best, score = best_matches(scores, allowed)
    rows = np.arange(len(best))
    hit = np.where(best >= 0, np.asarray(right, bool)[rows, np.maximum(best, 0)], False)
    return pr_curve(score, hit, int(np.asarray(right, bool).any(axis=1).sum()))


def decision_curve(decided: np.ndarray, matched: np.ndarray, scores: np.ndarray, right: np.ndarray) -> PRCurve:
    """The curve of a decision: per query whether it decided a match, the candidate column it
    matched (-1: a frame that is no candidate, never right) and the score it decided on; ``right``
    (queries, candidates)."""
    d = np.asarray(decided, bool)
    m = np.asarray(matched)
    r = np.asarray(right, bool)
    hit = d & (m >= 0) & r[np.arange(len(m)), np.maximum(m, 0)]
    s = np.where(d, np.asarray(scores, dtype=np.float64), np.nan)
    return pr_curve(s, hit, int(r.any(axis=1).sum()))


def sequence_curve(scores: np.ndarray, allowed: np.ndarray, right: np.ndarray, queries: np.ndarray,
                   candidates: np.ndarray, length: int, max_step: float, slack: int) -> PRCurve:
    """A ranking given the evidence D's decision takes (algorithms/calibration.py ``accept``): a
    query is scored only when the ``length`` frames before it were queries whose best matches lie
    within i * ``max_step`` + ``slack`` of its own, i frames back
    (:func:`~neoslam_stream.algorithms.sequence.refs_consistent`, on candidate frames), by the mean
    of the ``length`` + 1 best scores; any other query is never accepted. ``queries``, ``candidates``: the frame numbers of the rows and columns. With
    ``length`` 0 it is :func:`ranking_curve`."""
    best, score = best_matches(scores, allowed)
    q = np.asarray(queries, dtype=np.int64)
    c = np.asarray(candidates, dtype=np.int64)
    refs = {int(f): (int(c[b]) if b >= 0 else -1) for f, b in zip(q, best, strict=True)}
    by_frame = {int(f): s for f, s in zip(q, score, strict=True)}
    evidence = np.full(len(q), np.nan)
    for i, f in enumerate(map(int, q)):
        if best[i] < 0 or not refs_consistent(refs, f, refs[f], length, max_step, slack):
            continue
        evidence[i] = float(np.mean([by_frame[f - k] for k in range(length + 1)]))
    r = np.asarray(right, bool)
    hit = (best >= 0) & r[np.arange(len(best)), np.maximum(best, 0)]
    return pr_curve(evidence, hit, int(r.any(axis=1).sum()))
