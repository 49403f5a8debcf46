"""bench/camera_soak.py's computations on made-up samples, worked by hand: the memory verdict, the
latency from a frame's capture stamp to the end of D's service (through a real trace file), where
the frames went, and the names of the run's processes. The bench itself runs for an hour on a
quiet machine (docs/performance.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from camera_soak import (  # noqa: E402
    frame_figures,
    latency_figures,
    memory_rows,
    read_stamps,
    served_until,
    trace_finish_times,
    worker_label,
)
from memory_flat import memory_flat  # noqa: E402

from neoslam_stream.runtime.trace import TraceWriter  # noqa: E402


def test_memory_is_flat_when_the_total_moves_less_than_the_bound_after_the_first_minutes():
    # the start-up (t < 0), the first ten minutes and the shut-down after the stream's hour (the
    # processes save their state and exit) are left out: 2200, 2230, 2210, 2245 remain
    rows = [{"t_s": t, "rss_total_mb": m, "rss_mb": {"A": m - 1000.0, "D": 1000.0}} for t, m in
            [(-30, 100.0), (0, 2000.0), (300, 2100.0), (600, 2200.0), (610, 2230.0), (1200, 2210.0), (3600, 2245.0),
             (3610, 1900.0)]]
    flat = memory_flat(rows, after_s=600, until_s=3600)
    assert flat["samples"] == 4 and flat["range_mb"] == 45.0 and flat["flat"] is True
    assert (flat["first_mb"], flat["last_mb"], flat["min_mb"], flat["max_mb"]) == (2200.0, 2245.0, 2200.0, 2245.0)
    assert flat["rise_mb"] == 45.0 and flat["rise_mb_by_process"] == {"A": 45.0, "D": 0.0}
    assert memory_flat(rows, after_s=600, within_mb=40, until_s=3600)["flat"] is False
    assert memory_flat(rows, after_s=600)["range_mb"] == 345.0  # 2245 - 1900 with the shut-down
    # memory that falls counts as memory that rises: 2230 then 2180 is a range of 50, a rise of 30
    dip = [{"t_s": t, "rss_total_mb": m} for t, m in [(600, 2200.0), (700, 2230.0), (800, 2180.0)]]
    assert memory_flat(dip, within_mb=49)["flat"] is False and memory_flat(dip)["rise_mb"] == 30.0
    # a run shorter than the window has no verdict, not a made-up one
    assert memory_flat(rows, after_s=4000) == {"after_s": 4000, "until_s": None, "within_mb": 50.0, "samples": 0,
                                               "range_mb": None, "flat": None}


def test_the_live_hours_target_needs_flat_memory_and_no_frame_lost():
    from soak import memory_after_warmup

    rows = [{"t_s": t, "rss_total_mb": m, "rss_mb": {}} for t, m in [(600, 2000.0), (1200, 2030.0)]]
    assert memory_after_warmup(rows, 600, 50, frames_lost=0)["reached"] is True
    assert memory_after_warmup(rows, 600, 50, frames_lost=1)["reached"] is False
    assert memory_after_warmup(rows, 600, 20, frames_lost=0)["reached"] is False
    assert memory_after_warmup(rows, 3600, 50, frames_lost=0)["reached"] is None


def test_memory_rows_name_every_process_and_sum_them():
    samples = [{"time": 1010.0, "served": 300, "rss_mb": {"A": 500.0, "experie": 300.0, "source": 100.0,
                                                          "supervisor": 250.0}}]
    (row,) = memory_rows(samples, t0=1000.0, workers=["A", "experience_map", "pose_cells"])
    assert row == {"t_s": 10.0, "served": 300, "rss_mb": {"A": 500.0, "experience_map": 300.0, "source": 100.0,
                                                          "supervisor": 250.0}, "rss_total_mb": 1150.0}
    # the kernel keeps 15 characters of "neoslam-<worker>"
    assert worker_label("pose_ce", ["pose_cells", "visual_odometry"]) == "pose_cells"
    assert worker_label("visual_", ["pose_cells", "visual_odometry"]) == "visual_odometry"
    assert worker_label("monitor", ["pose_cells"]) == "monitor"


def _stage(name: str, start: float, end: float) -> tuple[str, float, float, float]:
    return (name, start, start, end)


def test_capture_to_template_from_templates_csv_and_a_trace(tmp_path):
    """Frames 0-2 captured at 100.0, 100.1 and 170.0 s (epoch), published 15 ms later; D ends 30, 40
    and 50 ms after capture. Frame 3 reached D but has no stamp (not recorded), frame 4 was recorded
    but never reached the end: neither counts."""
    origin = 90.0
    w = TraceWriter(tmp_path / "trace.json", {"A": ["A"], "B": ["B"], "C": ["C"], "D": ["D"]}, origin)
    stamps = {0: 100.0, 1: 100.1, 2: 170.0, 4: 171.0}
    for f, c2t in ((0, 0.030), (1, 0.040), (2, 0.050), (3, 0.045)):
        c = stamps.get(f, 170.5)
        w.add(f, [("source", c + 0.015, c + 0.015, c + 0.015), _stage("A", c + 0.016, c + 0.020),
                  _stage("B", c + 0.021, c + 0.022), _stage("C", c + 0.023, c + 0.025), _stage("D", c + 0.026, c + c2t)])
    w.close()
    (tmp_path / "templates.csv").write_text(
        "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
        + "".join(f"{f},{s:.6f},{f},0,-1,0.0\n" for f, s in stamps.items()))
    finished = trace_finish_times(tmp_path / "trace.json")
    assert finished["D"][1] == pytest.approx(100.14, abs=1e-6)  # back on the epoch through the trace's origin
    lat = latency_figures(read_stamps(tmp_path / "templates.csv"), finished, t0=50.0)
    c2t = lat["capture_to_template_ms"]
    # 30, 40, 50 ms: the median 40; the 95th percentile 40 + 0.9 x (50 - 40) = 49 (linear)
    assert c2t["n"] == 3 and c2t["p50"] == pytest.approx(40.0) and c2t["p95"] == pytest.approx(49.0)
    assert (c2t["mean"], c2t["min"], c2t["max"]) == pytest.approx((40.0, 30.0, 50.0))
    assert lat["by_stage_ms"]["source"]["p50"] == pytest.approx(15.0)  # capture -> published
    assert lat["by_stage_ms"]["C"]["max"] == pytest.approx(25.0)
    # minute by minute of capture time since t0 = 50 s: frames 0 and 1 in minute 0, frame 2 in minute 2
    assert [(b["t_s"], b["n"], b["p50_ms"]) for b in lat["over_time"]] == [(0.0, 2, pytest.approx(35.0)),
                                                                            (120.0, 1, pytest.approx(50.0))]


def test_where_the_frames_went():
    report = {"frames_in": 900, "frames_out": 880, "loss_breakdown": {"unattributed": 2},
              "source": {"camera": {"captured": 1000, "taken": 901, "dropped": 4, "discarded_at_start": 45,
                                    "outage_count": 1, "outage_s": 7.5, "outage_frames_missed": 224,
                                    "outages": [{"start": 1.0, "length_s": 7.5}], "skipped": {}}},
              "stages": {"A": {"dropped_queue": 0, "dropped_transport": 0},
                         "B": {"dropped_queue": 12, "dropped_transport": 1}, "D": {"dropped_queue": 3}}}
    fig = frame_figures(report, served=1012, connections=2, templates=890)
    assert fig["frames"] == {"served": 1012, "captured": 1000, "taken_by_source": 901, "published": 900,
                             "templates": 890, "processed": 880}
    d = fig["dropped"]
    assert d["source_ring"] == 4 and d["before_first_take"] == 45 and d["served_not_captured"] == 12
    assert d["rings_evicted"] == {"B": 12, "D": 3} and d["rings_evicted_total"] == 15
    assert d["transport"] == {"B": 1} and d["transport_total"] == 1 and d["unattributed"] == 2
    assert d["outage_frames_estimated"] == 224
    assert fig["outages"]["camera_reopenings"] == 1 and fig["outages"]["server_reopenings"] == 1
    # the stream's end: frames written up to it (the server serves on while the run drains)
    assert served_until([1.0, 2.0, 3.0, 4.0], 3.0) == 3 and served_until([1.0, 2.0], None) == 2
