"""Stage D: spatial-view cells, intervals of similar SDRs and loop closure onto older intervals.

The paper's rule, per winner-cell SDR y_t: the current interval [start, end] grows by y_t (end = t,
Y_curr |= y_t) when alpha(t) = |Y_curr & y_t| >= theta_alpha and end - start < theta_rho, else a
new interval [t, t] opens (so an interval covers at most theta_rho + 1 frames). The intervals
k < K - omega (omega = ``exclude_recent_intervals``, the current one included) with
s_k = |Y_k & y_t| > theta_sigma are candidates; the best k* (lowest index on ties) is a loop
closure onto k*'s template; otherwise a new interval gets a new template id (consecutive from 0)
and an extended one keeps the current template. Optional acceptance rules, off in the paper's
profile: ``sequence`` (algorithms/sequence.py), ``theta_margin`` over the runner-up and
``union_normalised`` scores, or the calibrated decision (algorithms/calibration.py), under which the
templates that a revisit's first, refused frames made become the place that the accepted closure
confirms (``_confirm_duplicates``). Unlike the ROS 2 NeoSLAM, interval k's template is its own and the
first frame opens interval 0 like any other. The scores come from
:class:`~.interval_index.IntervalIndex`, which receives an interval when it closes (no candidate is
younger than omega intervals); ``index_revisits: false`` keeps out an interval whose every frame
closed onto an older place, so a route driven again and again keeps a bounded index;
``merge_revisits`` also merges a revisit's first, refused frames into the place they matched and
forgets every interval that is no place (revisit_merge.py), so what D keeps grows with the places.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pyroaring import BitMap

from ._config import make_config
from .calibration import CalibrationConfig, PlatformConfig, RunCalibration
from .descriptors import IntervalDescriptors
from .errors import InvalidInput
from .interval_index import IntervalIndex
from .revisit_merge import DROP, EXPIRE, RevisitMerge, Stored
from .sequence import SequenceConfig, SequenceFilter


class SpatialViewConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    theta_alpha: int = Field(384, ge=0)
    theta_rho: int = Field(3, ge=0)
    theta_sigma: int = Field(470, ge=0)
    exclude_recent_intervals: int = Field(3, ge=0)
    sdr_size: int = Field(65536, ge=1)
    #: accept a closure only after a run of consistent candidates (algorithms.sequence; the
    #: default ``length: 0`` keeps the paper's rule)
    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    #: candidates are ranked and thresholded by the normalised score s_k |y_t| / max(|Y_k|, |y_t|),
    #: i.e. theta_sigma scaled to the union's size (a union of several frames overlaps every SDR
    #: more: docs/mapping.md). Every candidate is scored then (the exhaustive count, not the
    #: bounded search). False: the paper's s_k > theta_sigma
    union_normalised: bool = False
    #: a closure also needs a margin over the runner-up, score(k*) - score(k2) >=
    #: theta_margin (the scores are the normalised ones when ``union_normalised``): a place that
    #: looks like many others is refused. 0: off (the paper's rule)
    theta_margin: float = Field(0.0, ge=0)
    #: closures decided from the run's own statistics instead of theta_sigma and theta_margin
    #: (algorithms/calibration.py): ranked by the union-normalised score, candidates only from
    #: places seen a shortest loop ago, evidence over a stretch of travel. Off: the paper's rule
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    #: False: an interval whose every frame closed onto an older place does not enter the index.
    #: That place is there already (with the one-template-per-place merge, under the same
    #: template), so a patrol's index, D's time per frame and its memory grow with the new places
    #: only, not with every frame. Needs ``calibration.enabled`` (whose statistics then leave the
    #: revisits out too). True: every interval is a candidate (the paper's rule)
    index_revisits: bool = True
    #: k > 0: the calibrated decision's k best candidates by their cells are re-ranked by the
    #: frames' descriptors (B's centred features, ``projector.descriptor``; algorithms/descriptors.py)
    #: and the most alike wins; its confidence is judged as before. 0: the cells decide (the paper)
    rerank: int = Field(0, ge=0)
    #: with ``rerank``: 0 judges the winner by the cells' scores; n > 0 judges it by the
    #: descriptors' cosines, the unrelated places' level and spread measured on n candidates
    #: spread evenly over the rest
    rerank_sample: int = Field(0, ge=0)
    #: True: a new interval whose frame stands out on its own keeps the current template while the
    #: stretch's evidence accumulates, the intervals a closure confirms merge into the place they
    #: matched (never indexed), and intervals that are no place are forgotten (revisit_merge.py):
    #: what D keeps per place stops growing once the place is known. Needs ``index_revisits:
    #: false``. False: every refused interval makes a template and every interval is kept
    merge_revisits: bool = False

    @model_validator(mode="after")
    def _pruning_needs_calibration(self) -> SpatialViewConfig:
        if not self.index_revisits and not self.calibration.enabled:
            raise ValueError("index_revisits: false needs calibration.enabled: true (the thresholded "
                             "rules count every interval)")
        if self.merge_revisits and self.index_revisits:
            raise ValueError("merge_revisits needs index_revisits: false (a merged revisit stays out of the index)")
        if self.rerank and not self.calibration.enabled:
            raise ValueError("rerank needs calibration.enabled: true (it re-ranks the calibrated decision's candidates)")
        return self

    @field_validator("exclude_recent_intervals")
    @classmethod
    def _omega_excludes_the_current_interval(cls, v: int) -> int:
        # omega = 0 makes the current interval, which already holds y_t, a candidate: every frame
        # would match itself (a "loop closure" onto the template -1 it has not got yet at frame 0)
        if v < 1:
            raise ValueError(f"exclude_recent_intervals must be >= 1 (got {v}): the current interval "
                             "already holds y_t, so with 0 every frame matches its own interval")
        return v


#: the parameters a state records (its intervals and templates were made with them), in order
STATE_PARAMS = ("theta_alpha", "theta_rho", "theta_sigma", "exclude_recent_intervals", "sdr_size")


class SpatialViewCells:
    """SDR -> (template id, is_loop_closure, best interval, best score, runner-up); the module
    docstring gives the rule. The search settings (``exhaustive``, ``sliced``, ``dense_min``) and
    figures (``last_path``, ``last_search``, ``merges``) are the index's: ``cells.index``."""

    def __init__(self, config: SpatialViewConfig | None = None, platform: PlatformConfig | None = None,
                 **overrides: Any) -> None:
        self.config = make_config(SpatialViewConfig, config, overrides)
        self.platform = platform or PlatformConfig()
        self.index = IntervalIndex(self.config.sdr_size)
        #: merge_revisits: what happens to a revisit's intervals (None: every interval is kept)
        self.merge = RevisitMerge() if self.config.merge_revisits else None
        # per interval k: its union Y_k, first and last frame, template and first stamp (a Stored
        # holding the places and the recent intervals only, with merge_revisits)
        self.unions: list[BitMap] = self._store()
        self.interval_start: list[int] = self._store()
        self.interval_end: list[int] = self._store()
        self.interval_template: list[int] = self._store()
        self.interval_stamps: list[float] = self._store()
        # the intervals in the index, in order (``indexed``; the index numbers them 0, 1, ...: its
        # slots) and their first stamps, in stores grown by doubling so that a frame reads them as views
        self._indexed = np.zeros(1024, dtype=np.int64)
        self._place_stamps = np.zeros(1024, dtype=np.float64)
        self._n_indexed = 0
        #: whether every frame of the newest interval closed onto an older place
        self._all_closed = False
        #: merge_revisits with rerank: the descriptor row of each closed interval waiting to be indexed
        self._rows: dict[int, np.ndarray | None] = {}
        #: the last frame's confidence in its best candidate (-inf: none)
        self._confidence = -np.inf
        #: the frame each template was made on (the place's first visit): the sequence evidence of
        #: the calibrated decision is judged by it, not by the matched interval's own start
        self.template_start: list[int] = []
        self.n_templates = 0
        self.current_template = -1
        self.t = 0
        #: the runner-up of the last frame (interval, score): -1, 0 when there is none
        self.runner_up = (-1, 0)
        self.sequence = SequenceFilter(self.config.sequence)
        seq = self.config.sequence
        self.calibration = RunCalibration(self.config.calibration, self.platform, seq.max_step, seq.slack)
        #: the indexed intervals' descriptors (``rerank``)
        self.descriptors = IntervalDescriptors()
        #: set by :meth:`new_session` until the session's first frame: the old sessions' last stamp
        self._old_last_stamp: float | None = None

    def _store(self) -> Any:
        return Stored() if self.merge is not None else []

    def _kept(self) -> Any:
        """The numbers k of the intervals whose stores D still holds (in order)."""
        return self.interval_stamps.keys() if self.merge is not None else range(self.n_intervals)

    @property
    def n_intervals(self) -> int:
        """The intervals made so far (with merge_revisits most are forgotten: ``n_stored``)."""
        return len(self.unions)

    @property
    def n_stored(self) -> int:
        """The intervals whose union and figures D keeps."""
        return self.unions.stored() if self.merge is not None else len(self.unions)

    @property
    def indexed(self) -> np.ndarray:
        """The intervals in the index, in order: slot i of the index is interval ``indexed[i]``."""
        return self._indexed[:self._n_indexed]

    @property
    def place_stamps(self) -> np.ndarray:
        """The first stamp of each interval in the index, by slot (seconds; the frame number when
        frames come without stamps)."""
        return self._place_stamps[:self._n_indexed]

    def _validate(self, sdr: np.ndarray) -> np.ndarray:
        a = np.asarray(sdr)
        if a.ndim != 1:
            raise InvalidInput(f"SDR must be a 1-D array of cell indices, got shape {a.shape}")
        if a.size and (a.min() < 0 or a.max() >= self.config.sdr_size):
            raise InvalidInput(f"SDR indices must lie in [0, {self.config.sdr_size})")
        return np.unique(a.astype(np.int64)).astype(np.int32)

    def compute(self, sdr: np.ndarray, stamp: float | None = None,
                descriptor: np.ndarray | None = None) -> dict[str, Any]:
        """Process y_t (``stamp``: its time in seconds, default the frame number; ``descriptor``:
        B's int8 descriptor of the frame, for ``rerank``); returns template id, loop-closure flag,
        best interval and score, and the runner-up (``second_interval``, ``second_score``: the best
        candidate other than k*, -1 and 0 when there is none), from which a closure's margin
        best_score - second_score follows."""
        cfg = self.config
        y = self._validate(sdr)
        stamp = float(self.t if stamp is None else stamp)
        session_start = self._old_last_stamp is not None
        if session_start:  # a new session's first frame: the old stamps move back
            shift = self.calibration.session_shift(self._old_last_stamp, stamp)
            for k in self._kept():
                self.interval_stamps[k] += shift
            self._place_stamps[:self._n_indexed] += shift
            self._old_last_stamp = None
        y_bm = BitMap(y)
        new_interval = False
        if not self.unions or session_start:  # a new session's first view continues no old interval
            new_interval = True
        else:
            cur = self.n_intervals - 1
            alpha = self.unions[cur].intersection_cardinality(y_bm)
            duration = self.interval_end[cur] - self.interval_start[cur]
            if alpha >= cfg.theta_alpha and duration < cfg.theta_rho:
                self.unions[cur] |= y_bm
                self.interval_end[cur] = self.t
            else:
                new_interval = True
        if new_interval:
            k = self.n_intervals
            if k:
                self._close_interval(k - 1)
            self.unions.append(y_bm)
            self.descriptors.open_interval()
            self.interval_start.append(self.t)
            self.interval_stamps.append(stamp)
            self.interval_end.append(self.t)
            self.interval_template.append(-1)
        if cfg.rerank:
            self.descriptors.add_frame(descriptor)
            if cfg.rerank_sample and descriptor is not None:
                cal = self.calibration
                self.descriptors.note_view(stamp, descriptor, cal.seconds(cal.config.neighbourhood_m))
        if cfg.calibration.enabled:
            loop, best, best_score, second, second_score = self._calibrated(y, y_bm, stamp, descriptor)
        else:
            loop, best, best_score, second, second_score = self._thresholded(y)
        held = False
        if loop:
            template = self.interval_template[best]
        elif new_interval and self.merge is not None and self.current_template >= 0 and \
                self.merge.may_hold(self.t, self._confidence, self.calibration.sequence_frames):
            template, held = self.current_template, True  # the stretch may yet confirm a known place
        elif new_interval:
            template = self._new_template(self.t)
        else:
            template = self.current_template
        if self.merge is not None and (loop or (new_interval and not held)):
            self.merge.end_hold()
        if new_interval:
            self.interval_template[-1] = template
        self._all_closed = bool(loop) and (new_interval or self._all_closed)
        if cfg.calibration.enabled:
            self._confirm_duplicates(loop, new_interval and not loop, best, held)
        self.current_template = template
        if self.merge is not None:
            self._settle(self.t)
        self.t += 1
        out = {"id": template, "is_loop_closure": bool(loop), "best_interval": best if loop else -1,
               "best_score": best_score, "relative_rad": 0.0, "interval": self.n_intervals - 1,
               "second_interval": second, "second_score": second_score}
        if loop:  # what the decision was sure of (records.Template.confidence)
            out["confidence"] = float(self.calibration.evidence if cfg.calibration.enabled
                                      else best_score - cfg.theta_sigma)
        return out

    def _new_template(self, t: int) -> int:
        template = self.n_templates
        self.n_templates += 1
        self.template_start.append(t)
        return template

    def _close_interval(self, k: int) -> None:
        """Interval k is complete (k + 1 opens): into the index as its next slot, unless revisits
        stay out and every frame of k closed onto an older place. Such an interval's union is then
        needed only as the view a moment ago for k + 1's frames, and is freed when k + 1 closes.
        With merge_revisits it waits for its stretch's verdict instead (:meth:`_settle`)."""
        if self.merge is not None:
            if self.config.rerank:
                self._rows[k] = self.descriptors.open_row()
            self.merge.close(k, self._all_closed)
            return
        if k and not self.config.index_revisits and (not self._n_indexed or self.indexed[-1] != k - 1):
            self.unions[k - 1] = BitMap()  # interval k - 1 stayed out: nothing reads it any more
        if not self.config.index_revisits and self._all_closed:
            return
        self._index_interval(k)

    def _settle(self, t: int, force: Any = None) -> None:
        """merge_revisits: the closed intervals no closure can confirm any more (or that ``force``
        says are candidates now) into the index, or dropped when they are a known place (a revisit,
        merged, or held); the dropped ones' stores are forgotten once they are no longer the view a
        moment ago (the newest but one)."""
        assert self.merge is not None
        for k, decision in self.merge.settle(t, self.calibration.sequence_frames, force):
            if decision == EXPIRE and not self.merge.second_view(self.interval_template[k]):
                decision = DROP
            if decision == DROP:
                self._rows.pop(k, None)
                self.merge.dropped.append(k)
            else:
                self._index_interval(k)
        dropped = self.merge.dropped
        while dropped and dropped[0] < self.n_intervals - 2:
            k = dropped.popleft()
            for store in (self.unions, self.interval_start, self.interval_end, self.interval_template,
                          self.interval_stamps):
                store.forget(k)

    def _index_interval(self, k: int) -> None:
        """Interval k's union into the index as its next slot."""
        slot = self._n_indexed
        cells = np.asarray(self.unions[k].to_array(), dtype=np.int32)
        self.index.post(cells, slot)
        self.index.store_union(slot, cells.astype(np.int64))
        if self.config.rerank:
            if self.merge is not None:
                self.descriptors.close_interval(slot, self._rows.pop(k, None), given=True)
            else:
                self.descriptors.close_interval(slot)
        self._indexed = _put(self._indexed, slot, k)
        self._place_stamps = _put(self._place_stamps, slot, self.interval_stamps[k])
        self._n_indexed += 1

    def _thresholded(self, y: np.ndarray) -> tuple[bool, int, Any, int, Any]:
        """The paper's rule (s > theta_sigma) and the optional margin and sequence rules."""
        cfg = self.config
        limit = self.n_intervals - cfg.exclude_recent_intervals
        min_gap = cfg.sequence.min_gap_frames
        if min_gap:  # only intervals opened at least min_gap frames ago (sequence.py)
            limit = min(limit, bisect_right(self.interval_start, self.t - min_gap))
        best, best_score = -1, 0
        second, second_score = -1, 0
        if limit > 0:
            if cfg.union_normalised:
                best, best_score, second, second_score = self.index.top2_normalised(y, limit)
            else:
                best, best_score, second, second_score = self.index.top2(y, limit)
        self.runner_up = (second, second_score)
        loop = best >= 0 and best_score > cfg.theta_sigma
        if loop and cfg.theta_margin:  # the runner-up's score is 0 when there is none
            loop = best_score - second_score >= cfg.theta_margin
        if self.sequence.enabled:  # a candidate is a closure only within a consistent sequence
            loop = self.sequence.check(self.t, self.interval_start[best] if loop else -1)
        return loop, best, best_score, second, second_score

    def _calibrated(self, y: np.ndarray, y_bm: BitMap, stamp: float,
                    descriptor: np.ndarray | None = None) -> tuple[bool, int, float, int, float]:
        """The calibrated decision (algorithms/calibration.py) on the union-normalised scores of
        the intervals opened at least a shortest loop ago (and outside the omega newest); with
        ``rerank``, the winner is the most alike by descriptor among the best ``rerank`` by score."""
        cal = self.calibration
        cal.on_stamp(stamp)
        k_all = self.n_intervals
        limit = k_all - self.config.exclude_recent_intervals
        cutoff = stamp - cal.min_gap_s
        if self.merge is not None:  # an interval that is a candidate now is decided first
            self._settle(self.t, lambda k: k < limit and self.interval_stamps[k] <= cutoff)
        # the indexed intervals k < limit opened a shortest loop ago (stamps grow with k)
        slots = min(int(np.searchsorted(self.indexed, limit)),
                    int(np.searchsorted(self.place_stamps, cutoff, side="right"))) if limit > 0 else 0
        best, best_score, second, second_score = -1, 0.0, -1, 0.0
        a = None
        if slots > 0:
            which = self.indexed[:slots]
            times = self.place_stamps[:slots]
            scores = self.index.normalised_scores(y, slots)
            cal.note_distinctness("cells", cal.standing_out(scores, times))
            if self.config.rerank_sample and descriptor is not None and self.descriptors.n:
                a, which = self._assess_descriptors(scores, which, times, descriptor, stamp)
                if a is not None:
                    cal.note_distinctness("descriptors", a.z)
            else:
                a = cal.assess(scores, times, self._recent_score(y_bm) if k_all >= 2 else None,
                               self._reranked(scores, descriptor))
            if a is not None:
                best, best_score = int(which[a.best]), a.score
                second, second_score = int(which[a.second]), a.second_score
        # the reference is the place, the first frame of the winner's template: a place visited
        # twice before has near-identical intervals from both visits, and the winner may flip
        # between them from frame to frame; their template is the same once the second closed
        place = self.template_start[self.interval_template[best]] if a is not None else -1
        self._confidence = a.confidence if a is not None else -np.inf
        loop = cal.accept(self.t, place, self._confidence)
        cal.frame_done()
        self.runner_up = (second, second_score)
        return loop, best, best_score, second, second_score

    def _reranked(self, scores: np.ndarray, descriptor: np.ndarray | None) -> int | None:
        """With ``rerank`` k: the candidate the cells and the descriptor together vote best of the
        k best by score (:meth:`IntervalDescriptors.vote`). None when off or no descriptor can tell."""
        k = self.config.rerank
        if not k or descriptor is None or scores.shape[0] == 0:
            return None
        return self.descriptors.vote(scores, descriptor, k)

    def _assess_descriptors(self, scores: np.ndarray, which: np.ndarray, times: np.ndarray,
                            descriptor: np.ndarray, stamp: float) -> tuple[Any, np.ndarray]:
        """The calibrated decision on descriptors: the ``rerank`` best candidates by score and
        ``rerank_sample`` others spread over the rest, scored by cosine
        (:meth:`IntervalDescriptors.sampled`); the winner the most alike of the first, judged
        against them all."""
        cand, cos, n_top = self.descriptors.sampled(scores, descriptor, self.config.rerank,
                                                    self.config.rerank_sample)
        if n_top == 0:
            return None, which
        best = int(np.argmax(cos[:n_top]))
        cal = self.calibration
        recent = self.descriptors.view_ago_cosine(descriptor, stamp, cal.seconds(cal.config.neighbourhood_m))
        a = cal.assess(cos, times[cand], recent, best)
        return a, which[cand]

    def _confirm_duplicates(self, loop: bool, made_template: bool, best: int, held: bool = False) -> None:
        """A closure is accepted only after evidence over ``sequence_m`` of travel, so the first
        frames of a revisit are refused and make new templates of a place that already has one
        (or, with merge_revisits, hold the current one). When the evidence then confirms the
        revisit, each such interval registered within that stretch is the place its frame matched:
        it takes that place's template, so that later visits find one template there, not two that
        compete (their references would disagree); with merge_revisits it never enters the index.
        The ids already sent stay valid; they are just not matched again."""
        if loop:
            for k, matched in self.calibration.confirmed(self.t):  # keys: the intervals
                if self.merge is None or k in self.interval_template:
                    self.interval_template[k] = self.interval_template[matched]
                    if self.merge is not None:
                        self.merge.confirm(k)
        elif made_template and best >= 0:
            self.calibration.on_new_template(self.t, self.n_intervals - 1, best)
            if self.merge is not None:
                self.merge.register(self.n_intervals - 1, self.t, held)

    def _recent_score(self, y_bm: BitMap) -> float:
        """The normalised score of the interval before the newest: the view a moment ago."""
        n = len(y_bm)
        union = self.unions[self.n_intervals - 2]
        return union.intersection_cardinality(y_bm) * (n / max(len(union), n))

    def info(self) -> dict[str, Any]:
        """What D keeps and made: intervals made, stored and indexed, templates made; with
        merge_revisits how many intervals were held, merged into a place, expired and dropped."""
        out = {"intervals": self.n_intervals, "intervals_stored": self.n_stored, "indexed_intervals": self._n_indexed,
               "templates": self.n_templates}
        if self.merge is not None:
            out["revisit_merge"] = dict(self.merge.counts)
        return out

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the index's kernels now, not on a live frame."""
        self.index.warm_up()
        if self.config.rerank:
            self.descriptors.warm_up()

    def new_session(self) -> None:
        """A new session on this map (``neoslam run --map``): its stamps start afresh, so at its first
        frame the stored intervals' stamps move back to end a shortest loop before it
        (:meth:`~.calibration.RunCalibration.session_shift`): every known place is a candidate at
        once, the stamps stay in order (the candidates are found by bisection), and the decision's
        evidence starts afresh. Frame numbers (``t``) continue."""
        if self.n_intervals:
            last = self.calibration.last_stamp
            if last is None:  # the newest interval D still keeps (merge_revisits may forget some)
                last = max(self.interval_stamps[k] for k in self._kept())
            self._old_last_stamp = float(last)
        self.calibration.new_session()
        self.descriptors.new_session()  # the views a moment ago were the old stream's
        # where the old session ended is not where this one starts: its first frame opens an
        # interval of its own, and no held frame keeps the old session's last template
        self.current_template = -1
        if self.merge is not None:
            self.merge.end_hold()

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """The intervals D keeps (``stored``: their numbers, of ``n_intervals`` made), their unions
        and templates, the sequence filter's history, and the parameters they were made with
        (``params``, in STATE_PARAMS order): spatial_view_state.py."""
        from .spatial_view_state import state_of

        return state_of(self)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` (spatial_view_state.py); a state made with other parameters,
        or one that forgot intervals (merge_revisits) when this config keeps every one, is refused."""
        from .spatial_view_state import load_into

        load_into(self, state)


def _put(store: np.ndarray, k: int, value: Any) -> np.ndarray:
    """``store`` with ``store[k] = value``, grown by doubling when k lies beyond it (the per-interval
    stores that a frame reads as views)."""
    if k >= store.shape[0]:
        store = np.concatenate([store, np.zeros(max(k + 1, store.shape[0]), dtype=store.dtype)])
    store[k] = value
    return store
