"""Loop closures decided from the run's own statistics, not from absolute thresholds.

For each frame, the candidates' similarity scores are mostly those of unrelated places: their mean
mu and standard deviation sd (the candidates within ``neighbourhood_m`` of the winner left out,
as views of the same place) say what an unrelated place scores in this run, with this camera,
now. The winner is a revisit when it stands out: z = (s - mu) / sd >= z_min, and it reaches at
least ``rho`` of the way from mu to the level of the view a moment ago (how alike two views of
one place are here, which rejects look-alikes that stand out but are far from it). A closure then
needs evidence over ``sequence_m`` of travel: the frames of that stretch matched consistent places
and their mean confidence is >= 0. Distances become times through the platform's typical speed,
times become frames through the stamps' measured interval; a place can come back no sooner than
one shortest loop at twice the typical speed. docs/mapping.md gives the reasoning and how the
constants were chosen.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .sequence import refs_consistent


class PlatformConfig(BaseModel):
    """What a user knows about the robot and its world: physical quantities, not thresholds."""

    model_config = ConfigDict(extra="forbid")

    #: the robot's typical speed while mapping
    speed_mps: float = Field(0.5, gt=0)
    #: the shortest route that brings the robot back to a place it has seen (one lap of the
    #: smallest loop; for a route driven once and then again, the route's length)
    shortest_loop_m: float = Field(10.0, gt=0)
    #: the size of the area (its longest extent)
    area_m: float = Field(50.0, gt=0)

    def min_revisit_s(self) -> float:
        """The earliest a place can come back: one shortest loop at twice the typical speed."""
        return self.shortest_loop_m / (2.0 * self.speed_mps)


class CalibrationConfig(BaseModel):
    """Parameters of the calibrated decision (``enabled: false``: the absolute thresholds)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False
    #: the winner stands this many standard deviations above the unrelated places' mean
    #: (chosen on validation parts with rho: bench/generalisation.py, docs/mapping.md)
    z_min: float = Field(3.5, ge=0)
    #: and reaches this fraction of the way from their mean to the level of the view a moment ago
    #: (1: as alike as two views a moment apart; 0.9: nine tenths of that excess over the mean)
    rho: float = Field(0.9, ge=0)
    #: candidates (outside the winner's neighbourhood) needed before the statistics are trusted
    min_candidates: int = Field(20, ge=3)
    #: travel over which consistent evidence is needed
    sequence_m: float = Field(0.6, ge=0)
    #: views closer than this (along the way) show the same place
    neighbourhood_m: float = Field(2.0, gt=0)


class Distinctness:
    """How far each frame's best match stood out from the unrelated places (its z), for one kind
    of representation, as a histogram of 0.1-wide bins from 0 to 20 (bounded memory over any run):
    what a run can say about how distinct its places were without ground truth."""

    BIN, TOP = 0.1, 20.0

    def __init__(self) -> None:
        self.counts = np.zeros(int(self.TOP / self.BIN) + 1, np.int64)

    def add(self, z: float) -> None:
        if math.isfinite(z):
            self.counts[int(min(max(z, 0.0), self.TOP) / self.BIN)] += 1

    def quantile(self, q: float) -> float | None:
        n = int(self.counts.sum())
        if not n:
            return None
        return round(float(np.searchsorted(np.cumsum(self.counts), q * n)) * self.BIN, 2)

    def report(self, z_min: float) -> dict[str, Any]:
        n = int(self.counts.sum())
        above = int(self.counts[int(min(z_min, self.TOP) / self.BIN):].sum())
        return {"frames": n, "median_z": self.quantile(0.5), "p90_z": self.quantile(0.9),
                "share_above_z_min": round(above / n, 4) if n else None}


@dataclass
class Assessment:
    """One frame's verdict on its best candidate: ``confidence`` >= 0 when it stands out."""

    best: int
    score: float
    z: float
    confidence: float
    second: int
    second_score: float
    mean: float
    sd: float


