"""``neoslam run --trace FILE``: every frame's path through the stages as a Chrome / Perfetto trace
(runtime/trace.py). Hand-made traces give known events; a short run's trace gives the monitor's
figures of report.json (frames served, mean tau_i, queueing percentiles), computed apart."""

from __future__ import annotations

import json

import pytest

from neoslam_stream.runtime.trace import TraceWriter, read_trace, stage_figures, trace_origin

WORKERS = {"A": ["A"], "map": ["B", "recorder"]}


def _trace(frame: int, t0: float, batch_start: float) -> list[tuple[str, float, float, float]]:
    """source publishes at t0; A serves frames 0 and 1 as one batch; B one at a time."""
    return [("source", t0, t0, t0), ("A", t0 + 0.001, batch_start, batch_start + 0.004),
            ("B", batch_start + 0.005, batch_start + 0.005 + 0.002 * frame, batch_start + 0.006 + 0.002 * frame)]


def test_the_events_of_two_frames_by_hand(tmp_path):
    w = TraceWriter(tmp_path / "t.json", WORKERS, origin=100.0)
    w.add(0, _trace(0, 100.0, 100.002))
    w.add(1, _trace(1, 100.0005, 100.002))  # same batch at A
    w.close()
    ev = read_trace(tmp_path / "t.json")
    names = {(e["pid"], e.get("tid")): e["args"]["name"] for e in ev if e["ph"] == "M" and e["name"] == "thread_name"}
    assert names == {(1, 1): "source", (2, 1): "A", (3, 1): "B"}
    procs = {e["pid"]: e["args"]["name"] for e in ev if e["ph"] == "M" and e["name"] == "process_name"}
    assert procs == {1: "source", 2: "A", 3: "map"}
    # the origin rides on the source's name: a ts back on the epoch is the trace's own time
    assert trace_origin(tmp_path / "t.json") == 100.0
    spans = [(e["name"], e["ts"], e["dur"], e["args"]["frames"]) for e in ev if e["ph"] == "X"]
    # A's batch once, with both frames, 4 ms from 2 ms after the origin; B twice, 1 ms each
    assert ("A", 2000.0, 4000.0, [0, 1]) in spans
    assert ("B", 7000.0, 1000.0, [0]) in spans and ("B", 9000.0, 1000.0, [1]) in spans
    # frame 1 waited at A from 1.5 ms to 2 ms (0.5 ms), after 1 ms of transit from the source
    b = [e for e in ev if e["ph"] == "b" and e["id"] == 1 and e["name"] == "waits for A"]
    assert b[0]["ts"] == 1500.0 and b[0]["args"]["transit_ms"] == pytest.approx(1.0)
    flow = [(e["ph"], e["pid"]) for e in ev if e.get("cat") == "frame" and e["id"] == 1]
    assert flow == [("s", 1), ("t", 2), ("f", 3)]
    figures = stage_figures(ev)
    assert figures["A"]["frames"] == 2 and figures["A"]["tau_mean_ms"] == pytest.approx(2.0)  # 4 ms / 2 frames
    assert figures["B"]["tau_mean_ms"] == pytest.approx(1.0)
    # B: frame 0 waited 0 (no event), frame 1 2 ms: p50 1 ms
    assert figures["B"]["queue_p50_ms"] == pytest.approx(1.0)


def test_a_file_cut_short_is_read_and_continued(tmp_path):
    path = tmp_path / "t.json"
    w = TraceWriter(path, WORKERS, origin=100.0)
    w.add(0, _trace(0, 100.0, 100.002))
    w.flush()
    # killed here: the array is not closed, and the last line may be incomplete
    with open(path, "a") as fh:
        fh.write('{"ph":"X","na')
    cut = read_trace(path)  # read as far as it is whole
    assert [e["args"]["frames"] for e in cut if e["ph"] == "X"] == []  # spans were pending when killed
    assert [e["id"] for e in cut if e["ph"] == "s"] == [0]
    w2 = TraceWriter(path, WORKERS, origin=100.0)  # a restarted monitor continues the file
    w2.add(2, _trace(2, 100.1, 100.102))
    w2.close()
    ev = read_trace(path)
    assert json.loads(path.read_text())  # closed: plain JSON
    assert {tuple(e["args"]["frames"]) for e in ev if e["ph"] == "X" and e["name"] == "B"} == {(2,)}
    # a closed file of an earlier run is started afresh
    w3 = TraceWriter(path, WORKERS, origin=100.0)
    w3.close()
    assert not [e for e in read_trace(path) if e["ph"] == "X"]


@pytest.mark.zenoh
def test_a_runs_trace_gives_the_monitors_figures(tmp_path):
    from neoslam_stream.cli import main

    trace = tmp_path / "trace.json"
    assert main(["run", "--max-frames", "40", "--out", str(tmp_path / "run"), "--no-live", "--trace", str(trace)]) == 0
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    figures = stage_figures(read_trace(trace))
    assert figures["source"]["frames"] == report["frames_out"] == 40
    # the stages that take one message per frame: every frame they served reached the end, so the
    # trace holds all their messages (the pose cells also take each frame's odometry, not traced)
    for stage in ("A", "B", "C", "D", "experience_map"):
        got, want = figures[stage], report["stages"][stage]
        assert got["frames"] == want["processed"] == 40, stage
        for key in ("tau_mean_ms", "queue_p50_ms", "queue_p95_ms"):
            assert got[key] == pytest.approx(want[key], abs=1e-4), (stage, key)
    assert figures["pose_cells"]["frames"] == 40 and report["stages"]["pose_cells"]["processed"] == 80
