"""Stage D: spatial-view cells — intervals of similar SDRs and loop closure against older intervals.

The paper's formulation, per winner-cell SDR y_t:

1. Intervals. The current interval k has a union SDR Y_k and spans [start, end].
   alpha(t) = |Y_curr & y_t|. If alpha(t) >= theta_alpha and end - start < theta_rho the interval is
   extended (end += 1, Y_curr |= y_t); otherwise a new interval [t, t] with Y = y_t is opened. An
   interval therefore covers at most theta_rho + 1 frames.
2. Scores s_k = |Y_k & y_t| for the intervals k = 0 .. K-1-omega (K intervals exist after step 1;
   the omega = ``exclude_recent_intervals`` newest, the current one included, are never candidates).
3. Candidates are s_k > theta_sigma (strictly); the best is k* = argmax, the lowest index on ties.
4. Template tau(t): with a candidate, the template of interval k* (a loop closure); else, if a new
   interval was opened, a new template id (consecutive from 0); else the current template.
   Each interval keeps the template it got when it was opened.

Differences from the ROS 2 NeoSLAM on purpose: interval k's template is interval k's (the ROS 2
code returns the template of the interval *before* the match, because interval 0 never gets a map
row), and the first frame opens interval 0 like any other.

Speed: scores come from an inverted index bit -> intervals containing it (posting lists, sorted by
interval id because intervals are created in order and unions only grow), summed by a numba loop
over the ~512 postings of y_t, so one frame costs O(sum of posting lengths), never a Python loop
over K. The union of each interval is kept as a pyroaring BitMap as the paper describes.

The index has two parts. New postings go to linked blocks of BLOCK entries in one pool (appending
is O(1) and memory follows the number of postings), but walking scattered blocks is bound by
memory latency once the index outgrows the cache. So whenever the linked part holds more than a
quarter of the compacted part (and at least COMPACT_MIN postings), both are merged into one
contiguous CSR array (offsets per bit), which the scoring loop streams with hardware prefetching.
A merge costs O(postings) and happens after the index grew by 25 %, on a background thread: meanwhile
new postings go to a fresh linked part and scores read all three parts, so no frame waits for it
and results do not depend on when it finishes. Measured times: bench/results/frontend.json,
docs/frontend.md and docs/performance.md.
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Any

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field
from pyroaring import BitMap

from ._config import make_config
from .errors import InvalidInput
from .sequence import SequenceConfig, SequenceFilter


class SpatialViewConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    theta_alpha: int = Field(384, ge=0)
    theta_rho: int = Field(3, ge=0)
    theta_sigma: int = Field(470, ge=0)
    exclude_recent_intervals: int = Field(3, ge=0)
    sdr_size: int = Field(65536, ge=1)
    #: issue #14: accept a closure only after a run of consistent candidates (algorithms.sequence;
    #: the default ``length: 0`` keeps the paper's rule)
    sequence: SequenceConfig = Field(default_factory=SequenceConfig)


BLOCK = 128  # entries per posting block (512 B: few jumps per list, little slack)


@njit(cache=True)
def _append_postings(pool, nxt, head, tail, fill, n_blocks, bits, interval):  # pragma: no cover
    """Append ``interval`` to the posting list of every bit; returns the new block count.

    The caller guarantees room for one new block per bit.
    """
    for b in bits:
        t = tail[b]
        if t == -1 or fill[b] == BLOCK:
            blk = n_blocks
            n_blocks += 1
            nxt[blk] = -1
            if t == -1:
                head[b] = blk
            else:
                nxt[t] = blk
            tail[b] = blk
            fill[b] = 0
            t = blk
        pool[t, fill[b]] = interval
        fill[b] += 1
    return n_blocks


@njit(cache=True)
def _scores(pool, nxt, head, tail, fill, bits, out):  # pragma: no cover - compiled
    """out[k] += 1 for every interval k whose union holds a bit of ``bits``.

    Every interval is counted, the excluded recent ones too: they are the last few entries of each
    posting list, and ignoring their counts afterwards is cheaper than a test on every entry.
    """
    for b in bits:
        blk = head[b]
        while blk != -1:
            n = fill[b] if blk == tail[b] else BLOCK
            row = pool[blk]
            for i in range(n):
                out[row[i]] += 1
            blk = nxt[blk]


@njit(cache=True)
def _scores_csr(ptr, post, bits, out):  # pragma: no cover - compiled
    """out[k] += 1 for every posting of ``bits`` in the compacted (CSR) part of the index."""
    for b in bits:
        for i in range(ptr[b], ptr[b + 1]):
            out[post[i]] += 1


@njit(cache=True, nogil=True)
def _compact(ptr, post, pool, nxt, head, tail, fill):  # pragma: no cover - compiled
    """Merge the CSR part and the linked blocks into one new CSR index (ptr, post)."""
    n_bits = head.shape[0]
    counts = np.zeros(n_bits + 1, dtype=np.int64)
    for b in range(n_bits):
        c = ptr[b + 1] - ptr[b]
        blk = head[b]
        while blk != -1:
            c += fill[b] if blk == tail[b] else BLOCK
            blk = nxt[blk]
        counts[b + 1] = c
    new_ptr = np.cumsum(counts)
    new_post = np.empty(new_ptr[-1], dtype=np.int32)
    for b in range(n_bits):
        j = new_ptr[b]
        for i in range(ptr[b], ptr[b + 1]):
            new_post[j] = post[i]
            j += 1
        blk = head[b]
        while blk != -1:
            n = fill[b] if blk == tail[b] else BLOCK
            for i in range(n):
                new_post[j] = pool[blk, i]
                j += 1
            blk = nxt[blk]
    return new_ptr, new_post


#: the linked part is merged into the CSR part once it holds this many postings and more than a
#: quarter of the CSR part (512 intervals of 512 cells: no compaction at all for small maps)
COMPACT_MIN = 262144


class SpatialViewCells:
    """SDR -> (template id, is_loop_closure, best interval, best score). See the module docstring."""

    def __init__(self, config: SpatialViewConfig | None = None, **overrides: Any) -> None:
        cfg = self.config = make_config(SpatialViewConfig, config, overrides)
        self.theta_alpha = cfg.theta_alpha
        self.theta_rho = cfg.theta_rho
        self.theta_sigma = cfg.theta_sigma
        self.omega = cfg.exclude_recent_intervals
        self.sdr_size = cfg.sdr_size
        self._init_storage(1024)
        self.unions: list[BitMap] = []
        self.interval_start: list[int] = []
        self.interval_end: list[int] = []
        self.interval_template: list[int] = []
        self.n_templates = 0
        self.current_template = -1
        self.t = 0
        self._scores = np.zeros(1024, dtype=np.int32)
        self.sequence = SequenceFilter(cfg.sequence)

    def _init_storage(self, blocks: int) -> None:
        # compacted part: CSR offsets per bit and the postings
        self._ptr = np.zeros(self.sdr_size + 1, dtype=np.int64)
        self._post = np.zeros(0, dtype=np.int32)
        self._reset_linked(blocks)

    def _reset_linked(self, blocks: int) -> None:
        # linked part: blocks of BLOCK entries in one pool: memory grows with the number of
        # postings only, whatever the distribution of bits
        self._linked_postings = 0
        self._pool = np.zeros((blocks, BLOCK), dtype=np.int32)
        self._next = np.full(blocks, -1, dtype=np.int32)
        self._head = np.full(self.sdr_size, -1, dtype=np.int32)
        self._tail = np.full(self.sdr_size, -1, dtype=np.int32)
        self._fill = np.zeros(self.sdr_size, dtype=np.int32)
        self._n_blocks = 0
        # a linked part being merged in the background: (its arrays, the future of the merge)
        self._frozen: tuple[tuple[np.ndarray, ...], Any] | None = None

    def _post_bits(self, bits: np.ndarray, interval: int) -> None:
        need = self._n_blocks + len(bits)
        if need > self._pool.shape[0]:
            cap = max(need, 2 * self._pool.shape[0])
            pool = np.zeros((cap, BLOCK), dtype=np.int32)
            pool[: self._n_blocks] = self._pool[: self._n_blocks]
            nxt = np.full(cap, -1, dtype=np.int32)
            nxt[: self._n_blocks] = self._next[: self._n_blocks]
            self._pool, self._next = pool, nxt
        self._n_blocks = _append_postings(self._pool, self._next, self._head, self._tail, self._fill,
                                          self._n_blocks, bits, interval)
        self._linked_postings += len(bits)
        if self._frozen is not None and self._frozen[1].done():
            self._finish_background_merge()
        if self._frozen is None and self._linked_postings >= max(COMPACT_MIN, self._post.shape[0] // 4):
            self._start_background_merge()

    def _linked_arrays(self) -> tuple[np.ndarray, ...]:
        return self._pool, self._next, self._head, self._tail, self._fill

    def _start_background_merge(self) -> None:
        """Freeze the linked part, start merging it with the CSR part on a background thread
        (the numba kernel releases the GIL) and take a fresh linked part for new postings.
        Until the merge is done, scores read the CSR part, the frozen part and the new part: the
        same counts, so results do not depend on when the merge finishes; a frame never waits
        for it (a merge at a large K takes several frame periods: docs/frontend.md)."""
        from concurrent.futures import ThreadPoolExecutor

        if getattr(self, "_executor", None) is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="svc-compact")
        frozen = self._linked_arrays()
        future = self._executor.submit(_compact, self._ptr, self._post, *frozen)
        self.merges = getattr(self, "merges", 0) + 1
        self._reset_linked(1024)
        self._frozen = (frozen, future)

    def _finish_background_merge(self) -> None:
        assert self._frozen is not None
        self._ptr, self._post = self._frozen[1].result()
        self._frozen = None

    def compact(self) -> None:
        """Merge every linked posting into the contiguous CSR part now (waits for a background
        merge in progress first); see the module docstring."""
        if self._frozen is not None:
            self._finish_background_merge()
        if self._linked_postings == 0:
            return
        self._ptr, self._post = _compact(self._ptr, self._post, *self._linked_arrays())
        self._reset_linked(1024)

    @property
    def n_intervals(self) -> int:
        return len(self.unions)

    def _validate(self, sdr: np.ndarray) -> np.ndarray:
        a = np.asarray(sdr)
        if a.ndim != 1:
            raise InvalidInput(f"SDR must be a 1-D array of cell indices, got shape {a.shape}")
        if a.size and (a.min() < 0 or a.max() >= self.sdr_size):
            raise InvalidInput(f"SDR indices must lie in [0, {self.sdr_size})")
        return np.unique(a.astype(np.int64)).astype(np.int32)

    def compute(self, sdr: np.ndarray) -> dict[str, Any]:
        """Process y_t; returns template id, loop-closure flag, best interval and score."""
        y = self._validate(sdr)
        y_bm = BitMap(y)
        new_interval = False
        if not self.unions:
            new_interval = True
        else:
            cur = self.n_intervals - 1
            alpha = self.unions[cur].intersection_cardinality(y_bm)
            duration = self.interval_end[cur] - self.interval_start[cur]
            if alpha >= self.theta_alpha and duration < self.theta_rho:
                added = y_bm - self.unions[cur]
                self.unions[cur] |= y_bm
                self.interval_end[cur] = self.t
                if len(added):
                    self._post_bits(np.fromiter(added, dtype=np.int32, count=len(added)), cur)
            else:
                new_interval = True
        if new_interval:
            k = self.n_intervals
            self.unions.append(y_bm)
            self.interval_start.append(self.t)
            self.interval_end.append(self.t)
            self.interval_template.append(-1)
            self._post_bits(y, k)
        limit = self.n_intervals - self.omega
        if self.sequence.min_gap:  # only intervals opened at least min_gap frames ago (sequence.py)
            limit = min(limit, bisect_right(self.interval_start, self.t - self.sequence.min_gap))
        best, best_score = -1, 0
        if limit > 0:
            k_all = self.n_intervals
            if self._scores.shape[0] < k_all:
                self._scores = np.zeros(max(k_all, 2 * self._scores.shape[0]), dtype=np.int32)
            scores = self._scores[:k_all]
            scores[:] = 0
            _scores_csr(self._ptr, self._post, y, scores)
            if self._frozen is not None:
                _scores(*self._frozen[0], y, scores)
            if self._linked_postings:
                _scores(self._pool, self._next, self._head, self._tail, self._fill, y, scores)
            best = int(np.argmax(scores[:limit]))  # first maximum = lowest index
            best_score = int(scores[best])
        loop = best >= 0 and best_score > self.theta_sigma
        if self.sequence.enabled:  # a candidate is a closure only within a consistent sequence
            loop = self.sequence.check(self.t, self.interval_start[best] if loop else -1)
        if loop:
            template = self.interval_template[best]
        elif new_interval:
            template = self.n_templates
            self.n_templates += 1
        else:
            template = self.current_template
        if new_interval:
            self.interval_template[-1] = template
        self.current_template = template
        self.t += 1
        return {"id": template, "is_loop_closure": bool(loop), "best_interval": best if loop else -1,
                "best_score": best_score, "relative_rad": 0.0, "interval": self.n_intervals - 1}

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel now, on a throw-away copy: disjoint
        SDRs open a new interval each, so scoring runs on linked postings, then on the compacted
        index, with the dtype the node hands over."""
        warm = SpatialViewCells(self.config)
        n = self.sdr_size
        for i in range(self.omega + 3):
            warm.compute((np.arange(64, dtype=np.uint32) + 64 * i) % n)
        warm.compact()
        warm.compute(np.arange(64, dtype=np.uint32))

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        return {"params": [self.theta_alpha, self.theta_rho, self.theta_sigma, self.omega, self.sdr_size],
                "unions": [np.asarray(u.to_array(), dtype=np.uint32) for u in self.unions],
                "start": np.asarray(self.interval_start, np.int64), "end": np.asarray(self.interval_end, np.int64),
                "template": np.asarray(self.interval_template, np.int64), "n_templates": self.n_templates,
                "current_template": self.current_template, "t": self.t,
                "sequence": self.sequence.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        (self.theta_alpha, self.theta_rho, self.theta_sigma, self.omega, self.sdr_size) = state["params"]
        self._init_storage(1024)
        self.unions = []
        for k, arr in enumerate(state["unions"]):
            a = np.asarray(arr, dtype=np.int32)
            self.unions.append(BitMap(a))
            self._post_bits(a, k)
        self.compact()
        self.interval_start = [int(x) for x in state["start"]]
        self.interval_end = [int(x) for x in state["end"]]
        self.interval_template = [int(x) for x in state["template"]]
        self.n_templates = int(state["n_templates"])
        self.current_template = int(state["current_template"])
        self.t = int(state["t"])
        self.sequence.load_state_dict(state.get("sequence", {}))
