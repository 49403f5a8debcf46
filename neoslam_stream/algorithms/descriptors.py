"""The descriptors of D's intervals: the finer copy of a place that re-ranks what the bits shortlisted.

B keeps each frame's centred features as int8 (``projector.descriptor``; ``BinaryCode``). A binary
code of 512 bits ranks places that differ a little (a corridor, a night scene) worse than the
features it came from: the projection and the binarisation each add noise as large as the gap
between the right place and the next best. So D shortlists its candidates by their cells, as the
paper does, and re-ranks the shortlist by the cosine of these descriptors (the usual two-stage
retrieval: binary codes to shortlist, a finer descriptor to decide). An interval's descriptor is
the mean of its frames' unit descriptors, kept as int8 with its norm; one row per indexed interval.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _int8_dots(rows: np.ndarray, slots: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out[i] = rows[slots[i]] . q, summed exactly in int32 (no float copy of the rows; |sum| <=
    127^2 n < 2^31 for n < 133 000)."""
    for i in range(slots.shape[0]):
        r = rows[slots[i]]
        acc = np.int32(0)
        for j in range(q.shape[0]):
            acc += np.int32(r[j]) * np.int32(q[j])
        out[i] = acc


def _as_int8(v: np.ndarray) -> np.ndarray:
    peak = float(np.abs(v).max()) if v.size else 0.0
    return np.zeros(v.shape, np.int8) if peak == 0.0 else np.rint(v * (127.0 / peak)).astype(np.int8)


