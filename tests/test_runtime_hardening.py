"""Hardening of the runtime: a run's processes die with their supervisor, the
monitor is supervised, loss is counted by frame numbers across restarts, the control topic obeys
only its own supervisor, ``--resume`` starts at once and honours ``--max-frames``, a full disk never
loses report.json.

Expected values come from the definitions (a frame published by the source and never seen on the
final topic is lost), from hand-worked cases, or from an earlier run of the same data.
"""

from __future__ import annotations

import errno
import os
import signal
import time

import numpy as np
import psutil
import pytest
from runhelpers import attach, finish, start_looping_run, start_run, still_running, wait_stats
from runhelpers import light_config as _cfg
from runhelpers import read_report as _report

from neoslam_stream.evaluation import read_tum
from neoslam_stream.nodes.topics import ALGORITHM_TOPICS
from neoslam_stream.runtime import files
from neoslam_stream.runtime.bus import key_for
from neoslam_stream.runtime.messages import Message, encode, register_topics
from neoslam_stream.runtime.monitor import FinalTracker, StatsCollector, build_report, write_report


# ------------------------------------------------------------------------------ 1. supervisor death
@pytest.mark.slow
@pytest.mark.zenoh
def test_killing_the_supervisor_takes_every_process_of_the_run_with_it(tmp_path):
    proc, children = start_looping_run(tmp_path, processed=3)
    assert len(children) >= 8  # monitor, six workers, source
    try:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        deadline = time.monotonic() + 90  # generous: a liveness bound, not a timing claim
        while time.monotonic() < deadline and still_running(children):
            time.sleep(0.5)
        alive = still_running(children)
        assert alive == [], f"processes left running after the supervisor died: {alive}"
        # the stages flushed on their way out: what the map processed is on disk
        assert (tmp_path / "run" / "trajectory.tum").stat().st_size > 0
    finally:
        for c in still_running(children):  # whatever the outcome, leave nothing of ours behind
            c.kill()
        proc.stdout.close()


# ------------------------------------------------------------------------------ 4. forged control
@pytest.mark.slow
@pytest.mark.zenoh
def test_a_forged_control_stop_is_refused_and_the_run_finishes_with_all_its_outputs(tmp_path):
    frames = 40
    run_dir = tmp_path / "run"
    proc = start_run(tmp_path, _cfg("lossless", {"kind": "synthetic", "params": {
        "seed": 0, "frames": frames, "laps_cw": 1, "laps_ccw": 0}, "rate": 6.0, "pacing": "fixed"}))
    session, run_id = attach(run_dir)
    try:
        wait_stats(session, run_id, "D", until=lambda s: s.get("processed", 0) >= 3)
        key = key_for(run_id, "control")
        # another local process on the run's key: no token, then a wrong one, then a broadcast
        session.put(key, encode(Message("control", 0, time.time(), {"command": "stop"})))
        session.put(key, encode(Message("control", 0, time.time(), {"command": "stop", "token": "0" * 32})))
        session.put(key, encode(Message("control", 0, time.time(), {"command": "stop", "target": "monitor"})))
        time.sleep(1.0)
    finally:
        session.close()
    out = finish(proc)
    assert proc.returncode == 0, out
    rep = _report(run_dir)
    assert rep["interrupted"] is False
    # every frame through, every output complete
    assert rep["frames_out"] == frames and rep["loss"] == 0.0
    assert len(read_tum(run_dir / "trajectory.tum")) == frames
    assert len((run_dir / "templates.csv").read_text().splitlines()) - 1 == frames
    # each forged message counted as refused, with its cause, by every process that got it
    refused = rep["control_refused"]
    for proc_name in [*rep["workers"], "source"]:
        assert refused[proc_name] == 3, refused
    causes = " | ".join(rep["control_refused_causes"])
    assert "without the run's token" in causes and "wrong token" in causes


