"""The run folder's per-frame and per-place numbers (nodes/run_numbers.py): a spilled store gives
back exactly the rows appended, holds one block in memory, survives a failed write and leaves no
file at close; the keyed store is a sorted map whatever order its keys come in."""

from __future__ import annotations

import numpy as np
import pytest

from neoslam_stream.nodes import run_numbers
from neoslam_stream.nodes.run_numbers import BLOCK, KeyedNumbers, NumberRows


def _rows(n: int, start: int = 0) -> list[tuple[float, ...]]:
    return [(float(f), f * 0.1, f % 7, f * 0.5, -f * 0.25, 1.0) for f in range(start, start + n)]


def test_spilled_rows_come_back_whole_and_memory_holds_one_block(tmp_path):
    rows = NumberRows(6, np.array(_rows(10)))
    rows.spill_to(tmp_path / ".local.f64")
    for r in _rows(3 * BLOCK + 5, start=10):
        rows.append(r)
    assert rows.n == 3 * BLOCK + 15
    np.testing.assert_array_equal(rows.rows(), np.array(_rows(3 * BLOCK + 15)))
    assert rows._a.shape[0] == BLOCK  # noqa: SLF001 - the point of spilling
    # the 10 rows held when it spilled, then each full block
    assert (tmp_path / ".local.f64").stat().st_size == (10 + 3 * BLOCK) * 6 * 8
    rows.discard()
    assert not (tmp_path / ".local.f64").exists()


def test_latest_by_frame_keeps_each_frames_last_row_across_file_and_memory(tmp_path):
    rows = NumberRows(2)
    rows.spill_to(tmp_path / "n.f64")
    for f in range(BLOCK):
        rows.append((f, 1.0))
    rows.append((5, 2.0))  # a frame again (a restart's replay): its latest row counts
    got = rows.latest_by_frame()
    assert got.shape == (BLOCK, 2) and got[5, 1] == 2.0 and got[6, 1] == 1.0
    np.testing.assert_array_equal(got[:, 0], np.arange(BLOCK))


def test_a_failed_write_keeps_the_rows_in_memory_and_writes_them_later(tmp_path, monkeypatch):
    rows = NumberRows(1)
    rows.spill_to(tmp_path / "n.f64")
    real_open = open
    failing = {"on": True}

    def flaky_open(path, mode="r", *a, **k):
        if failing["on"] and str(path).endswith("n.f64") and "+" in mode:
            raise OSError(28, "No space left on device")
        return real_open(path, mode, *a, **k)

    monkeypatch.setattr("builtins.open", flaky_open)
    for f in range(2 * BLOCK):  # the first block's write fails: the store grows instead
        rows.append((f,))
    assert rows._a.shape[0] == 2 * BLOCK  # noqa: SLF001
    failing["on"] = False
    for f in range(2 * BLOCK, 2 * BLOCK + 3):  # the next full store is written whole
        rows.append((f,))
    np.testing.assert_array_equal(rows.rows()[:, 0], np.arange(2 * BLOCK + 3))
    assert (tmp_path / "n.f64").stat().st_size == 2 * BLOCK * 8


def test_an_unwritable_folder_leaves_the_rows_in_memory(tmp_path):
    rows = NumberRows(1)
    rows.spill_to(tmp_path / "missing" / "n.f64")
    for f in range(BLOCK + 1):
        rows.append((f,))
    assert rows.path is None and rows.n == BLOCK + 1


@pytest.mark.parametrize("order", ["increasing", "shuffled"])
def test_keyed_numbers_is_a_sorted_map(order):
    keys = list(range(0, 3000, 3))
    if order == "shuffled":
        np.random.default_rng(0).shuffle(keys)
    store, ref = KeyedNumbers(2), {}
    for k in keys:
        store.set(k, (k * 2.0, -k))
        ref[k] = (k * 2.0, -k)
    store.set(3, (9.0, 9.0))  # replaced, not added
    ref[3] = (9.0, 9.0)
    assert len(store) == len(ref)
    assert all(store.get(k) == v for k, v in ref.items())
    assert store.get(1) is None and 1 not in store and 3 in store
    items = store.items()
    assert items[:, 0].tolist() == sorted(ref)
    again = KeyedNumbers(2, items)  # a checkpoint's arrays restore the same map
    assert all(again.get(k) == v for k, v in ref.items())


def test_module_block_is_what_memory_holds():
    assert run_numbers.BLOCK == BLOCK > 0
