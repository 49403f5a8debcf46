"""What the run folder keeps of every frame and every place, as numbers that do not grow in memory.

A patrol's run lasts all day, so what the writer keeps per frame or per interval must not sit in
memory as Python objects (a dict entry and its tuple take ~300 bytes; 8 bytes a number here):

* :class:`NumberRows`: rows of numbers per frame (a pose in its experience's frame for
  trajectory_map.tum, outputs.mcap's template and pose), read back once at the end. In memory they
  grow by doubling; once :meth:`NumberRows.spill_to` names a file (the run folder's writer does
  when its files are open) every full block of :data:`BLOCK` rows is written there, and memory
  holds one block, whatever the run's length. The file is the writer's scratch: removed at close.
* :class:`KeyedNumbers`: a map from an int key (a template, an interval, a frame) to a few numbers
  (its first frame; a place's true x, y), in sorted arrays: keys come in increasing order, so an
  entry is appended; a key out of order (a restart's replayed frames) is inserted.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger("neoslam.recorder")

#: rows a spilled :class:`NumberRows` holds in memory before it writes them to its file
BLOCK = 4096


class NumberRows:
    """Rows of ``width`` numbers (float64): in a store grown by doubling, or, once spilled, in a file
    and one block in memory (module docstring)."""

    def __init__(self, width: int, rows: np.ndarray | None = None) -> None:
        rows = np.zeros((0, width)) if rows is None else np.asarray(rows, dtype=np.float64).reshape(-1, width)
        self.width = width
        self._a = np.zeros((max(1024, 2 * rows.shape[0]), width))
        self._a[:rows.shape[0]] = rows
        self._k = rows.shape[0]  # rows in memory
        self.path: Path | None = None
        self._in_file = 0  # rows in the file, before those in memory

    @property
    def n(self) -> int:
        return self._in_file + self._k

    def spill_to(self, path: Path) -> None:
        """Keep the rows in ``path`` from now on (those held now are written at once); where the
        file cannot be written, they stay in memory (nothing is lost) and it is tried again at
        the next full block."""
        if self.path is not None:
            return
        self.path = Path(path)
        try:
            self.path.write_bytes(b"")
        except OSError as exc:
            log.warning("recorder: %s not usable (%s); the run's per-frame numbers stay in memory", path, exc)
            self.path = None
            return
        self._flush()

    def _flush(self) -> bool:
        """Write the rows in memory after the file's (at their offset, so a failed write is simply
        written again); True when they are in the file."""
        assert self.path is not None
        try:
            with open(self.path, "r+b") as fh:
                fh.seek(self._in_file * self.width * 8)
                fh.write(self._a[:self._k].tobytes())
        except OSError:
            return False
        self._in_file += self._k
        self._k = 0
        if self._a.shape[0] != BLOCK:
            self._a = np.zeros((BLOCK, self.width))
        return True

    def append(self, row: tuple[float, ...]) -> None:
        if self._k == self._a.shape[0] and not (self.path is not None and self._flush()):
            self._a = np.concatenate([self._a, np.zeros_like(self._a)])
        self._a[self._k] = row
        self._k += 1

    def rows(self) -> np.ndarray:
        """Every row, in the order appended."""
        held = self._a[:self._k]
        if self.path is None or not self._in_file:
            return held.copy()
        disk = np.fromfile(self.path, dtype=np.float64, count=self._in_file * self.width)
        return np.concatenate([disk.reshape(-1, self.width), held])

    def latest_by_frame(self) -> np.ndarray:
        """The rows (column 0: the frame), the latest of each frame, in frame order."""
        rows = self.rows()
        _, last = np.unique(rows[::-1, 0], return_index=True)
        return rows[::-1][last]

    def discard(self) -> None:
        """Remove the file (the writer's close); the rows are gone with it."""
        if self.path is not None:
            try:
                os.unlink(self.path)
            except OSError:
                pass
        self.path, self._in_file, self._k = None, 0, 0


class KeyedNumbers:
    """int key -> ``width`` numbers, in arrays sorted by key (module docstring)."""

    def __init__(self, width: int, items: np.ndarray | None = None) -> None:
        items = np.zeros((0, 1 + width)) if items is None else np.asarray(items, dtype=np.float64).reshape(-1, 1 + width)
        items = items[np.argsort(items[:, 0], kind="stable")] if items.shape[0] else items
        self.width = width
        self._keys = np.zeros(max(1024, 2 * items.shape[0]), dtype=np.int64)
        self._vals = np.zeros((self._keys.size, width))
        self._n = items.shape[0]
        self._keys[:self._n] = items[:, 0].astype(np.int64)
        self._vals[:self._n] = items[:, 1:]

    def __len__(self) -> int:
        return self._n

    def _find(self, key: int) -> tuple[int, bool]:
        i = int(np.searchsorted(self._keys[:self._n], key))
        return i, i < self._n and int(self._keys[i]) == key

    def __contains__(self, key: int) -> bool:
        return self._find(int(key))[1]

    def get(self, key: int) -> tuple[float, ...] | None:
        i, found = self._find(int(key))
        return tuple(self._vals[i].tolist()) if found else None

    def set(self, key: int, values: tuple[float, ...]) -> None:
        """Set (or replace) ``key``'s numbers."""
        key = int(key)
        if self._n and key > int(self._keys[self._n - 1]):
            i, found = self._n, False
        else:
            i, found = self._find(key)
        if not found:
            if self._n == self._keys.size:
                self._keys = np.concatenate([self._keys, np.zeros_like(self._keys)])
                self._vals = np.concatenate([self._vals, np.zeros_like(self._vals)])
            self._keys[i + 1:self._n + 1] = self._keys[i:self._n].copy()
            self._vals[i + 1:self._n + 1] = self._vals[i:self._n].copy()
            self._keys[i] = key
            self._n += 1
        self._vals[i] = values

    def items(self) -> np.ndarray:
        """(key, numbers...) rows in key order (what a checkpoint keeps)."""
        return np.column_stack([self._keys[:self._n].astype(np.float64), self._vals[:self._n]])
