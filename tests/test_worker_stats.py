"""A worker's service-time statistics (runtime/worker_stats.py ServiceStats): percentiles by their
definition, the bounded sample store, and the whole-run percentiles that the live stats refresh
only when the samples grew by REFRESH_GROWTH (their cost grows with the samples) while the final
stats are exact."""

from __future__ import annotations

import pytest

from neoslam_stream.runtime.worker_stats import ServiceStats


def _filled(values_ms: list[float], cls: type[ServiceStats] = ServiceStats) -> ServiceStats:
    s = cls()
    for v in values_ms:
        s.add(v / 1e3, 2 * v / 1e3)  # queueing time: twice the service time
    return s


def test_percentiles_of_one_to_one_hundred_ms_by_hand():
    class Recent10(ServiceStats):
        RECENT = 10

    s = _filled([float(v) for v in range(1, 101)], Recent10)
    got = s.summary(exact=True)
    # linear interpolation between order statistics: rank q/100 * (n - 1) from the smallest
    assert got["tau_p50_ms"] == pytest.approx(50.5)  # between 50 and 51
    assert got["tau_p95_ms"] == pytest.approx(95.05)  # rank 94.05: 95 + 0.05
    assert got["queue_p50_ms"] == pytest.approx(101.0) and got["queue_p95_ms"] == pytest.approx(190.1)
    assert got["tau_mean_ms"] == pytest.approx(50.5) and got["tau_max_ms"] == pytest.approx(100.0)
    # the newest ten: 91..100
    assert got["tau_recent_p50_ms"] == pytest.approx(95.5) and got["tau_recent_p95_ms"] == pytest.approx(99.55)


def test_no_sample_gives_zeros():
    assert set(ServiceStats().summary().values()) == {0.0}


def test_the_store_drops_its_older_half_when_full():
    class Small(ServiceStats):
        MAX_SAMPLES = 10

    s = _filled([float(v) for v in range(1, 26)], Small)
    # the rule applied by hand: a full store (10) keeps its newest 5, then takes the new sample
    held: list[float] = []
    for v in range(1, 26):
        if len(held) >= 10:
            held = held[5:]
        held.append(v / 1e3)
    assert list(s.tau) == pytest.approx(held) and list(s.wait) == pytest.approx([2 * h for h in held])
    assert held == pytest.approx([v / 1e3 for v in range(16, 26)])
    # the mean and maximum cover every sample, the percentiles the held ones
    got = s.summary(exact=True)
    assert got["tau_mean_ms"] == pytest.approx(13.0) and got["tau_max_ms"] == pytest.approx(25.0)
    assert got["tau_p50_ms"] == pytest.approx(20.5)


def test_live_whole_run_percentiles_refresh_after_a_growth_and_final_ones_are_exact():
    s = _filled([float(v) for v in range(1, 101)])
    assert s.summary()["tau_p50_ms"] == pytest.approx(50.5)  # the first live summary computes them
    grow = int(100 * ServiceStats.REFRESH_GROWTH)  # 12 samples: n = 112 is within the growth
    for v in range(101, 101 + grow):
        s.add(v / 1e3, 0.0)
    live, exact = s.summary(), s.summary(exact=True)
    assert exact["tau_p50_ms"] == pytest.approx(56.5)  # 1..112
    assert live["tau_p50_ms"] == pytest.approx(50.5)  # not yet refreshed
    # the recent window is always current: the newest 1000 are all 112 samples here
    assert live["tau_recent_p50_ms"] == pytest.approx(56.5)
    s2 = _filled([float(v) for v in range(1, 101)])
    s2.summary()
    for v in range(101, 101 + grow + 1):  # n = 113 > 100 * 1.125: refreshed
        s2.add(v / 1e3, 0.0)
    assert s2.summary()["tau_p50_ms"] == pytest.approx(57.0)  # 1..113
