"""The inverted interval index of stage D: for a query y_t, the best and runner-up interval k by
s_k = |Y_k & y_t| (ties: lowest index) without scoring every interval.

Postings (cell -> intervals whose union Y_k holds it) are appended to linked blocks (O(1), memory
follows the postings); once those outgrow a quarter of the contiguous CSR part they are merged
into it on a background thread, while scores read every part, so results never depend on when a
merge finishes. Cells whose lists grow long also get dense rows (one bit per interval). Per query
a cost model picks the bounded posting-list search or the bit-sliced count over the dense rows;
both give exactly the top two of counting every posting, which ``exhaustive = True`` does (the
reference). Each union's sorted cells are stored too, for exact scores of single candidates.
Kernels: :mod:`.interval_kernels` and :mod:`.interval_sliced_kernels`; speed: docs/frontend.md,
docs/performance.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import interval_kernels as kern
from . import interval_sliced_kernels as sliced_kern
from .interval_kernels import BLOCK
from .interval_sliced_kernels import SLICE_BLOCK, SLICE_WORDS, SLICES

#: the linked part is merged into the CSR part once it holds this many postings and more than a
#: quarter of the CSR part (512 intervals of 512 cells: no compaction at all for small maps)
COMPACT_MIN = 262144
#: a cell gets a dense row (one bit per interval) once its posting list holds this many intervals
#: and at least 1/32 of them: from then on the row is no larger than the list it mirrors
DENSE_MIN = 1024


def _row_words(n_dense: int, limit: int) -> int:
    """Row-words a bit-sliced count reads: the query's dense rows, padded to 8, times the words
    holding the intervals below ``limit``."""
    return (n_dense + 7) // 8 * 8 * ((limit + 63) // 64)


class IntervalIndex:
    """Posting lists, union store and dense rows of the intervals 0..K-1 over ``sdr_size`` cells.

    The owner adds interval k's new cells with :meth:`post` and its sorted union with
    :meth:`store_union` (only the newest interval grows); :meth:`top2` answers a query.
    """

    def __init__(self, sdr_size: int) -> None:
        self.sdr_size = sdr_size
        #: True: count every posting (the reference the two searches are tested against)
        self.exhaustive = False
        #: None: each query takes the cheaper of the bounded posting-list search and the bit-sliced
        #: count (when y_t's cells have dense rows); True / False: always / never bit-sliced.
        #: Both give the exhaustive top two (tests/test_spatial_view.py).
        self.sliced: bool | None = None
        #: posting-list length from which a cell gets a dense row (with >= 1/32 of the intervals)
        self.dense_min = DENSE_MIN
        #: which search the last query used: "postings" or "sliced"
        self.last_path = "postings"
        #: how the last :meth:`all_scores` counted: "postings" or "sliced"
        self.last_count_path = "postings"
        #: postings read and unions verified by the last query's search (bench figures)
        self.last_search = (0, 0)
        #: background merges started
        self.merges = 0
        self._executor: Any = None
        # the last query's best and runner-up (and the newest candidates): scored first
        self._hints = np.full(6, -1, dtype=np.int64)
        self._scores = np.zeros(1024, dtype=np.int32)
        self.clear()

    def clear(self) -> None:
        """Forget every interval (the search settings above stay)."""
        n = self.sdr_size
        # compacted part: CSR offsets per bit and the postings
        self._ptr = np.zeros(n + 1, dtype=np.int64)
        self._post = np.zeros(0, dtype=np.int32)
        # posting-list length per bit (all parts): the bounded search reads the rarest lists first
        self._count = np.zeros(n, dtype=np.int64)
        # every union Y_k as sorted cells, one flat array (CSR by interval): exact s_k of a
        # candidate in O(|Y_k|). Only the newest interval grows, and it is stored last.
        self._u_ptr = np.zeros(1025, dtype=np.int64)
        self._u_cells = np.zeros(1 << 16, dtype=np.uint16 if n <= 65536 else np.int32)
        self._u_n = 0
        self._partial = np.zeros(1024, dtype=np.int32)
        self._touched = np.zeros(1024, dtype=np.int32)
        self._inq = np.zeros(n, dtype=np.uint8)
        # dense rows (bit-sliced part): row r of cell b = one bit per interval, in blocks of
        # SLICE_BLOCK intervals, block-major so that one block of every row is contiguous. Row 0
        # stays zero (it pads the query's rows to groups of 8); cells get rows when their lists grow
        # long (DENSE_MIN), which on real SDRs is most of them (docs/performance.md).
        self._row_of = np.full(n, -1, dtype=np.int32)
        self._dense = np.zeros((0, 1, SLICE_WORDS), dtype=np.uint64)
        self._n_dense = 1
        # an empty linked part stands for "no merge in progress" in the searches
        self._no_linked = (np.zeros((1, BLOCK), np.int32), np.full(1, -1, np.int32), np.full(n, -1, np.int32),
                           np.full(n, -1, np.int32), np.zeros(n, np.int32))
        self._reset_linked(1024)

    @property
    def n_intervals(self) -> int:
        """Intervals whose union is stored."""
        return self._u_n

    def union_sizes(self, limit: int) -> np.ndarray:
        """|Y_k| of the intervals k < limit."""
        return np.diff(self._u_ptr[:limit + 1])

    # ---------------------------------------------------------------- storage
    def store_union(self, k: int, cells: np.ndarray) -> None:
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

    def post(self, bits: np.ndarray, interval: int) -> None:
        """Append ``interval`` to the posting lists of ``bits`` (unique int32 cells new to its union)."""
        need = self._n_blocks + len(bits)
        if need > self._pool.shape[0]:
            cap = max(need, 2 * self._pool.shape[0])
            pool = np.zeros((cap, BLOCK), dtype=np.int32)
            pool[: self._n_blocks] = self._pool[: self._n_blocks]
            nxt = np.full(cap, -1, dtype=np.int32)
            nxt[: self._n_blocks] = self._next[: self._n_blocks]
            self._pool, self._next = pool, nxt
        self._n_blocks = kern.append_postings(self._pool, self._next, self._head, self._tail, self._fill,
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
            sliced_kern.set_dense_bits(self._dense, self._row_of, bits, interval)
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
            sliced_kern.fill_dense_row(int(b), r, self._dense, self._ptr, self._post, *frozen, *self._linked_arrays())

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
        same counts, so results do not depend on when the merge finishes; a query never waits
        for it."""
        from concurrent.futures import ThreadPoolExecutor

        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="svc-compact")
        frozen = self._linked_arrays()
        future = self._executor.submit(kern.compact, self._ptr, self._post, *frozen)
        self.merges += 1
        self._reset_linked(1024)
        self._frozen = (frozen, future)

    def _finish_background_merge(self) -> None:
        assert self._frozen is not None
        self._ptr, self._post = self._frozen[1].result()
        self._frozen = None

    def compact(self) -> None:
        """Merge every linked posting into the contiguous CSR part now (waits for a background
        merge in progress first)."""
        if self._frozen is not None:
            self._finish_background_merge()
        if self._linked_postings == 0:
            return
        self._ptr, self._post = kern.compact(self._ptr, self._post, *self._linked_arrays())
        self._reset_linked(1024)

    # ---------------------------------------------------------------- queries
    def all_scores(self, y: np.ndarray, rows: bool | None = None) -> np.ndarray:
        """s_k = |Y_k & y_t| of every interval, from the whole index; a scratch array, zeroed again
        at the next call. The cells with dense rows are counted bit-sliced (64 intervals a word)
        when that reads less than their posting lists (the cost model of :meth:`top2_bounded`;
        ``rows`` True / False: always / never, None: ``sliced``'s setting), the others posting by
        posting: the same counts either way (``last_count_path`` says which ran)."""
        k_all = self._u_n
        if self._scores.shape[0] < k_all:
            self._scores = np.zeros(max(k_all, 2 * self._scores.shape[0]), dtype=np.int32)
        scores = self._scores[:k_all]
        scores[:] = 0
        use = self.sliced if rows is None else rows
        row = self._row_of[y]
        dense = row > 0
        n_dense = int(dense.sum())
        sliced = use is not False and 0 < n_dense <= (1 << SLICES) - 8 and k_all > 0
        if sliced and use is None:  # the cost model of top2_bounded, the sparse cells counted either way
            sliced = 3 * _row_words(n_dense, k_all) < int(self._count[y[dense]].sum())
        if sliced:
            sliced_kern.scores_sliced(self._query_rows(row[dense]), self._dense, k_all, scores)
            y = y[~dense]
        kern.scores_csr(self._ptr, self._post, y, scores)
        if self._frozen is not None:
            kern.scores_linked(*self._frozen[0], y, scores)
        if self._linked_postings:
            kern.scores_linked(self._pool, self._next, self._head, self._tail, self._fill, y, scores)
        self.last_count_path = "sliced" if sliced else "postings"
        return scores

    def top2(self, y: np.ndarray, limit: int) -> tuple[int, int, int, int]:
        """(best, its score, runner-up, its score) among the intervals k < limit (limit >= 1) for
        the sorted unique int32 cells ``y``; the runner-up is -1, 0 when limit is 1."""
        if self.exhaustive:
            return self.top2_exhaustive(y, limit)
        return self.top2_bounded(y, limit)

    def normalised_scores(self, y: np.ndarray, limit: int) -> np.ndarray:
        """s_k |y_t| / max(|Y_k|, |y_t|) of the slots < limit (a new array): a long interval's
        union, which overlaps everything a little, is no hub (``union_normalised``)."""
        n = len(y)
        return self.all_scores(y)[:limit] * (n / np.maximum(self.union_sizes(limit), n))

    def top2_normalised(self, y: np.ndarray, limit: int) -> tuple[int, float, int, float]:
        """The top two slots < limit by :meth:`normalised_scores` (ties: lowest index), with their
        normalised scores."""
        norm = self.normalised_scores(y, limit)
        best = int(np.argmax(norm))  # first maximum = lowest index
        best_score = float(norm[best])
        second, second_score = -1, 0.0
        if limit > 1:
            norm[best] = -1.0
            second = int(np.argmax(norm))
            second_score = float(norm[second])
        return best, best_score, second, second_score

    def top2_exhaustive(self, y: np.ndarray, limit: int) -> tuple[int, int, int, int]:
        """Every s_k from the whole index, every posting counted: the reference."""
        cand = self.all_scores(y, rows=False)[:limit]
        best = int(np.argmax(cand))  # first maximum = lowest index
        best_score = int(cand[best])
        second, second_score = -1, 0
        if limit > 1:
            cand[best] = -1  # scores are zeroed before the next query
            second = int(np.argmax(cand))
            second_score = int(cand[second])
        return best, best_score, second, second_score

    def top2_bounded(self, y: np.ndarray, limit: int) -> tuple[int, int, int, int]:
        """The same top two as :meth:`top2_exhaustive`, from the bounded posting-list search or
        the bit-sliced count, whichever the cost model (or ``sliced``) picks."""
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
            # cost model: a row-word of the bit-sliced count, a sparse posting and a posting the
            # bounded search could read cost 3 : 10 : 1 (measured on one machine: docs/performance.md)
            sliced = n_dense > 0 and 3 * _row_words(n_dense, limit) + 10 * sparse_postings < int(lengths.sum())
        if sliced:
            read = sparse_postings
            b1, s1, b2, s2, verified = sliced_kern.top2_sliced(
                y, self._query_rows(rows[dense]), y[~dense], self._dense, self._ptr, self._post, *frozen,
                self._pool, self._next, self._head, self._tail, self._fill, self._u_ptr, self._u_cells, limit, h,
                self._inq, self._partial, self._touched)
        else:
            b1, s1, b2, s2, read, verified = kern.top2(
                y, lengths, self._ptr, self._post, *frozen, self._pool, self._next, self._head, self._tail,
                self._fill, self._u_ptr, self._u_cells, limit, h, self._inq, self._partial, self._touched,
                np.zeros(y.shape[0] + 2, np.int64))
        self.last_path = "sliced" if sliced else "postings"
        self.last_search = (int(read), int(verified))
        h[0], h[2] = b1, b2
        return int(b1), int(s1), int(b2), int(s2)

    def _query_rows(self, rows: np.ndarray) -> np.ndarray:
        """A query's dense rows as the bit-sliced kernels take them: sorted, padded to a multiple of
        8 with the all-zero row 0; every interval's block allocated (even without any dense row)."""
        self._dense_capacity(self._u_n - 1, 0)
        r = np.sort(rows).astype(np.int64)
        return np.concatenate([r, np.zeros(-len(r) % 8, np.int64)])

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel now, on a throw-away index of the same
        size: the posting-list search on linked then compacted postings, the exhaustive count, and
        dense rows with the bit-sliced count, of the top two and of every score (on real SDRs they
        start after thousands of intervals, where compiling them would stall a live frame)."""
        warm = IntervalIndex(self.sdr_size)
        ys = [np.unique((np.arange(64, dtype=np.int64) + 64 * i) % self.sdr_size).astype(np.int32)
              for i in range(6)]

        def add(k: int, y: np.ndarray) -> None:
            warm.post(y, k)
            warm.store_union(k, y)
            warm.top2_bounded(y, k + 1)

        for k, y in enumerate(ys):
            add(k, y)
        warm.compact()
        warm.top2_bounded(ys[0], len(ys))
        warm.top2_exhaustive(ys[0], len(ys))
        warm.dense_min = 1
        warm.sliced = True
        add(len(ys), ys[0])
        add(len(ys) + 1, ys[1])
        warm.all_scores(ys[0])  # the bit-sliced count of every score