# ------------------------------------------------------------------------------ 2, 3, 7. restarts
@pytest.mark.slow
@pytest.mark.zenoh
def test_loss_stays_true_across_restarts_of_a_stage_and_of_the_monitor(tmp_path):
    """Without checkpoints: kill the experience map (its worker also hosts the recorder) and the
    monitor mid-run. Both come back; the report counts loss by frame numbers over the whole run."""
    run_dir = tmp_path / "run"
    proc = start_run(tmp_path, _cfg("realtime", {"kind": "synthetic", "params": {"seed": 0, "loop": True},
                                                 "rate": 10.0, "pacing": "fixed", "duration": 40.0},
                                    max_restarts=2))
    session, run_id = attach(run_dir)
    # the test's own view of the final topic: which camera frames arrived (this process decodes
    # the algorithms' topics, so it registers them, as every process of the run does)
    register_topics(ALGORITHM_TOPICS)
    seen = FinalTracker(entry_stages={"A"})
    sub = session.declare_subscriber(key_for(run_id, "experience_map/pose"), seen.on_sample)
    try:
        st = wait_stats(session, run_id, "experience_map", until=lambda s: s.get("processed", 0) >= 40)
        os.kill(st["pid"], signal.SIGKILL)
        wait_stats(session, run_id, "experience_map",
                   until=lambda s, pid=st["pid"]: s["pid"] != pid and s.get("processed", 0) >= 30)
        # the monitor: late in the run, so that most frames were counted by its first incarnation
        with seen.lock:
            before_monitor_kill = len(seen.frames)
        old_monitor = _monitor_pid(proc.pid, session, run_id)
        os.kill(old_monitor, signal.SIGKILL)
        # once a new monitor runs and has seen a few frames, a clean stop instead of waiting for
        # the source's 40 s (kept as an upper bound); SIGTERM writes the report as the end would
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not _monitors(proc.pid, session, run_id) - {old_monitor}:
            time.sleep(0.2)
        time.sleep(2.0)
        proc.send_signal(signal.SIGTERM)
    finally:
        time.sleep(0.5)
    out = finish(proc, timeout=600)
    sub.undeclare()
    session.close()
    assert proc.returncode == 128 + signal.SIGTERM, out
    rep = _report(run_dir)
    assert rep["restarts"] == {"experience_map": 1, "monitor": 1}
    assert [e["worker"] for e in rep["restart_events"]] == ["experience_map", "monitor"]
    # 2. the loss is measured over the whole run, not from the restarted monitor's frames only
    assert rep["frames_out"] >= before_monitor_kill > 0
    # 3. one headline figure by frame numbers: what the source published minus what arrived
    lost = rep["frames_in"] + rep["frames_lost_at_source"] - rep["frames_strided"] - rep["frames_out"]
    assert rep["frames_lost"] == lost > 0  # frames were lost while the map restarted
    assert rep["frames_expected"] == rep["frames_in"] + rep["frames_lost_at_source"] - rep["frames_strided"]
    assert rep["loss"] == pytest.approx(lost / rep["frames_expected"])
    assert f"loss {100 * rep['loss']:.1f} %" in out
    # per-stage drop counters are cumulative over the stage's lives: none claims more messages
    # lost than its upstream ever published (they reset to 0 on restart, so the new life's
    # "received" was compared with the upstream's total: hundreds "dropped" for ~30 frames)
    for name, row in rep["stages"].items():
        assert row["dropped"] <= rep["frames_in"] + rep["source"].get("odom", 0), (name, row)
    em = rep["stages"]["experience_map"]
    assert em["incarnations"] == 2
    # its one input (an action per frame) lost what came while it was down, and the frames its
    # killed life processed after its last stats (at most 0.5 s of stats at 10 Hz): not the 40+
    # messages its first life had received, which the reset counters added to the drops
    assert em["dropped"] <= lost + 15, (em["dropped"], lost)
    breakdown = rep["loss_breakdown"]
    assert sum(breakdown["source"].values()) == rep["frames_lost_at_source"]
    assert breakdown["unattributed"] >= 0
    # 7. without checkpoints the outputs written before the crash are kept
    traj = read_tum(run_dir / "trajectory.tum")
    assert traj[0, 0] < 0.5 and np.all(np.diff(traj[:, 0]) > 0)
    assert (run_dir / "report.json").stat().st_size > 0