class IntervalDescriptors:
    """One int8 row per indexed interval (its slot in D's index) and the sum of the open interval's
    unit descriptors. A frame without a descriptor adds nothing; an interval none of whose frames
    had one gets a zero row, which :meth:`cosines` reports as missing (NaN)."""

    def __init__(self) -> None:
        self._rows = np.zeros((0, 0), np.int8)
        self._norms = np.zeros(0, np.float64)
        self.n = 0
        self._sum: np.ndarray | None = None
        #: the recent frames' (stamp, descriptor), back to the newest at least ``ago_s`` old
        self._recent: deque[tuple[float, np.ndarray]] = deque()

    def open_interval(self) -> None:
        """A new interval opens: its frames' descriptors are summed afresh."""
        self._sum = None

    def note_view(self, stamp: float, descriptor: np.ndarray, keep_s: float) -> None:
        """Keep a frame's descriptor for :meth:`view_ago_cosine`, and the views back to the newest
        at least ``keep_s`` older than it."""
        while len(self._recent) > 1 and self._recent[1][0] <= stamp - keep_s:
            self._recent.popleft()
        self._recent.append((float(stamp), np.asarray(descriptor, dtype=np.int8).copy()))

    def view_ago_cosine(self, descriptor: np.ndarray, stamp: float, ago_s: float) -> float | None:
        """The cosine of a frame's descriptor with the view ``ago_s`` seconds before it on the way
        here (the newest kept view at least that old; None before there is one): how alike two views
        of one place are on this visit, at the distance that still counts as the same place."""
        q = np.asarray(descriptor, dtype=np.float32)
        older = [d for t, d in self._recent if t <= stamp - ago_s]
        if not older or older[-1].shape != q.shape:
            return None
        ref = older[-1].astype(np.float32)
        den = float(np.linalg.norm(ref)) * float(np.linalg.norm(q))
        return float(ref @ q) / den if den else None

    def add_frame(self, descriptor: np.ndarray | None) -> None:
        """One frame of the open interval (``descriptor``: int8, or None)."""
        if descriptor is None:
            return
        d = np.asarray(descriptor, dtype=np.float32)
        norm = float(np.linalg.norm(d))
        if norm == 0.0:
            return
        self._sum = d / norm if self._sum is None else self._sum + d / norm

    def open_row(self) -> np.ndarray | None:
        """The open interval's row as it stands (None: none of its frames had a descriptor)."""
        return _as_int8(self._sum) if self._sum is not None else None

    def close_interval(self, slot: int, row: np.ndarray | None = None, given: bool = False) -> None:
        """The open interval (``given``: the interval whose :meth:`open_row` was ``row``, kept
        while it waited) enters D's index as ``slot`` (slots come in order: ``slot == n``). An
        interval merged into a place never comes here: the place keeps the row of its first visit,
        as it keeps that visit's union."""
        if not given:
            row = self.open_row()
        if row is not None and self._rows.shape[1] not in (0, row.shape[0]):
            raise ValueError(f"descriptor of length {row.shape[0]}, the intervals' have {self._rows.shape[1]}")
        width = row.shape[0] if row is not None else self._rows.shape[1]
        if slot >= self._rows.shape[0] or self._rows.shape[1] != width:
            grown = np.zeros((max(2 * self._rows.shape[0], slot + 1, 64), width), np.int8)
            if self._rows.shape[1] == width:
                grown[:self.n] = self._rows[:self.n]
            self._rows = grown
            self._norms = np.concatenate([self._norms, np.zeros(grown.shape[0] - self._norms.shape[0])])
        if row is not None:
            self._rows[slot] = row
            self._norms[slot] = float(np.linalg.norm(row.astype(np.float64)))
        self.n = slot + 1

    def new_session(self) -> None:
        """A new session: the recent views were the old stream's."""
        self._recent.clear()

    def cosines(self, descriptor: np.ndarray, slots: np.ndarray) -> np.ndarray:
        """The cosine of a frame's descriptor with the intervals at ``slots`` (NaN where either
        has none)."""
        q = np.ascontiguousarray(descriptor, dtype=np.int8)
        qn = float(np.linalg.norm(q.astype(np.float64)))
        out = np.full(len(slots), np.nan)
        if not qn or not self.n or self._rows.shape[1] != q.shape[0]:
            return out
        slots = np.asarray(slots, dtype=np.int64)
        norms = self._norms[slots]
        ok = norms > 0
        dots = np.empty(slots.shape[0], np.int64)
        _int8_dots(self._rows, slots, q, dots)
        out[ok] = dots[ok] / (norms[ok] * qn)
        return out

    def vote(self, scores: np.ndarray, descriptor: np.ndarray, k: int) -> int | None:
        """Of the k best slots by ``scores``, the one whose score and descriptor cosine, each
        standardised over those k, sum highest (ties: the better score): the cells and the finer
        descriptor both vote, so a view that only the descriptor finds alike (the same scene seen
        from elsewhere) does not win on it alone. None when no candidate has a descriptor."""
        top = np.argsort(-scores, kind="stable")[:k]
        cos = self.cosines(descriptor, top)
        ok = ~np.isnan(cos)
        if not ok.any():
            return None
        top, c, s = top[ok], cos[ok], scores[top[ok]]
        votes = (c - c.mean()) / (c.std() + 1e-9) + (s - s.mean()) / (s.std() + 1e-9)
        return int(top[np.argmax(votes)])

    def sampled(self, scores: np.ndarray, descriptor: np.ndarray, k: int,
                n: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The k best slots by ``scores`` then n others spread evenly over the rest (a sample of
        how alike unrelated places look), with their cosines; slots without a descriptor dropped.
        Returns (slots, cosines, how many of the first k remain, which come first)."""
        order = np.argsort(-scores, kind="stable")
        top, rest = order[:k], np.sort(order[k:])
        if rest.shape[0] > n:
            rest = rest[np.linspace(0, rest.shape[0] - 1, n).astype(np.int64)]
        cand = np.concatenate([top, rest])
        cos = self.cosines(descriptor, cand)
        ok = ~np.isnan(cos)
        return cand[ok], cos[ok], int(ok[:top.shape[0]].sum())

    def warm_up(self) -> None:
        """Compile the dot-product kernel now, not on a live frame."""
        _int8_dots(np.zeros((1, 1), np.int8), np.zeros(1, np.int64), np.zeros(1, np.int8), np.zeros(1, np.int64))

    def state_dict(self) -> dict[str, Any]:
        return {"rows": self._rows[:self.n].copy(), "open": None if self._sum is None else self._sum.copy(),
                "recent_stamps": np.array([t for t, _ in self._recent], np.float64),
                "recent": [d for _, d in self._recent]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        rows = np.asarray(st["rows"], dtype=np.int8)
        self.n = rows.shape[0]
        self._rows = rows.reshape(self.n, rows.shape[1] if rows.ndim == 2 else 0).copy()
        self._norms = np.linalg.norm(self._rows.astype(np.float64), axis=1)
        self._sum = None if st["open"] is None else np.asarray(st["open"], dtype=np.float32).copy()
        self._recent = deque((float(t), np.asarray(d, dtype=np.int8).copy())
                             for t, d in zip(st["recent_stamps"], st["recent"], strict=True))
