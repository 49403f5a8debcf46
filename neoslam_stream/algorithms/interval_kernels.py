"""The numba kernels of the interval index (:mod:`.interval_index`), on arrays the index owns.

Posting lists (bit -> intervals whose union Y_k holds it, sorted by interval id) live in linked
blocks of BLOCK entries and in a CSR part; ``compact`` merges them. Dense rows hold one bit per
interval for cells with long lists. Two searches give the best and runner-up interval by
s_k = |Y_k & y_t|, ties to the lowest index, exactly as scoring every interval would:
``top2`` reads posting lists rarest first under score bounds; ``top2_sliced``
(:mod:`.interval_sliced_kernels`) adds dense rows with a carry-save adder tree into bit planes.
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
