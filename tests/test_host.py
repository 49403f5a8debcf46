"""report.json's ``host``: the CPU the hypervisor took over a run, read from /proc/stat."""

import os

import pytest

from neoslam_stream.runtime.host import HostSample, host_usage, sample_host, steal_ticks

# /proc/stat's layout (proc(5)): after the label, user nice system idle iowait irq softirq steal ...
STAT = "cpu  4705 150 1120 16250 520 0 30 812 0 0\ncpu0 2352 75 560 8125 260 0 15 406 0 0\nintr 1 2\n"


def test_steal_is_the_eighth_column_of_the_all_cpu_line():
    assert steal_ticks(STAT) == 812  # the "cpu" line's, not cpu0's 406
    assert steal_ticks("cpu 1 2 3 4 5 6 7\n") is None  # a kernel without the steal column
    assert steal_ticks("intr 1 2\n") is None


def test_usage_over_a_run_by_hand():
    start, end = HostSample(10.0, 812, 1.5), HostSample(15.0, 1062, 0.2)
    got = host_usage(start, end, ticks_per_s=100.0)
    cpus = os.cpu_count() or 1
    # 250 ticks at 100 a second: 2.5 s taken over 5 s of the machine's cpus cores
    assert got["steal_s"] == pytest.approx(2.5)
    assert got["steal_share"] == pytest.approx(round(2.5 / (5.0 * cpus), 4))
    assert got["load_1min_before"] == 1.5 and got["cpus"] == cpus
    unknown = host_usage(HostSample(0.0, None, None), end)
    assert unknown["steal_s"] is None and unknown["steal_share"] is None


def test_sample_reads_the_given_stat_file(tmp_path):
    path = tmp_path / "stat"
    path.write_text(STAT)
    assert sample_host(path).steal == 812
    assert sample_host(tmp_path / "missing").steal is None  # not Linux: no figure, no error