def _monitors(sup_pid: int, session, run_id: str) -> set[int]:
    """The supervisor's living children that are no worker, not the source and not
    multiprocessing's resource tracker (workers and the source say their pid in their stats)."""
    others = {wait_stats(session, run_id, n)["pid"] for n in ("A", "B", "C", "D", "pose_cells",
                                                               "experience_map", "source")}
    found = set()
    for c in psutil.Process(sup_pid).children():
        try:
            if c.pid not in others and c.status() != psutil.STATUS_ZOMBIE \
                    and "resource_tracker" not in " ".join(c.cmdline()):
                found.add(c.pid)
        except psutil.NoSuchProcess:
            continue
    return found


def _monitor_pid(sup_pid: int, session, run_id: str) -> int:
    """The run's monitor (see :func:`_monitors`)."""
    kids = _monitors(sup_pid, session, run_id)
    assert len(kids) == 1, kids
    return kids.pop()


# ------------------------------------------------------------------------------ 5. resume
@pytest.mark.slow
@pytest.mark.zenoh
def test_resume_starts_at_once_and_stops_at_max_frames(tmp_path):
    src = {"kind": "synthetic", "params": {"seed": 0, "frames": 90, "laps_cw": 1, "laps_ccw": 0}}
    part = start_run(tmp_path, _cfg("lossless", src, checkpoint_every=20), "--max-frames", "50",
                     run_dir=tmp_path / "part")
    out = finish(part, timeout=600)
    assert part.returncode == 0, out
    assert (tmp_path / "part" / "checkpoint" / f"{40:09d}").is_dir()
    resumed = start_run(tmp_path, _cfg("lossless", src, checkpoint_every=20), "--resume", str(tmp_path / "part"),
                        "--max-frames", "70", run_dir=tmp_path / "resumed")
    out = finish(resumed, timeout=600)
    assert resumed.returncode == 0, out
    # no start-up stall: the source never waited for frames below the resumed cut
    assert "no progress on" not in out, out
    a = (tmp_path / "part" / "trajectory.tum").read_text().splitlines()
    b = (tmp_path / "resumed" / "trajectory.tum").read_text().splitlines()
    # --max-frames counts the run's frames from 0: 70 frames, the first 50 as in the part
    assert len(b) == 70 and b[:50] == a
    # and so does the ground truth the evaluation compares it with (frames below the cut included)
    ga = (tmp_path / "part" / "groundtruth.tum").read_text().splitlines()
    gb = (tmp_path / "resumed" / "groundtruth.tum").read_text().splitlines()
    assert len(gb) == 70 and gb[:50] == ga
    rep = _report(tmp_path / "resumed")
    assert rep["frames_in"] == 70 - 40  # frames 40..69 published
    assert rep["frames_out"] == 30 and rep["loss"] == 0.0


# ------------------------------------------------------------------------------ 3. accounting units
def _src(first: int, last: int, **kw) -> dict:
    return {"stage": "source", "frames_in": last - first + 1, "published_ranges": [[first, last]],
            "first_publish": 0.0, "last_publish": (last - first) / 10, "odom": 0, **kw}


def _stage(name: str, pid: int, received: int, processed: int, **kw) -> dict:
    return {"stage": name, "worker": name, "pid": pid, "time": 10.0, "started": 0.0, "received": received,
            "processed": processed, "published": {}, "errors": 0, "error_causes": {}, "counters": {},
            "inputs": {"image": {"received": received, "evicted": 0, "depth": 0}}, **kw}


def test_refused_frames_and_source_losses_are_in_the_headline_loss():
    """10 frames read by the source: frame 4 not published (a gap: the source skipped it), 2 more
    lost in the camera's ring; of the 9 published, A refused frame 7 (bad encoding): 8 arrive.
    Lost: 1 + 2 + 1 = 4 of 12 frames the camera produced."""
    src = _src(0, 9, frames_in=9, published_ranges=[[0, 3], [5, 9]],
               lost_at_source={"gap in the source's frame numbers": 1, "source ring full (oldest dropped)": 2})
    a = _stage("A", 1, 9, 8, errors=1, error_causes={"StageInputError: encoding 'mono16'": 1})
    final = FinalTracker(entry_stages={"A"})
    for f in (0, 1, 2, 3, 5, 6, 8, 9):
        final.add(f, [("source", 0.0, 0.0, 0.0), ("A", 0.0, 0.0, 0.0)], 1.0)
    final.add(10**6, [("A", 0.0, 0.0, 0.0)], 1.0)  # injected, never published: not a frame of the run
    rep = build_report({"source": src, "A": a}, final, {"A": ["A"]}, {})
    assert rep["frames_out"] == 8
    assert rep["frames_lost"] == 4
    assert rep["loss"] == pytest.approx(4 / 12)
    assert rep["loss_breakdown"]["source"] == {"gap in the source's frame numbers": 1,
                                               "source ring full (oldest dropped)": 2}
    assert rep["loss_breakdown"]["stages"]["A"]["refused"] == 1
    assert rep["loss_breakdown"]["unattributed"] == 0


