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

Issue #14's acceptance rules (all off in the paper profile): ``sequence`` (a run of consistent
candidates, a minimum gap: algorithms/sequence.py), ``theta_margin`` (a closure also needs
s_k* - s_k2 >= theta_margin over the runner-up k2) and ``union_normalised`` (every s_k replaced by
s_k |y_t| / max(|Y_k|, |y_t|) for ranking, threshold and margin, from the exhaustive count).

Differences from the ROS 2 NeoSLAM on purpose: interval k's template is interval k's (the ROS 2
code returns the template of the interval *before* the match, because interval 0 never gets a map
row), and the first frame opens interval 0 like any other.

Speed, the bounded search (#16): only the best candidate k*, its score and the runner-up matter,
so not every s_k is computed. (1) The last frame's best and runner-up (and their successors) and
the two newest candidates are scored exactly, s_k = |Y_k & y_t| from Y_k's sorted cells; the
runner-up's score s2 is a lower bound of the final one. (2) The posting lists of y_t's cells are
read rarest first; after e of the n lists an interval met in none of them has s_k <= n - e, so
once n - e < s2 no unseen interval can enter the top two (a tie needs s_k = s2) and reading stops;
at e = 16, 32, 64... the candidates with the most shared cells so far are scored exactly to raise
s2. (3) Met candidates, most shared cells first, are scored exactly while their bound
partial_k + (n - e) can reach s2. The result is the exhaustive argmax with its ties (lowest index)
bit for bit (tests/test_spatial_view.py checks it against a brute-force scan), and the runner-up
(``runner_up``). When the n - s2 + 1 rarest lists, which must be read anyway, are most of the
postings (y_t unlike every interval: random SDRs), every posting is counted instead, without the
bookkeeping of bounds. ``exhaustive = True`` scores every interval (the reference, below).

Speed on real SDRs, the bit-sliced count (#16): real winner cells are cell 0 of their column, so
only ~2048 cells occur and each is in ~60 % of the intervals; the posting lists are long and alike,
and the bounded search still read 5 % of them (6.3 ms at K = 100k). A cell whose list holds at least
DENSE_MIN intervals and 1/32 of them gets a dense row, one bit per interval (no larger than its
list). A query adds the rows of its cells, 8 at a time, with a carry-save adder tree into 10 bit
planes, one machine word counting 64 intervals; cells without a row are counted from their lists.
Only intervals whose count can reach the runner-up are looked at (a bit-sliced comparison per
word), so the top two and their ties are the exhaustive ones (tested against a brute-force scan).
The cost is linear in K, at K / 64 word operations per cell: 0.8 ms at K = 100k replayed real
SDRs, against 30 ms exhaustive (docs/performance.md). Per query a cost model picks the bit-sliced
count or the posting-list search (``sliced`` forces either; ``last_path`` says which ran).

Scores (exhaustive) come from an inverted index bit -> intervals containing it (posting lists, sorted by
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
from pydantic import BaseModel, ConfigDict, Field, field_validator
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
    #: issue #14: candidates are ranked and thresholded by the normalised score
    #: s_k |y_t| / max(|Y_k|, |y_t|), i.e. theta_sigma scaled to the union's size (a union of
    #: several frames overlaps every SDR more: on Nordland one 4-frame interval of 820 cells took
    #: 101 of 115 wrong closures). Every candidate is scored then (the exhaustive count, not the
    #: bounded search). False: the paper's s_k > theta_sigma
    union_normalised: bool = False
    #: issue #14: a closure also needs a margin over the runner-up, score(k*) - score(k2) >=
    #: theta_margin (the scores are the normalised ones when ``union_normalised``): a place that
    #: looks like many others is refused. 0: off (the paper's rule)
    theta_margin: float = Field(0.0, ge=0)

    @field_validator("exclude_recent_intervals")
    @classmethod
    def _omega_excludes_the_current_interval(cls, v: int) -> int:
        # omega = 0 makes the current interval, which already holds y_t, a candidate: every frame
        # would match itself (a "loop closure" onto the template -1 it has not got yet at frame 0)
        if v < 1:
            raise ValueError(f"exclude_recent_intervals must be >= 1 (got {v}): the current interval "
                             "already holds y_t, so with 0 every frame matches its own interval")
        return v


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


@njit(cache=True, inline="always")
def _walk_csr(b, ptr, post, limit, partial, touched, n_touched):  # pragma: no cover - compiled
    """partial[j] += 1 for every candidate j < limit in bit b's list of the CSR part; newly touched
    candidates are appended to ``touched``. Lists are sorted by interval id across the parts (every
    posting is appended for the newest interval), so the excluded recent intervals are the tail of
    each list: stop at the first j >= limit."""
    for i in range(ptr[b], ptr[b + 1]):
        j = post[i]
        if j >= limit:
            break
        if partial[j] == 0:
            touched[n_touched] = j
            n_touched += 1
        partial[j] += 1
    return n_touched


@njit(cache=True, inline="always")
def _walk_linked(b, pool, nxt, head, tail, fill, limit, partial, touched, n_touched):  # pragma: no cover
    """:func:`_walk_csr` for bit b's list in a linked part."""
    blk = head[b]
    while blk != -1:
        n = fill[b] if blk == tail[b] else BLOCK
        row = pool[blk]
        for i in range(n):
            j = row[i]
            if j >= limit:
                return n_touched
            if partial[j] == 0:
                touched[n_touched] = j
                n_touched += 1
            partial[j] += 1
        blk = nxt[blk]
    return n_touched


@njit(cache=True, inline="always")
def _exact(j, u_ptr, u_cells, inq):  # pragma: no cover - compiled
    """s_j = |Y_j & y_t|: the cells of union j that the query marks in ``inq``."""
    s = 0
    for i in range(u_ptr[j], u_ptr[j + 1]):
        s += inq[u_cells[i]]
    return s


@njit(cache=True, inline="always")
def _offer(j, s, b1, s1, b2, s2):  # pragma: no cover - compiled
    """Insert (j, s) into the running top two, ordered by score then lowest index."""
    if j == b1 or j == b2:
        return b1, s1, b2, s2
    if s > s1 or (s == s1 and j < b1):
        return j, s, b1, s1
    if s > s2 or (s == s2 and j < b2):
        return b1, s1, j, s
    return b1, s1, b2, s2


@njit(cache=True, inline="always")
def _offer_hints(hints, limit, u_ptr, u_cells, inq):  # pragma: no cover - compiled
    """The running top two (b1, s1, b2, s2) from the exact scores of the hinted intervals below
    ``limit`` (``inq`` marks y_t's cells), and how many were scored; (limit + 1, -1) pairs when none."""
    big = limit + 1
    b1, s1, b2, s2 = big, -1, big, -1
    scored = 0
    for h in hints:
        if 0 <= h < limit:
            b1, s1, b2, s2 = _offer(h, _exact(h, u_ptr, u_cells, inq), b1, s1, b2, s2)
            scored += 1
    return b1, s1, b2, s2, scored


@njit(cache=True)
def _top2_counted(y, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head, tail, fill, limit,
                  counts, verified):  # pragma: no cover - compiled
    """:func:`_top2`'s top two from every posting of y_t counted into ``counts`` (zero on entry,
    sized for every interval; zeroed again on exit)."""
    _scores_csr(ptr, post, y, counts)
    _scores(f_pool, f_next, f_head, f_tail, f_fill, y, counts)
    _scores(pool, nxt, head, tail, fill, y, counts)
    big = limit + 1
    b1, s1, b2, s2 = big, -1, big, -1
    for j in range(limit):
        v = counts[j]
        if v > s2:  # strictly: on ties the lower index, met first, stays
            if v > s1:
                b1, s1, b2, s2 = j, v, b1, s1
            else:
                b2, s2 = j, v
    counts[:] = 0
    return b1, s1, b2, s2, verified


@njit(cache=True)
def _top2(y, lengths, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head, tail, fill,
          u_ptr, u_cells, limit, hints, inq, partial, touched, bucket):  # pragma: no cover - compiled
    """The best and runner-up candidates k < limit by s_k = |Y_k & y_t| (ties: lowest index),
    exactly as exhaustive scoring ranks them, without reading every posting (see the module
    docstring: score bounds, lists rarest first). Returns (b1, s1, b2, s2, postings read,
    unions verified); b2 = -1 when limit < 2.

    ``lengths[i]`` is the posting-list length of y[i]. Scratch arrays ``inq`` (sdr_size),
    ``partial`` (>= limit) are zero on entry and on exit.
    """
    n = y.shape[0]
    for c in y:
        inq[c] = 1
    if limit == 1:
        s = _exact(0, u_ptr, u_cells, inq)
        for c in y:
            inq[c] = 0
        return 0, s, -1, 0, 0, 1
    # 1. a lower bound from likely winners (the last frame's, the newest candidates): exact scores
    b1, s1, b2, s2, verified = _offer_hints(hints, limit, u_ptr, u_cells, inq)
    # 2. rarest lists first. After e lists an interval met in none of them scores at most n - e;
    # once n - e < s2 it cannot enter the top two (a tie needs s = s2), so candidate generation stops.
    order = np.argsort(lengths, kind="mergesort")
    # the n - s2 + 1 rarest lists must be read whatever happens; when they are most of the postings
    # (s2 small: SDRs unlike every interval, e.g. random ones) bounds cannot pay for their
    # bookkeeping: count every posting instead (plain increments, 4x faster there)
    must = 0
    for q in range(min(n, max(n - s2 + 1, 0))):
        must += lengths[order[q]]
    if 2 * must > lengths.sum():
        for c in y:
            inq[c] = 0
        b1, s1, b2, s2, verified = _top2_counted(y, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt,
                                                 head, tail, fill, limit, partial, verified)
        return b1, s1, b2, s2, lengths.sum(), verified
    avg_union = u_ptr[limit] / limit  # cost of one exact score, in cells read
    n_touched = 0
    read = 0
    e = 0
    next_check = 16
    last_count = -8
    prev_alive = 1 << 62
    while e < n:
        if n - e < s2 and e - last_count >= 8:
            # every interval in the top two has been met. Reading on only prunes: a candidate
            # missing more than n - s2 of the lists read is out. Stop when verifying the
            # survivors costs less than the next 8 lists (real SDRs: long, similar lists), or
            # when reading prunes little and verifying is cheaper than reading the rest.
            last_count = e
            alive = 0
            for t in range(n_touched):
                if partial[touched[t]] + n - e >= s2:
                    alive += 1
            ahead = 0
            for q in range(e, min(n, e + 8)):
                ahead += lengths[order[q]]
            remaining = 0
            for q in range(e, n):
                remaining += lengths[order[q]]
            if alive * avg_union <= ahead:
                break
            # the last 8 lists pruned little (the survivors are near copies of y_t): verify them
            # if that is cheaper than reading every remaining list
            if alive > 0.9 * prev_alive and alive * avg_union <= remaining:
                break
            prev_alive = alive
        b = y[order[e]]
        read += lengths[order[e]]
        n_touched = _walk_csr(b, ptr, post, limit, partial, touched, n_touched)
        n_touched = _walk_linked(b, f_pool, f_next, f_head, f_tail, f_fill, limit, partial, touched, n_touched)
        n_touched = _walk_linked(b, pool, nxt, head, tail, fill, limit, partial, touched, n_touched)
        e += 1
        if e == next_check:
            # raise the bound: verify the touched candidates with the most shared bits so far
            next_check *= 2
            top = 0
            for t in range(n_touched):
                if partial[touched[t]] > top:
                    top = partial[touched[t]]
            got = 0
            for t in range(n_touched):
                j = touched[t]
                if partial[j] == top and got < 4:
                    b1, s1, b2, s2 = _offer(j, _exact(j, u_ptr, u_cells, inq), b1, s1, b2, s2)
                    verified += 1
                    got += 1
    # 3. candidates met so far, most shared bits first: s_j <= partial_j + (n - e); verify exactly
    # while that bound can reach s2 (then no later one can: the order is by partial, descending)
    rest = n - e
    bucket[: e + 2] = 0
    for t in range(n_touched):
        bucket[partial[touched[t]]] += 1
    start = 0
    for p in range(e, -1, -1):  # counting sort by partial, descending
        c = bucket[p]
        bucket[p] = start
        start += c
    ranked = np.empty(n_touched, np.int32)
    for t in range(n_touched):
        j = touched[t]
        ranked[bucket[partial[j]]] = j
        bucket[partial[j]] += 1
    for t in range(n_touched):
        j = ranked[t]
        if partial[j] + rest < s2:
            break
        if rest == 0:
            s = partial[j]
        else:
            s = _exact(j, u_ptr, u_cells, inq)
            verified += 1
        b1, s1, b2, s2 = _offer(j, s, b1, s1, b2, s2)
    for t in range(n_touched):
        partial[touched[t]] = 0
    for c in y:
        inq[c] = 0
    # 4. fewer than two candidates share a bit with y_t: the lowest-index zero scores complete the
    # top two (every list was read then, so untouched means s = 0)
    j = 0
    while s2 < 0 and j < limit:
        b1, s1, b2, s2 = _offer(j, 0, b1, s1, b2, s2)
        j += 1
    return b1, s1, b2, s2, read, verified


# ----------------------------------------------------------------------- bit-sliced part (#16)
#: words per block of the dense rows (64 intervals a word): one block of the ten counter planes
#: (20 kB) stays in L1 while the query's rows stream through it, and each row's 2 kB run is long
#: enough for the hardware prefetcher (64-word blocks were 1.6x slower with a cold cache)
SLICE_WORDS = 256
SLICE_BLOCK = 64 * SLICE_WORDS
#: a cell gets a dense row (one bit per interval) once its posting list holds this many intervals
#: and at least 1/32 of them: from then on the row is no larger than the list it mirrors
DENSE_MIN = 1024
#: counter slices: counts up to 1023, so at most 1016 dense rows per query (8-row groups)
SLICES = 10
_ALL = np.uint64(0xFFFFFFFFFFFFFFFF)
_ONE = np.uint64(1)


@njit(cache=True, inline="always")
def _csa(a, b, c):  # pragma: no cover - compiled
    """Carry-save adder on 64 lanes at once: per bit position, a + b + c = 2 * carry + sum."""
    u = a ^ b
    return (a & b) | (u & c), u ^ c


@njit(cache=True, inline="always")
def _half_add(a, b):  # pragma: no cover - compiled
    """(sum, carry) of a + b per bit position."""
    return a ^ b, a & b


@njit(cache=True)
def _set_dense_bits(dense, row_of, bits, interval):  # pragma: no cover - compiled
    """Mark ``interval`` in the dense row of every cell of ``bits`` that has one."""
    blk = interval // SLICE_BLOCK
    w = (interval >> 6) % SLICE_WORDS
    m = _ONE << np.uint64(interval & 63)
    for b in bits:
        r = row_of[b]
        if r >= 0:
            dense[blk, r, w] |= m


@njit(cache=True)
def _fill_dense_row(b, row, dense, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head, tail,
                    fill):  # pragma: no cover - compiled
    """A new dense row for cell b from its posting list (all three parts)."""
    for i in range(ptr[b], ptr[b + 1]):
        j = post[i]
        dense[j // SLICE_BLOCK, row, (j >> 6) % SLICE_WORDS] |= _ONE << np.uint64(j & 63)
    _fill_dense_linked(b, row, dense, f_pool, f_next, f_head, f_tail, f_fill)
    _fill_dense_linked(b, row, dense, pool, nxt, head, tail, fill)


@njit(cache=True, inline="always")
def _fill_dense_linked(b, row, dense, pool, nxt, head, tail, fill):  # pragma: no cover - compiled
    blk = head[b]
    while blk != -1:
        n = fill[b] if blk == tail[b] else BLOCK
        for i in range(n):
            j = pool[blk, i]
            dense[j // SLICE_BLOCK, row, (j >> 6) % SLICE_WORDS] |= _ONE << np.uint64(j & 63)
        blk = nxt[blk]


@njit(cache=True)
def _top2_sliced(y, rows, sparse, dense, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head,
                 tail, fill, u_ptr, u_cells, limit, hints, inq, partial, touched):  # pragma: no cover - compiled
    """The top two of :func:`_top2` (same order, same ties) from bit-sliced counts.

    Every s_k, k < limit, is counted: ``rows`` are the dense rows of y_t's cells (padded to a
    multiple of 8 with the all-zero row 0), added 8 at a time by a carry-save adder tree into
    SLICES bit planes per block of SLICE_BLOCK intervals (64 intervals per machine word, so one
    word operation counts 64 intervals; the loops vectorise). The cells in ``sparse`` (no dense
    row) are counted from their posting lists into ``partial``. Interval k is looked at only if
    its block count can reach the runner-up: count_k >= s2 - max(partial in k's word), a
    bit-sliced comparison per word; the exact score of a lane is its planes plus partial_k.
    Scratch ``inq`` and ``partial`` are zero on entry and on exit. Returns (b1, s1, b2, s2,
    intervals looked at).
    """
    for c in y:
        inq[c] = 1
    # a runner-up score from the likely winners: fewer intervals to look at
    b1, s1, b2, s2, _ = _offer_hints(hints, limit, u_ptr, u_cells, inq)
    for c in y:
        inq[c] = 0
    n_touched = 0
    for b in sparse:
        n_touched = _walk_csr(b, ptr, post, limit, partial, touched, n_touched)
        n_touched = _walk_linked(b, f_pool, f_next, f_head, f_tail, f_fill, limit, partial, touched, n_touched)
        n_touched = _walk_linked(b, pool, nxt, head, tail, fill, limit, partial, touched, n_touched)
    n_words = (limit + 63) >> 6
    wmax = np.zeros(n_words, np.int64)
    for t in range(n_touched):
        j = touched[t]
        if partial[j] > wmax[j >> 6]:
            wmax[j >> 6] = partial[j]
    # the counter planes are allocated here, not passed in: the compiler then knows they alias no
    # row, which is what lets it vectorise the adder loop
    c0 = np.zeros(SLICE_WORDS, np.uint64)
    c1 = np.zeros(SLICE_WORDS, np.uint64)
    c2 = np.zeros(SLICE_WORDS, np.uint64)
    c3 = np.zeros(SLICE_WORDS, np.uint64)
    c4 = np.zeros(SLICE_WORDS, np.uint64)
    c5 = np.zeros(SLICE_WORDS, np.uint64)
    c6 = np.zeros(SLICE_WORDS, np.uint64)
    c7 = np.zeros(SLICE_WORDS, np.uint64)
    c8 = np.zeros(SLICE_WORDS, np.uint64)
    c9 = np.zeros(SLICE_WORDS, np.uint64)
    planes = np.zeros((SLICES, SLICE_WORDS), np.uint64)
    looked = 0
    n_rows = rows.shape[0]
    for blk in range((limit + SLICE_BLOCK - 1) // SLICE_BLOCK):
        nw = min(SLICE_WORDS, n_words - blk * SLICE_WORDS)  # words of this block below the limit
        for w in range(nw):
            c0[w] = 0
            c1[w] = 0
            c2[w] = 0
            c3[w] = 0
            c4[w] = 0
            c5[w] = 0
            c6[w] = 0
            c7[w] = 0
            c8[w] = 0
            c9[w] = 0
        dblk = dense[blk]
        for g in range(0, n_rows, 8):
            d0 = dblk[rows[g]]
            d1 = dblk[rows[g + 1]]
            d2 = dblk[rows[g + 2]]
            d3 = dblk[rows[g + 3]]
            d4 = dblk[rows[g + 4]]
            d5 = dblk[rows[g + 5]]
            d6 = dblk[rows[g + 6]]
            d7 = dblk[rows[g + 7]]
            for w in range(nw):
                # 8 rows into planes 0-2 (ones, twos, fours) and a carry of weight 8
                ones = c0[w]
                twos = c1[w]
                fours = c2[w]
                twos_a, ones = _csa(ones, d0[w], d1[w])
                twos_b, ones = _csa(ones, d2[w], d3[w])
                fours_a, twos = _csa(twos, twos_a, twos_b)
                twos_a, ones = _csa(ones, d4[w], d5[w])
                twos_b, ones = _csa(ones, d6[w], d7[w])
                fours_b, twos = _csa(twos, twos_a, twos_b)
                carry, fours = _csa(fours, fours_a, fours_b)
                c0[w] = ones
                c1[w] = twos
                c2[w] = fours
                c3[w], carry = _half_add(c3[w], carry)  # the carry ripples up the higher planes
                c4[w], carry = _half_add(c4[w], carry)
                c5[w], carry = _half_add(c5[w], carry)
                c6[w], carry = _half_add(c6[w], carry)
                c7[w], carry = _half_add(c7[w], carry)
                c8[w], carry = _half_add(c8[w], carry)
                c9[w] ^= carry
        planes[0] = c0
        planes[1] = c1
        planes[2] = c2
        planes[3] = c3
        planes[4] = c4
        planes[5] = c5
        planes[6] = c6
        planes[7] = c7
        planes[8] = c8
        planes[9] = c9
        for w in range(nw):
            gw = blk * SLICE_WORDS + w
            thr = s2 - wmax[gw]
            if thr <= 0:
                ge = _ALL
            elif thr >= 1 << SLICES:
                ge = np.uint64(0)
            else:  # lanes whose count >= thr, plane by plane from the top
                gt = np.uint64(0)
                eq = _ALL
                for s in range(SLICES - 1, -1, -1):
                    if (thr >> s) & 1:
                        eq &= planes[s, w]
                    else:
                        gt |= eq & planes[s, w]
                        eq &= ~planes[s, w]
                ge = gt | eq
            if gw == n_words - 1 and (limit & 63):
                ge &= (_ONE << np.uint64(limit & 63)) - _ONE
            lane = 0
            while ge != 0:
                if ge & _ONE:
                    j = (gw << 6) + lane
                    v = np.int64(partial[j])
                    for s in range(SLICES):
                        v += np.int64((planes[s, w] >> np.uint64(lane)) & _ONE) << s
                    b1, s1, b2, s2 = _offer(j, v, b1, s1, b2, s2)
                    looked += 1
                ge >>= _ONE
                lane += 1
    for t in range(n_touched):
        partial[touched[t]] = 0
    return b1, s1, b2, s2, looked


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
        #: True: score every candidate (the reference the bounded search is tested against)
        self.exhaustive = False
        #: the runner-up of the last frame (interval, score): -1, 0 when there is none
        self.runner_up = (-1, 0)
        #: postings read and unions verified by the last frame's bounded search (bench figures)
        self.last_search = (0, 0)
        self._hints = np.full(6, -1, dtype=np.int64)
        #: None: each query takes the cheaper of the bounded posting-list search and the bit-sliced
        #: count (when y_t's cells have dense rows); True / False: always / never bit-sliced.
        #: Both give the exhaustive top two (tests/test_spatial_view.py).
        self.sliced: bool | None = None
        #: which search the last frame used: "postings" or "sliced"
        self.last_path = "postings"
        #: posting-list length from which a cell gets a dense row (with >= 1/32 of the intervals)
        self.dense_min = DENSE_MIN
        self.sequence = SequenceFilter(cfg.sequence)

    def _init_storage(self, blocks: int) -> None:
        # compacted part: CSR offsets per bit and the postings
        self._ptr = np.zeros(self.sdr_size + 1, dtype=np.int64)
        self._post = np.zeros(0, dtype=np.int32)
        # posting-list length per bit (all parts): the bounded search reads the rarest lists first
        self._count = np.zeros(self.sdr_size, dtype=np.int64)
        # every union Y_k as sorted cells, one flat array (CSR by interval): exact s_k of a
        # candidate in O(|Y_k|). Only the newest interval grows, and it is stored last.
        self._u_ptr = np.zeros(1025, dtype=np.int64)
        self._u_cells = np.zeros(1 << 16, dtype=np.uint16 if self.sdr_size <= 65536 else np.int32)
        self._u_n = 0
        self._partial = np.zeros(1024, dtype=np.int32)
        self._touched = np.zeros(1024, dtype=np.int32)
        n = self.sdr_size
        self._inq = np.zeros(n, dtype=np.uint8)
        # dense rows (bit-sliced part): row r of cell b = one bit per interval, in blocks of
        # SLICE_BLOCK intervals, block-major so that one block of every row is contiguous. Row 0
        # stays zero (it pads the query's rows to groups of 8); cells get rows when their lists grow
        # long (DENSE_MIN), which on real SDRs is most of them (docs/performance.md).
        self._row_of = np.full(n, -1, dtype=np.int32)
        self._dense = np.zeros((0, 1, SLICE_WORDS), dtype=np.uint64)
        self._n_dense = 1
        # an empty linked part stands for "no merge in progress" in the bounded search
        self._no_linked = (np.zeros((1, BLOCK), np.int32), np.full(1, -1, np.int32), np.full(n, -1, np.int32),
                           np.full(n, -1, np.int32), np.zeros(n, np.int32))
        self._reset_linked(blocks)

    def _store_union(self, k: int, cells: np.ndarray) -> None:
        """Y_k's sorted cells into the flat store: a new last interval, or the last one rewritten."""
        if k == self._u_n:
            self._u_n += 1
            if self._u_n + 1 > self._u_ptr.shape[0]:
                self._u_ptr = np.concatenate([self._u_ptr, np.zeros(self._u_ptr.shape[0], np.int64)])
                grow = self._u_ptr.shape[0]
                self._partial = np.zeros(grow, dtype=np.int32)
                self._touched = np.zeros(grow, dtype=np.int32)
        elif k != self._u_n - 1:
            raise AssertionError("only the newest interval's union changes")
        lo = int(self._u_ptr[k])
        hi = lo + cells.shape[0]
        if hi > self._u_cells.shape[0]:
            grown = np.zeros(max(hi, 2 * self._u_cells.shape[0]), dtype=self._u_cells.dtype)
            grown[:lo] = self._u_cells[:lo]
            self._u_cells = grown
        self._u_cells[lo:hi] = cells
        self._u_ptr[k + 1] = hi

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
        self._count[bits] += 1  # bits are unique
        self._update_dense(bits, interval)
        if self._frozen is not None and self._frozen[1].done():
            self._finish_background_merge()
        if self._frozen is None and self._linked_postings >= max(COMPACT_MIN, self._post.shape[0] // 4):
            self._start_background_merge()

    def _update_dense(self, bits: np.ndarray, interval: int) -> None:
        """Keep the dense rows equal to the posting lists: mark ``interval`` in the rows of its new
        cells, and give a row to every cell whose list became long (DENSE_MIN, >= 1/32 of the
        intervals), filled from that list."""
        row = self._row_of[bits]
        if self._n_dense > 1:
            self._dense_capacity(interval, 0)
            _set_dense_bits(self._dense, self._row_of, bits, interval)
        fresh = bits[row < 0]
        cnt = self._count[fresh]
        promote = fresh[(cnt >= self.dense_min) & (cnt * 32 >= interval + 1)]
        if not len(promote):
            return
        self._dense_capacity(interval, len(promote))
        frozen = self._frozen[0] if self._frozen is not None else self._no_linked
        for b in promote:
            r = self._n_dense
            self._n_dense += 1
            self._row_of[b] = r
            _fill_dense_row(int(b), r, self._dense, self._ptr, self._post, *frozen, *self._linked_arrays())

    def _dense_capacity(self, interval: int, new_rows: int) -> None:
        """Room in the dense rows for interval ``interval`` and ``new_rows`` more rows (doubling)."""
        blocks, rows, _ = self._dense.shape
        need_blocks = interval // SLICE_BLOCK + 1
        need_rows = self._n_dense + new_rows
        if need_blocks <= blocks and need_rows <= rows:
            return
        grown = np.zeros((max(need_blocks, 2 * blocks, 4) if need_blocks > blocks else blocks,
                          max(need_rows, 2 * rows, 64) if need_rows > rows else rows, SLICE_WORDS), dtype=np.uint64)
        grown[:blocks, :rows] = self._dense
        self._dense = grown

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
        """Process y_t; returns template id, loop-closure flag, best interval and score, and the
        runner-up (``second_interval``, ``second_score``: the best candidate other than k*, -1 and
        0 when there is none), from which a closure's margin best_score - second_score follows."""
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
                    self._store_union(cur, np.asarray(self.unions[cur].to_array(), dtype=np.int64))
            else:
                new_interval = True
        if new_interval:
            k = self.n_intervals
            self.unions.append(y_bm)
            self.interval_start.append(self.t)
            self.interval_end.append(self.t)
            self.interval_template.append(-1)
            self._post_bits(y, k)
            self._store_union(k, y)
        limit = self.n_intervals - self.omega
        if self.sequence.min_gap:  # only intervals opened at least min_gap frames ago (sequence.py)
            limit = min(limit, bisect_right(self.interval_start, self.t - self.sequence.min_gap))
        best, best_score = -1, 0
        second, second_score = -1, 0
        if limit > 0:
            if self.config.union_normalised:
                best, best_score, second, second_score = self._top2_normalised(y, limit)
            elif self.exhaustive:
                best, best_score, second, second_score = self._top2_exhaustive(y, limit)
            else:
                best, best_score, second, second_score = self._top2_bounded(y, limit)
        self.runner_up = (second, second_score)
        loop = best >= 0 and best_score > self.theta_sigma
        if loop and self.config.theta_margin:  # the runner-up's score is 0 when there is none
            loop = best_score - second_score >= self.config.theta_margin
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
                "best_score": best_score, "relative_rad": 0.0, "interval": self.n_intervals - 1,
                "second_interval": second, "second_score": second_score}

    def _all_scores(self, y: np.ndarray) -> np.ndarray:
        """s_k = |Y_k & y_t| of every interval, from the whole index (O(sum of posting lengths));
        a scratch array, zeroed again at the next call."""
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
        return scores

    def _top2_normalised(self, y: np.ndarray, limit: int) -> tuple[int, float, int, float]:
        """The top two candidates k < limit by s_k |y_t| / max(|Y_k|, |y_t|) (``union_normalised``;
        ties: lowest index), with their normalised scores."""
        n = len(y)
        norm = self._all_scores(y)[:limit] * (n / np.maximum(np.diff(self._u_ptr[:limit + 1]), n))
        best = int(np.argmax(norm))  # first maximum = lowest index
        best_score = float(norm[best])
        second, second_score = -1, 0.0
        if limit > 1:
            norm[best] = -1.0
            second = int(np.argmax(norm))
            second_score = float(norm[second])
        return best, best_score, second, second_score

    def _top2_exhaustive(self, y: np.ndarray, limit: int) -> tuple[int, int, int, int]:
        """Every s_k from the whole index (O(sum of posting lengths)): the reference."""
        cand = self._all_scores(y)[:limit]
        best = int(np.argmax(cand))  # first maximum = lowest index
        best_score = int(cand[best])
        second, second_score = -1, 0
        if limit > 1:
            cand[best] = -1  # scores are zeroed before the next frame
            second = int(np.argmax(cand))
            second_score = int(cand[second])
        return best, best_score, second, second_score

    def _top2_bounded(self, y: np.ndarray, limit: int) -> tuple[int, int, int, int]:
        """The same top two as :meth:`_top2_exhaustive` from a bounded search (:func:`_top2`)."""
        frozen = self._frozen[0] if self._frozen is not None else self._no_linked
        h = self._hints
        prev = (int(h[0]), int(h[2]))
        h[:] = (prev[0], prev[0] + 1, prev[1], prev[1] + 1, limit - 1, limit - 2)
        lengths = self._count[y]
        rows = self._row_of[y]
        dense = rows > 0
        n_dense = int(dense.sum())
        sparse_postings = int(lengths[~dense].sum())  # of the cells without a dense row
        sliced = self.sliced
        if limit < 2 or n_dense > (1 << SLICES) - 8:
            sliced = False
        elif sliced is None:
            # cost model measured on this machine (docs/performance.md): ~0.6 ns per row-word of the
            # bit-sliced count, ~2 ns per sparse posting, ~0.2 ns per posting the bounded search
            # could read (it reads ~5 % of them, at ~4 ns each)
            words = (n_dense + 7) // 8 * 8 * ((limit + 63) // 64)
            sliced = n_dense > 0 and 3 * words + 10 * sparse_postings < int(lengths.sum())
        if sliced:
            self._dense_capacity(self.n_intervals - 1, 0)  # blocks to read even without any dense row
            r = np.sort(rows[dense]).astype(np.int64)
            r = np.concatenate([r, np.zeros(-len(r) % 8, np.int64)])
            read = sparse_postings
            b1, s1, b2, s2, verified = _top2_sliced(
                y, r, y[~dense], self._dense, self._ptr, self._post, *frozen, self._pool, self._next, self._head,
                self._tail, self._fill, self._u_ptr, self._u_cells, limit, h, self._inq, self._partial,
                self._touched)
        else:
            b1, s1, b2, s2, read, verified = _top2(
                y, lengths, self._ptr, self._post, *frozen, self._pool, self._next, self._head, self._tail,
                self._fill, self._u_ptr, self._u_cells, limit, h, self._inq, self._partial, self._touched,
                np.zeros(y.shape[0] + 2, np.int64))
        self.last_path = "sliced" if sliced else "postings"
        self.last_search = (int(read), int(verified))
        h[0], h[2] = b1, b2
        return int(b1), int(s1), int(b2), int(s2)

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
        # the bit-sliced count and its dense rows too: on real SDRs they start after thousands of
        # intervals, where compiling them would stall a live frame
        warm.dense_min = 1
        warm.sliced = True
        for i in range(2):
            warm.compute(np.arange(64, dtype=np.uint32) + 32 * i)

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
            self._store_union(k, np.sort(a))
        self.compact()
        self.interval_start = [int(x) for x in state["start"]]
        self.interval_end = [int(x) for x in state["end"]]
        self.interval_template = [int(x) for x in state["template"]]
        self.n_templates = int(state["n_templates"])
        self.current_template = int(state["current_template"])
        self.t = int(state["t"])
        self.sequence.load_state_dict(state.get("sequence", {}))
