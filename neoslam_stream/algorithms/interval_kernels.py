"""The numba kernels of the interval index (:mod:`.interval_index`), on arrays the index owns.

Posting lists (bit -> intervals whose union Y_k holds it, sorted by interval id) live in linked
blocks of BLOCK entries and in a CSR part; ``compact`` merges them. Dense rows hold one bit per
interval for cells with long lists. Two searches give the best and runner-up interval by
s_k = |Y_k & y_t|, ties to the lowest index, exactly as scoring every interval would:
``top2`` reads posting lists rarest first under score bounds, ``top2_sliced`` adds dense rows
with a carry-save adder tree into bit planes (64 intervals a machine word).
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK = 128  # entries per posting block (512 B: few jumps per list, little slack)


@njit(cache=True)
def append_postings(pool, nxt, head, tail, fill, n_blocks, bits, interval):  # pragma: no cover
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
def scores_linked(pool, nxt, head, tail, fill, bits, out):  # pragma: no cover - compiled
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
def scores_csr(ptr, post, bits, out):  # pragma: no cover - compiled
    """out[k] += 1 for every posting of ``bits`` in the compacted (CSR) part of the index."""
    for b in bits:
        for i in range(ptr[b], ptr[b + 1]):
            out[post[i]] += 1


@njit(cache=True, nogil=True)
def compact(ptr, post, pool, nxt, head, tail, fill):  # pragma: no cover - compiled
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
    """:func:`top2`'s top two from every posting of y_t counted into ``counts`` (zero on entry,
    sized for every interval; zeroed again on exit)."""
    scores_csr(ptr, post, y, counts)
    scores_linked(f_pool, f_next, f_head, f_tail, f_fill, y, counts)
    scores_linked(pool, nxt, head, tail, fill, y, counts)
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
def top2(y, lengths, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head, tail, fill,
         u_ptr, u_cells, limit, hints, inq, partial, touched, bucket):  # pragma: no cover - compiled
    """The best and runner-up candidates k < limit by s_k = |Y_k & y_t| (ties: lowest index),
    exactly as exhaustive scoring ranks them, without reading every posting. Returns (b1, s1, b2,
    s2, postings read, unions verified); b2 = -1 when limit < 2.

    The bound: after e of y_t's n lists (rarest first), an interval met in none of them has
    s_k <= n - e, so once n - e < s2 (the runner-up's score so far, first from the exactly scored
    ``hints``) no unseen interval can enter the top two; met ones are scored exactly while
    partial_k + (n - e) can reach s2 (steps 1-4 below).

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
    # bookkeeping: count every posting instead (plain increments; docs/performance.md)
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


# ----------------------------------------------------------------------- bit-sliced count
#: words per block of the dense rows (64 intervals a word): one block of the ten counter planes
#: (20 kB) stays in L1 while the query's rows stream through it, and each row's 2 kB run is long
#: enough for the hardware prefetcher (shorter blocks: docs/performance.md)
SLICE_WORDS = 256
SLICE_BLOCK = 64 * SLICE_WORDS
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
def set_dense_bits(dense, row_of, bits, interval):  # pragma: no cover - compiled
    """Mark ``interval`` in the dense row of every cell of ``bits`` that has one."""
    blk = interval // SLICE_BLOCK
    w = (interval >> 6) % SLICE_WORDS
    m = _ONE << np.uint64(interval & 63)
    for b in bits:
        r = row_of[b]
        if r >= 0:
            dense[blk, r, w] |= m


@njit(cache=True)
def fill_dense_row(b, row, dense, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head, tail,
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


@njit(cache=True, inline="always")
def _block_planes(dblk, rows, nw, planes):  # pragma: no cover - compiled
    """Count ``rows`` (dense rows of one block, padded to a multiple of 8 with the all-zero row 0)
    into ``planes``: SLICES bit planes of the first ``nw`` words, 8 rows at a time through a
    carry-save adder tree (64 intervals per machine word; the loops vectorise)."""
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
    for g in range(0, rows.shape[0], 8):
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


@njit(cache=True)
def top2_sliced(y, rows, sparse, dense, ptr, post, f_pool, f_next, f_head, f_tail, f_fill, pool, nxt, head,
                tail, fill, u_ptr, u_cells, limit, hints, inq, partial, touched):  # pragma: no cover - compiled
    """The top two of :func:`top2` (same order, same ties) from bit-sliced counts.

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
    planes = np.zeros((SLICES, SLICE_WORDS), np.uint64)
    looked = 0
    for blk in range((limit + SLICE_BLOCK - 1) // SLICE_BLOCK):
        nw = min(SLICE_WORDS, n_words - blk * SLICE_WORDS)  # words of this block below the limit
        _block_planes(dense[blk], rows, nw, planes)
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


@njit(cache=True)
def scores_sliced(rows, dense, limit, out):  # pragma: no cover - compiled
    """out[k] += the number of ``rows`` (dense rows, padded to a multiple of 8 with the all-zero
    row 0) that hold interval k, for every k < limit: :func:`top2_sliced`'s carry-save count,
    every lane then read out of the SLICES bit planes (every score, for the calibrated decision)."""
    n_words = (limit + 63) >> 6
    planes = np.zeros((SLICES, SLICE_WORDS), np.uint64)
    for blk in range((limit + SLICE_BLOCK - 1) // SLICE_BLOCK):
        nw = min(SLICE_WORDS, n_words - blk * SLICE_WORDS)
        _block_planes(dense[blk], rows, nw, planes)
        for w in range(nw):
            base = (blk * SLICE_WORDS + w) << 6
            lanes = min(64, limit - base)
            for s in range(SLICES):
                v = planes[s, w]
                if v == 0:
                    continue
                for lane in range(lanes):
                    out[base + lane] += np.int32((v >> np.uint64(lane)) & _ONE) << s