def test_a_run_with_a_refused_frame_never_prints_loss_0(capsys):
    from neoslam_stream.cli import print_summary

    src = _src(0, 4)
    a = _stage("A", 1, 5, 4, errors=1, error_causes={"StageInputError: encoding 'mono16'": 1})
    final = FinalTracker(entry_stages={"A"})
    for f in range(4):
        final.add(f, [("A", 0.0, 0.0, 0.0)], 1.0)
    rep = build_report({"source": src, "A": a}, final, {"A": ["A"]}, {})
    print_summary(rep)
    text = capsys.readouterr().out
    assert "loss 20.0 %" in text and "loss 0.0 %" not in text
    # a loss that was not measured is said so, never printed as 0
    print_summary({**rep, "loss": None, "loss_percent": None})
    text = capsys.readouterr().out
    assert "loss unknown" in text and "loss 0.0 %" not in text


def test_no_source_stats_means_the_loss_is_unknown():
    rep = build_report({}, FinalTracker(), {"A": ["A"]}, {})
    assert rep["loss"] is None and rep["loss_percent"] is None


def test_stage_counters_add_up_over_its_incarnations():
    """A restarted stage reports counters from 0 again; the collector adds its earlier lives."""
    c = StatsCollector()
    c.add(_stage("B", 100, 50, 48, errors=2, error_causes={"x": 2}, counters={"strided": 3},
                 published={"sdr": 48}))
    c.add(_stage("B", 200, 10, 10, errors=1, error_causes={"x": 1}, counters={"strided": 1},
                 published={"sdr": 10}))
    c.add(_stage("B", 200, 12, 12, published={"sdr": 12}))  # same life: replaces, not adds
    b = c.snapshot()["B"]
    assert b["received"] == 62 and b["processed"] == 60 and b["errors"] == 2
    assert b["error_causes"] == {"x": 2}
    assert b["counters"]["strided"] == 3
    assert b["published"] == {"sdr": 60}
    assert b["inputs"]["image"]["received"] == 62
    assert b["incarnations"] == 2


# ------------------------------------------------------------------------------ 7. report on a full disk
def test_a_full_disk_never_loses_the_previous_report(tmp_path, monkeypatch):
    path = tmp_path / "report.json"
    assert write_report(path, {"frames_in": 1})
    before = path.read_bytes()

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files, "write_all", full)
    assert write_report(path, {"frames_in": 2}) is False  # said, not raised
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]  # no temporary left behind


# ------------------------------------------------------------------------------ 6. cuts per message
def test_one_message_makes_at_most_one_checkpoint_cut(tmp_path):
    """Adversarial frame numbers on the pose cells' two inputs (no jump limit): after every message
    the number of cut folders grew by at most one."""
    from test_hardening_outputs import _odo, _pose_cells_worker, _tpl

    w = _pose_cells_worker(tmp_path, max_frame_jump=0)
    root = tmp_path / "checkpoint"
    n_cuts = 0
    rng = np.random.default_rng(3)
    for i in range(200):
        f = int(rng.integers(0, 10**6)) if i % 5 == 0 else i
        topic, payload = ("odom", _odo(f)) if rng.random() < 0.5 else ("visual_template", _tpl(f, i % 7))
        w.handle(topic, payload, time.time())
        now = len(list(root.iterdir())) if root.exists() else 0
        assert now - n_cuts <= 1, (i, f, now, n_cuts)
        n_cuts = now
