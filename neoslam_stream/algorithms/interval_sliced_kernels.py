"""The bit-sliced count of the interval index (:mod:`.interval_index`): dense rows hold one bit per
interval for cells with long posting lists, and ``top2_sliced`` adds a query's rows 8 at a time
through a carry-save adder tree into bit planes (64 intervals a machine word), giving the best and
runner-up interval exactly as :func:`.interval_kernels.top2` does (same order, same ties).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .interval_kernels import BLOCK, _offer, _offer_hints, _walk_csr, _walk_linked

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