class RunCalibration:
    """The per-frame statistics, the consistency of the evidence and what the run settled on.

    ``assess`` judges one frame's candidates; ``accept`` records the frame's best candidate
    (its reference frame) and confidence and says whether the evidence over the last
    ``sequence_m`` of travel makes it a closure.
    """

    def __init__(self, config: CalibrationConfig, platform: PlatformConfig, max_step: float = 2.0,
                 slack: int = 4) -> None:
        self.config = config
        self.platform = platform
        self.max_step = max_step
        self.slack = slack
        self.history: deque[tuple[int, int, float]] = deque(maxlen=1)
        self.intervals: deque[float] = deque(maxlen=64)
        self.last_stamp: float | None = None
        #: what the run settled on, for its report
        self.ready_frame = -1
        self.frames_assessed = 0
        self.sum_mean = self.sum_sd = 0.0
        self.closures = 0
        self.first_closure_frame = -1
        #: templates made while a revisit's evidence accumulated, then found to be that place
        self.templates_merged = 0
        #: templates on probation: (frame, the caller's key for the template, the key of what its
        #: frame matched), kept for one stretch of evidence (:meth:`on_new_template`)
        self.pending: list[tuple[int, int, int]] = []
        #: how far each frame's best match stood out, per representation (:meth:`note_distinctness`)
        self.distinctness: dict[str, Distinctness] = {}
        #: the evidence the last :meth:`accept` decided on: the mean confidence over the stretch
        #: (>= 0 is a closure); -inf when it had no candidate or inconsistent references
        self.evidence = -math.inf

    # ---------------------------------------------------------------- time
    def on_stamp(self, stamp: float) -> None:
        """Measure the frame interval from the stamps (median of the last 64)."""
        if self.last_stamp is not None and stamp > self.last_stamp:
            self.intervals.append(stamp - self.last_stamp)
        self.last_stamp = stamp

    @property
    def frame_s(self) -> float:
        return float(np.median(self.intervals)) if self.intervals else 1.0

    def seconds(self, metres: float) -> float:
        return metres / self.platform.speed_mps

    @property
    def min_gap_s(self) -> float:
        return self.platform.min_revisit_s()

    @property
    def sequence_frames(self) -> int:
        """L: the frames before this one that must agree (0 when sequence_m is 0)."""
        if self.config.sequence_m <= 0:
            return 0
        return max(1, math.ceil(self.seconds(self.config.sequence_m) / self.frame_s - 1e-9))

    # ---------------------------------------------------------------- decisions
    def assess(self, scores: np.ndarray, times: np.ndarray, recent: float | None,
               best: int | None = None) -> Assessment | None:
        """``scores``: the candidates' similarities (higher: more alike); ``times``: their stamps;
        ``recent``: the similarity to the view a moment ago (None: unknown); ``best``: the winner
        when another ranking chose it (a re-ranking), else the highest score. None when too few
        candidates lie outside the winner's neighbourhood."""
        if scores.shape[0] == 0:
            return None
        if best is None:
            best = int(np.argmax(scores))
        far = np.abs(times - times[best]) > self.seconds(self.config.neighbourhood_m)
        rest = scores[far]
        if rest.shape[0] < self.config.min_candidates:
            return None
        mean, sd = float(rest.mean()), float(rest.std()) + 1e-9
        s = float(scores[best])
        z = (s - mean) / sd
        level = mean if recent is None else mean + self.config.rho * max(recent - mean, 0.0)
        confidence = min(z - self.config.z_min, (s - level) / sd)
        second = int(np.flatnonzero(far)[np.argmax(rest)])
        if self.ready_frame < 0:
            self.ready_frame = self.frames_assessed
        self.sum_mean += mean
        self.sum_sd += sd
        return Assessment(best, s, z, confidence, second, float(scores[second]), mean, sd)

    def accept(self, t: int, ref: int, confidence: float) -> bool:
        """Frame t's best candidate (``ref``: the first frame of the place it matched, i.e. of its
        template, so that equivalent visits of one place agree; -1 for none) with its confidence:
        a closure when the L frames before t had consistent references and the mean confidence
        of the L + 1 is >= 0 (that mean, or with L = 0 the frame's confidence, is kept as
        ``evidence``). Call once per frame, in frame order."""
        n = self.sequence_frames
        self.evidence = -math.inf
        if self.history.maxlen != max(n, 1):
            self.history = deque(self.history, maxlen=max(n, 1))
        ok = ref >= 0
        total = confidence  # the stretch's confidence, summed below
        if ok and n:
            ok = refs_consistent({f: m for f, m, _ in self.history}, t, ref, n, self.max_step, self.slack)
            if ok:
                conf = {f: c for f, _, c in self.history}
                for i in range(1, n + 1):
                    total += conf[t - i]
                self.evidence = total / (n + 1)
                ok = self.evidence >= 0
        elif ok:
            self.evidence = confidence
            ok = confidence >= 0
        self.history.append((t, ref, confidence if ref >= 0 else -math.inf))
        if ok:
            self.closures += 1
            if self.first_closure_frame < 0:
                self.first_closure_frame = t
        return ok

    def on_new_template(self, t: int, key: int, matched: int) -> None:
        """Frame t made a new template (``key``) while its best candidate was ``matched``: if a
        closure within the next L frames confirms the revisit, that template is the place it matched."""
        self.pending = [e for e in self.pending if e[0] >= t - self.sequence_frames]
        self.pending.append((t, key, matched))

    def confirmed(self, t: int) -> list[tuple[int, int]]:
        """At a closure accepted on frame t: (key, matched) of each template made within its stretch
        of evidence (the L frames before t), which the caller makes the place its frame matched."""
        out = [(k, m) for f, k, m in self.pending if f >= t - self.sequence_frames]
        self.pending = []
        self.templates_merged += len(out)
        return out

    def frame_done(self) -> None:
        self.frames_assessed += 1

    def note_distinctness(self, name: str, z: float) -> None:
        """One frame's best match under representation ``name`` stood ``z`` sd above the rest."""
        self.distinctness.setdefault(name, Distinctness()).add(z)

    def standing_out(self, scores: np.ndarray, times: np.ndarray) -> float:
        """z of the best of ``scores`` over the candidates outside its neighbourhood (NaN when too few)."""
        if scores.shape[0] == 0:
            return math.nan
        best = int(np.argmax(scores))
        rest = scores[np.abs(times - times[best]) > self.seconds(self.config.neighbourhood_m)]
        if rest.shape[0] < self.config.min_candidates:
            return math.nan
        return (float(scores[best]) - float(rest.mean())) / (float(rest.std()) + 1e-9)

    # ---------------------------------------------------------------- sessions
    def new_session(self) -> None:
        """A new session on a stored map: the evidence of the old stream (its last frames, the
        templates on probation, its last stamp) is no evidence for the new one; the measured frame
        interval and the statistics are kept, and the session's closures counted afresh."""
        self.history.clear()
        self.pending = []
        self.last_stamp = None
        self.closures, self.first_closure_frame = 0, -1

    def session_shift(self, last_old: float, first_new: float) -> float:
        """What to add to an old session's stamps (its last one ``last_old``) so that they lie one
        shortest loop (``min_gap_s``) and one frame before the new session's first stamp
        ``first_new``: the new session's stamps start afresh, the old places are candidates from
        its first frame on, and every stamp stays in order."""
        return first_new - self.min_gap_s - self.frame_s - last_old

    # ---------------------------------------------------------------- report and state
    def report(self) -> dict[str, Any]:
        """What this run settled on: the unrelated places' level and spread, the score a winner
        needed (mean + z_min sd, averaged over the frames), from which frame, and whether any
        revisit was seen."""
        n = self.frames_assessed - self.ready_frame if self.ready_frame >= 0 else 0
        out: dict[str, Any] = {"z_min": self.config.z_min, "rho": self.config.rho,
                               "min_revisit_s": round(self.min_gap_s, 3), "sequence_frames": self.sequence_frames,
                               "frame_s": round(self.frame_s, 4), "ready_from_frame": self.ready_frame,
                               "closures": self.closures, "first_closure_frame": self.first_closure_frame,
                               "templates_merged": self.templates_merged}
        if n > 0:
            mean, sd = self.sum_mean / n, self.sum_sd / n
            out.update({"unrelated_mean": round(mean, 3), "unrelated_sd": round(sd, 3),
                        "score_needed": round(mean + self.config.z_min * sd, 3)})
        out["revisit_seen"] = self.closures > 0
        if self.distinctness:
            out["distinctness"] = {k: d.report(self.config.z_min) for k, d in sorted(self.distinctness.items())}
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"history": [[t, m, c] for t, m, c in self.history], "intervals": list(self.intervals),
                "last_stamp": self.last_stamp, "pending": [list(e) for e in self.pending],
                "figures": [self.ready_frame, self.frames_assessed, self.sum_mean, self.sum_sd, self.closures,
                            self.first_closure_frame, self.templates_merged],
                "distinctness": {k: d.counts.copy() for k, d in self.distinctness.items()}}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        # the intervals first: the evidence kept (L frames) follows from the interval they measure
        self.intervals = deque((float(v) for v in st["intervals"]), maxlen=64)
        self.history = deque(((int(t), int(m), float(c)) for t, m, c in st["history"]),
                             maxlen=max(self.sequence_frames, 1))
        self.pending = [(int(f), int(k), int(m)) for f, k, m in st["pending"]]
        stamp = st["last_stamp"]
        self.last_stamp = None if stamp is None else float(stamp)
        fig = st["figures"]
        (self.ready_frame, self.frames_assessed, self.sum_mean, self.sum_sd, self.closures,
         self.first_closure_frame, self.templates_merged) = (int(fig[0]), int(fig[1]), float(fig[2]),
                                                             float(fig[3]), int(fig[4]), int(fig[5]), int(fig[6]))
        self.distinctness = {}
        for k, counts in st["distinctness"].items():
            self.distinctness[k] = Distinctness()
            self.distinctness[k].counts = np.asarray(counts, dtype=np.int64).copy()
