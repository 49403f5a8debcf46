"""runtime/tallies.py: the per-frame records of a run in memory that does not grow with it."""

import numpy as np
import pytest

from neoslam_stream.runtime.collector import FinalTracker
from neoslam_stream.tallies import FrameRanges, LogHistogram


def test_frame_ranges_is_a_set_of_frames():
    rng = np.random.default_rng(1)
    frames = rng.permutation(np.concatenate([np.arange(0, 50), np.arange(60, 61), np.arange(70, 120)]))
    fr, ref = FrameRanges(), set()
    for f in list(frames) + [3, 60, 119]:  # in any order, some twice
        fr.add(int(f))
        ref.add(int(f))
        assert len(fr) == len(ref)
    assert sorted(fr) == sorted(ref) and list(fr) == sorted(ref)
    assert all(f in fr for f in ref) and not any(f in fr for f in (-1, 50, 59, 61, 69, 120))
    assert fr.ranges() == [[0, 49], [60, 60], [70, 119]]
    fr.add_range(50, 59)  # fills the gap: the three become one with the next
    assert fr.ranges() == [[0, 60], [70, 119]] and len(fr) == 111
    fr.add(61)
    fr.add(69)
    assert fr.ranges() == [[0, 61], [69, 119]]
    copy = fr.copy()
    assert copy == fr and fr == set(fr) and fr != set(fr) | {200} and fr != {0}
    copy.add(65)
    assert 65 in copy and 65 not in fr and copy != fr


def test_an_hour_of_frames_in_order_is_one_range():
    fr = FrameRanges(range(108_000))
    assert fr.ranges() == [[0, 107_999]] and len(fr) == 108_000


def test_log_histogram_percentiles_are_within_a_bin_of_the_exact_ones():
    values = np.random.default_rng(2).lognormal(np.log(0.02), 0.6, 20_000)  # latencies around 20 ms
    h = LogHistogram()
    for v in values:
        h.add(v)
    width = 10 ** (1 / LogHistogram.BINS_PER_DECADE)  # one bin: a factor of 1.0023
    for q in (50, 95, 99):
        exact = np.percentile(values, q, method="lower")
        assert exact / width <= h.percentile(q) <= exact * width
    assert len(h) == 20_000 and LogHistogram().percentile(50) == 0.0
    h = LogHistogram()
    for v in (-0.5, 0.0, 1e9, float("nan")):  # a clock stepping back, a stuck one, an absurd value
        h.add(v)
    assert len(h) == 3 and h.percentile(0) == h.percentile(50) == 0.0 and h.percentile(100) >= LogHistogram.HIGH / 1.01
    again = LogHistogram()
    again.load(h.state())
    assert len(again) == 3 and again.percentile(100) == h.percentile(100)


def test_the_final_tracker_counts_frames_and_latencies_without_keeping_them():
    t = FinalTracker(entry_stages={"A"})
    for f in range(1000):
        t.add(f, [["A", 100.0]], 100.0 + 0.01 * (1 + f % 3))
    t.add(5, [["A", 100.0]], 200.0)  # a duplicate is not counted again
    assert len(t.frames) == 1000 and t.frames.ranges() == [[0, 999]] and t.messages == 1001
    assert t.latencies.percentile(50) == pytest.approx(0.02, rel=3e-3)
