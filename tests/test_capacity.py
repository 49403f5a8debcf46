"""runtime.capacity: the rate a topology sustains on c cores, from worker service times (hand-worked)."""

import math

import pytest

from neoslam_stream.runtime.capacity import sustainable_rate, worker_service_ms

WORKERS = {"A": 25.0, "B": 6.0, "C": 1.5}  # ms per frame; 32.5 ms in all


def test_one_core_is_bound_by_the_total_cpu_time():
    # 32.5 ms in the workers + 2.5 ms of source, transport and monitor per frame
    r = sustainable_rate(WORKERS, cpu_ms_per_frame=35.0, cores=1)
    assert r["bound"] == "cores" and r["rate_hz"] == pytest.approx(1000 / 35)  # 28.6 Hz


def test_enough_cores_leave_the_slowest_worker():
    for cores in (2, 4, 16):
        r = sustainable_rate(WORKERS, cpu_ms_per_frame=35.0, cores=cores)
        assert r["bound"] == "worker" and r["bottleneck"] == "A"
        assert r["rate_hz"] == pytest.approx(40.0)  # 1 / 25 ms
    # the cores' bound grows linearly: 2 cores give 2000 / 35 Hz
    assert sustainable_rate(WORKERS, 35.0, 2)["cores_bound_hz"] == pytest.approx(2000 / 35)


def test_one_worker_hosting_every_stage_is_the_monolithic_topology():
    mono = {"monolithic": sum(WORKERS.values())}
    assert sustainable_rate(mono, 35.0, 1)["rate_hz"] == pytest.approx(1000 / 35)
    # more cores cannot help one process serving the stages in sequence
    assert sustainable_rate(mono, 35.0, 8)["rate_hz"] == pytest.approx(1000 / 32.5)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError):
        sustainable_rate({}, 35.0, 2)
    with pytest.raises(ValueError):
        sustainable_rate(WORKERS, 35.0, 0)
    with pytest.raises(ValueError):
        sustainable_rate({"A": math.nan}, 35.0, 2)


def test_service_time_per_frame_from_a_report():
    # pose_cells serves two messages per camera frame (template and odometry); the recorder shares
    # the experience map's process; a missing stage counts nothing
    st = lambda worker, tau, n: {"worker": worker, "tau_mean_ms": tau, "processed": n}  # noqa: E731
    report = {"frames_out": 100, "stages": {
        "A": st("A", 20.0, 100), "pose_cells": st("pose_cells", 0.5, 200),
        "experience_map": st("experience_map", 0.2, 100), "recorder": st("experience_map", 0.1, 300),
        "D": {"missing": True}}}
    assert worker_service_ms(report) == pytest.approx({"A": 20.0, "pose_cells": 1.0, "experience_map": 0.5})
    with pytest.raises(ValueError):
        worker_service_ms({"frames_out": 0, "stages": {}})


def test_a_workers_least_measured_service_time_counts():
    # uncontended one frame at a time: 11 ms for A; saturated in batches: 9 ms; sharing a core: 30 ms
    runs = ({"A": 11.0, "B": 6.0}, {"A": 9.0, "B": 7.0}, {"A": 30.0, "C": 2.0})
    from neoslam_stream.runtime.capacity import least_service_ms

    assert least_service_ms(*runs) == {"A": 9.0, "B": 6.0, "C": 2.0}
