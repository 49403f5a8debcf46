"""What a run counts per frame, in memory that does not grow with the run (the runtime's and the
algorithms' alike: this module imports neither).

The monitor and the supervisor each follow every frame that reaches the run's end: which frames
arrived (to count the loss by frame number) and how long each took (the report's latency
percentiles); visual odometry's typical speed is the median of every raw speed so far. Kept as a
Python set and lists of floats, the two processes grew by about 15 MB an hour each at 30 FPS, so a
robot running all day grew by hundreds of MB for its bookkeeping alone.

* :class:`FrameRanges`: a set of frame numbers as sorted ``[first, last]`` ranges. Frames arrive
  nearly in order, so an hour of them is one range per gap.
* :class:`LogHistogram`: values counted in bins of equal width on a log scale,
  ``BINS_PER_DECADE`` to a decade between ``LOW`` and ``HIGH``; a percentile is read back as the
  geometric centre of its bin, within 0.12 % of the value (0.0 for values at or below ``LOW``).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Iterator
from collections.abc import Set as AbcSet
from typing import Any

import numpy as np


class FrameRanges:
    """A set of frame numbers kept as sorted, disjoint, non-adjacent ``[first, last]`` ranges."""

    def __init__(self, frames: Iterable[int] = ()) -> None:
        self._starts: list[int] = []
        self._ends: list[int] = []
        self._count = 0
        self.update(frames)

    def add(self, frame: int) -> None:
        f = int(frame)
        starts, ends = self._starts, self._ends
        if ends and f == ends[-1] + 1:  # the usual case: the next frame in order
            ends[-1] = f
            self._count += 1
            return
        i = bisect.bisect_right(starts, f) - 1  # the range starting at or before f
        if i >= 0 and f <= ends[i]:
            return
        joins_left = i >= 0 and ends[i] == f - 1
        joins_right = i + 1 < len(starts) and starts[i + 1] == f + 1
        if joins_left and joins_right:
            ends[i] = ends[i + 1]
            del starts[i + 1], ends[i + 1]
        elif joins_left:
            ends[i] = f
        elif joins_right:
            starts[i + 1] = f
        else:
            starts.insert(i + 1, f)
            ends.insert(i + 1, f)
        self._count += 1

    def update(self, frames: Iterable[int]) -> None:
        for f in frames:
            self.add(f)

    def add_range(self, first: int, last: int) -> None:
        """Every frame from ``first`` to ``last``, both included."""
        for f in range(int(first), int(last) + 1):
            self.add(f)

    def copy(self) -> FrameRanges:
        out = FrameRanges()
        out._starts, out._ends, out._count = list(self._starts), list(self._ends), self._count
        return out

    def ranges(self) -> list[list[int]]:
        """The frames as sorted ``[first, last]`` ranges (a copy)."""
        return [[a, b] for a, b in zip(self._starts, self._ends, strict=True)]

    def __contains__(self, frame: object) -> bool:
        if not isinstance(frame, (int, np.integer)):
            return False
        i = bisect.bisect_right(self._starts, int(frame)) - 1
        return i >= 0 and int(frame) <= self._ends[i]

    def __len__(self) -> int:
        return self._count

    def __eq__(self, other: object) -> bool:
        """Equal to another FrameRanges, or to a set, holding the same frames."""
        if isinstance(other, FrameRanges):
            return self._starts == other._starts and self._ends == other._ends
        if isinstance(other, AbcSet):
            return len(other) == self._count and all(f in self for f in other)
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]  # mutable, as a set

    def __iter__(self) -> Iterator[int]:
        for a, b in zip(self._starts, self._ends, strict=True):
            yield from range(a, b + 1)


class LogHistogram:
    """Counts of positive values on a log scale, for percentiles in constant memory. Values at or
    below ``LOW`` (zero, or a latency made negative by a clock that stepped back) count as 0.0,
    values above ``HIGH`` in the last bin (a latency lies between a microsecond and a quarter of an
    hour)."""

    LOW, HIGH, BINS_PER_DECADE = 1e-6, 1e3, 1000

    def __init__(self) -> None:
        self.counts = np.zeros(round(math.log10(self.HIGH / self.LOW) * self.BINS_PER_DECADE), dtype=np.int64)
        #: values at or below LOW
        self.below = 0
        self.n = 0

    def add(self, value: float) -> None:
        v = float(value)
        if math.isnan(v):
            return
        self.n += 1
        if v <= self.LOW:
            self.below += 1
            return
        k = math.floor(math.log10(v / self.LOW) * self.BINS_PER_DECADE)
        self.counts[min(k, len(self.counts) - 1)] += 1

    def __len__(self) -> int:
        return self.n

    def state(self) -> dict[str, Any]:
        return {"counts": self.counts.copy(), "below": self.below}

    def load(self, st: dict[str, Any]) -> None:
        counts = np.asarray(st["counts"], dtype=np.int64)
        if counts.shape != self.counts.shape:
            raise ValueError(f"a histogram of {counts.size} bins, this one has {self.counts.size}")
        self.counts, self.below = counts.copy(), int(st["below"])
        self.n = int(self.counts.sum()) + self.below

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0-100) as the geometric centre of the bin holding the value of
        rank q/100 * (n - 1) (np.percentile's nearest rank below); 0.0 when empty."""
        if not self.n:
            return 0.0
        rank = math.floor(q / 100.0 * (self.n - 1))
        if rank < self.below:
            return 0.0
        k = int(np.searchsorted(np.cumsum(self.counts), rank - self.below, side="right"))
        return self.LOW * 10 ** ((k + 0.5) / self.BINS_PER_DECADE)
