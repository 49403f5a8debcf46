"""What the host machine itself did during a run, for ``report.json``'s ``host``.

A stage's service time tau_i on a shared virtual machine moves by the hour: the hypervisor takes
CPU time from the guest (steal) and other software loads the cores. A report that says how much
was taken shows those two causes of a slow run; a core that is slower for the same CPU time (its
clock, caches or a physical core shared with other guests) does not show here, so a figure of one
hour is compared with another's only with that said. Linux's /proc/stat and load average;
elsewhere the figures are null.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: the column of /proc/stat's ``cpu`` line that counts stolen time (after the label: user, nice,
#: system, idle, iowait, irq, softirq, steal)
STEAL_COLUMN = 7


def steal_ticks(stat_text: str) -> int | None:
    """The machine's stolen CPU time in clock ticks, from /proc/stat's first (all-CPU) line;
    None when the line has no steal column (kernels before 2.6.11) or is not there."""
    for line in stat_text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            values = fields[1:]
            return int(values[STEAL_COLUMN]) if len(values) > STEAL_COLUMN else None
    return None


@dataclass(frozen=True)
class HostSample:
    """One reading of the host: monotonic time, stolen ticks (or None), 1-minute load average."""

    t: float
    steal: int | None
    load_1min: float | None


def sample_host(stat_path: str | Path = "/proc/stat") -> HostSample:
    """The host now; a figure the platform cannot give is None (never an error)."""
    try:
        steal = steal_ticks(Path(stat_path).read_text())
    except (OSError, ValueError):
        steal = None
    try:
        load = os.getloadavg()[0]
    except (OSError, AttributeError):
        load = None
    return HostSample(time.monotonic(), steal, load)


def host_usage(start: HostSample, end: HostSample, ticks_per_s: float | None = None) -> dict[str, Any]:
    """``report.json``'s ``host``: the CPU seconds the hypervisor took from all cores between the
    two samples (``steal_s``), that as a fraction of the cores' time (``steal_share``), the load
    average before the run (``load_1min_before``: processes already running or waiting) and the
    CPU count."""
    cpus = os.cpu_count() or 1
    if ticks_per_s is None:
        try:
            ticks_per_s = float(os.sysconf("SC_CLK_TCK"))
        except (ValueError, OSError, AttributeError):
            ticks_per_s = 100.0
    steal_s = fraction = None
    if start.steal is not None and end.steal is not None:
        steal_s = round((end.steal - start.steal) / ticks_per_s, 2)
        wall = end.t - start.t
        fraction = round(steal_s / (wall * cpus), 4) if wall > 0 else None
    return {"cpus": cpus, "steal_s": steal_s, "steal_share": fraction, "load_1min_before": start.load_1min}
