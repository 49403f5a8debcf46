"""Reliability through real processes: the bad-input corpus, crash recovery of every stage,
checkpoint/resume, shutdown without orphans.

Expected counts come from the corpus itself (tests/badinput/corpus.py): every broken item is
counted exactly once by the stage that meets it, every good frame is processed.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import psutil
import pytest
import zenoh
from badinput.corpus import bus_items, write_image_folder
from runhelpers import attach, finish, start_looping_run, start_run, still_running, wait_stats
from runhelpers import light_config as _cfg
from runhelpers import read_report as _report

from neoslam_stream.evaluation import read_tum
from neoslam_stream.runtime.bus import key_for

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

# ------------------------------------------------------------------------------ bad input
def test_bad_input_corpus_through_the_running_pipeline(tmp_path):
    man = write_image_folder(tmp_path / "data")
    items = bus_items()
    run_dir = tmp_path / "run"
    # fixed pacing keeps the run going while the bus items are injected; lossless: nothing is
    # dropped, so every count below is exact
    proc = start_run(tmp_path, _cfg("lossless", {"kind": "folder", "params": {"path": str(man.root)},
                                                  "rate": 6.0, "pacing": "fixed"}))
    session, run_id = attach(run_dir)
    try:
        # frames 0.. have reached the pose cells: "out of order" items are then really late
        wait_stats(session, run_id, "pose_cells", until=lambda st: st.get("processed", 0) >= 4)
        for topic, payload, _stage, _cause in items:
            # BLOCK: the 64 MB item must not be dropped by zenoh's congestion control on the way
            session.put(key_for(run_id, topic), payload, congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.05)
        time.sleep(2.0)  # samples in flight are lost when their session closes
    finally:
        session.close()
    out = finish(proc)
    assert proc.returncode == 0, out
    rep = _report(run_dir)
    st = rep["stages"]

    # 0 crashes: no restart, every stage reported
    assert rep["restarts"] == {}
    assert not [n for n, s in st.items() if s.get("missing")]

    # every broken item counted once, by the stage that met it, with its cause
    expected = {name: 0 for name in st}
    expected["A"] += len(man.bad)
    for _topic, _payload, stage, _cause in items:
        expected[stage] += 1
    assert {n: s["errors"] for n, s in st.items()} == expected, {n: s["error_causes"] for n, s in st.items()}
    # each counted once in its causes too (a refused frame of a micro-batch was counted twice)
    assert {n: sum(s["error_causes"].values()) for n, s in st.items()} == expected
    causes = {n: " | ".join(s["error_causes"]) for n, s in st.items()}
    for what, cause in man.bad.values():
        assert cause in causes["A"], (what, causes["A"])
    for topic, _payload, stage, cause in items:
        assert cause in causes[stage], (topic, cause, causes[stage])

    # the source skipped the broken odometry rows (and published their frames' images)
    assert rep["source_errors"] == len(man.bad_odometry)
    src_causes = " | ".join(rep["source_error_causes"])
    for cause in man.bad_odometry.values():
        assert cause in src_causes
    assert rep["frames_in"] == len(man.files)
    assert rep["errors"] == sum(expected.values()) + len(man.bad_odometry)

    # everything good went through: every good image to D, every published odometry to the map
    assert st["A"]["processed"] == len(man.good)
    assert st["D"]["processed"] == len(man.good)
    assert st["experience_map"]["processed"] == len(man.files) - len(man.bad_odometry)
    # a camera frame is done when its pose comes out: the good images whose odometry was usable
    # (the broken odometry rows sit on good frames)
    assert set(man.bad_odometry) <= set(man.good)
    assert rep["frames_out"] == len(man.good) - len(man.bad_odometry)
    # ... and the report says why those frames are lost, not "in flight or lost while restarting"
    breakdown = rep["loss_breakdown"]
    assert breakdown["unattributed"] == 0, breakdown
    assert sum(n for cause, n in breakdown["source"].items() if "without odometry" in cause) == \
        len(man.bad_odometry), breakdown


def test_truncated_bag_ends_the_stream_cleanly(tmp_path):
    """A recording cut short (disk full, copy interrupted): the frames before the cut are processed,
    the source reports why it stopped, the run ends normally."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(0)
    path = tmp_path / "rec"
    n = 60
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(n):
            t = 1.0 + 0.1 * i
            stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
            img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
            msg = T["sensor_msgs/msg/Image"](header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam"),
                                             height=48, width=64, encoding="mono8", is_bigendian=0, step=64,
                                             data=img.reshape(-1))
            w.write(ci, int(round(t * 1e9)), ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    mcap = next(path.glob("*.mcap"))
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * 0.6)])
    run_dir = tmp_path / "run"
    proc = start_run(tmp_path, {**_cfg("lossless", {"kind": "bag", "params": {
        "path": str(mcap), "image_topic": "/camera/image_raw"}}), "odometry": "visual"})
    out = finish(proc)
    assert proc.returncode == 0, out
    rep = _report(run_dir)
    assert 0 < rep["frames_in"] < n
    assert rep["stages"]["D"]["processed"] == rep["frames_in"]  # every frame read was processed
    assert rep["source_errors"] == 1
    assert "truncated: read its first" in " ".join(rep["source_error_causes"])


# ------------------------------------------------------------------------------ crashes
def test_every_stage_recovers_from_sigkill_with_its_checkpointed_state(tmp_path):
    run_dir = tmp_path / "run"
    workers = ["A", "B", "C", "D", "pose_cells", "experience_map"]
    proc = start_run(tmp_path, _cfg("realtime", {"kind": "synthetic", "params": {"seed": 0, "loop": True},
                                                 "rate": 10.0, "pacing": "fixed", "duration": 75.0},
                                    checkpoint_every=20, max_restarts=2))
    session, run_id = attach(run_dir)
    killed_at = {}
    try:
        for w in workers:
            # a checkpoint exists and the worker is busy: kill it, then wait for its replacement
            st = wait_stats(session, run_id, w, until=lambda s: s.get("processed", 0) >= 25)
            pid = st["pid"]
            killed_at[w] = st["processed"]
            os.kill(pid, signal.SIGKILL)
            wait_stats(session, run_id, w, until=lambda s, pid=pid: s["pid"] != pid and s.get("processed", 0) > 0)
        # every worker was replaced and works again: a clean stop now instead of waiting for the
        # source's 75 s (kept as an upper bound); SIGTERM flushes every output as the end would
        wait_stats(session, run_id, "experience_map", until=lambda s: s.get("processed", 0) >= 10)
        proc.send_signal(signal.SIGTERM)
    finally:
        session.close()
    out = finish(proc, timeout=600)
    assert proc.returncode == 128 + signal.SIGTERM, out
    rep = _report(run_dir)
    assert rep["restarts"] == {w: 1 for w in workers}
    events = rep["restart_events"]
    assert [e["worker"] for e in events] == workers
    for e in events:
        assert e["exit_code"] == -signal.SIGKILL
        assert e["resumed_from_cut"] is not None and e["resumed_from_cut"] >= 20  # its last checkpoint
    assert rep["frames_out"] > 0 and rep["frames_out"] < rep["frames_in"]  # frames lost while restarting
    # the map survived its worker's death: the trajectory starts at the run's first frames
    traj = read_tum(run_dir / "trajectory.tum")
    assert traj[0, 0] < 0.5  # stamp of one of the first frames (10 Hz from 0)
    assert np.all(np.diff(traj[:, 0]) > 0)  # restored once, no frame twice, none out of order
    assert len(traj) >= rep["frames_out"] // 2
    # and so did the spatial-view cells' early templates
    rows = (run_dir / "templates.csv").read_text().splitlines()[1:]
    assert int(rows[0].split(",")[0]) < 5


# ------------------------------------------------------------------------------ resume
def _synthetic(frames: int) -> dict:
    return {"kind": "synthetic", "params": {"seed": 0, "frames": frames, "laps_cw": 1, "laps_ccw": 0}}


def test_resume_gives_the_trajectory_of_an_uninterrupted_run(tmp_path):
    frames = 90
    full = start_run(tmp_path, _cfg("lossless", _synthetic(frames)), run_dir=tmp_path / "full")
    assert full.wait(timeout=600) == 0, finish(full)
    # the same run, stopped by SIGINT after the checkpoint at frame 40, then resumed
    part = start_run(tmp_path, _cfg("lossless", _synthetic(frames), checkpoint_every=20),
                     run_dir=tmp_path / "part")
    session, run_id = attach(tmp_path / "part")
    try:
        wait_stats(session, run_id, "experience_map", until=lambda s: s.get("processed", 0) >= 45)
    finally:
        session.close()
    part.send_signal(signal.SIGINT)
    finish(part, timeout=300)
    assert part.returncode == 130
    assert (tmp_path / "part" / "checkpoint" / f"{40:09d}").is_dir()
    resumed = start_run(tmp_path, _cfg("lossless", _synthetic(frames), checkpoint_every=20), "--resume",
                        str(tmp_path / "part"), run_dir=tmp_path / "resumed")
    out = finish(resumed, timeout=600)
    assert resumed.returncode == 0, out
    a = (tmp_path / "full" / "trajectory.tum").read_text()
    b = (tmp_path / "resumed" / "trajectory.tum").read_text()
    assert len(a.splitlines()) == frames
    assert a == b  # byte-identical: the state (TM, intervals, pose cells, map, RNGs) reloaded exactly
    assert (tmp_path / "full" / "templates.csv").read_text() == (tmp_path / "resumed" / "templates.csv").read_text()


# ------------------------------------------------------------------------------ shutdown
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_flushes_outputs_and_leaves_no_orphans(tmp_path, sig):
    run_dir = tmp_path / "run"
    proc, children = start_looping_run(tmp_path, processed=10)
    assert len(children) >= 8  # monitor, six workers, source
    proc.send_signal(sig)
    finish(proc, timeout=300)
    assert proc.returncode == 128 + sig
    rep = _report(run_dir)
    assert rep["interrupted"] is True
    # every output flushed: trajectory, map and templates of the frames processed (the trajectory
    # holds a pose per action the map integrated; frames_out counts camera frames through A-D only)
    traj = read_tum(run_dir / "trajectory.tum")
    assert len(traj) == rep["stages"]["experience_map"]["processed"] >= rep["frames_out"] >= 10
    assert (run_dir / "map.json").stat().st_size > 0
    assert len((run_dir / "templates.csv").read_text().splitlines()) - 1 == rep["stages"]["D"]["processed"]
    time.sleep(0.5)
    alive = still_running(children)
    assert alive == [], f"orphans left: {alive}"


def test_second_sigint_forces_exit_without_orphans(tmp_path):
    proc, children = start_looping_run(tmp_path, processed=3)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    finish(proc, timeout=120)
    assert proc.returncode == 130
    time.sleep(1.0)
    alive = still_running(children)
    assert alive == [], f"orphans left: {alive}"


# ------------------------------------------------------------------------------ map export / import
def test_exported_map_is_recognised_in_a_new_session(tmp_path):
    from neoslam_stream.cli import main
    from neoslam_stream.runtime.checkpoint import load_map_file

    frames = 60
    # a backbone that tells places apart (random weights make every frame look alike)
    cfg = {**_cfg("lossless", _synthetic(frames)), "features": {"backbone": "efficientnet_lite0"}}
    first = start_run(tmp_path, cfg, run_dir=tmp_path / "first")
    assert first.wait(timeout=600) == 0, finish(first)
    assert main(["map", "export", str(tmp_path / "first"), "--out", str(tmp_path / "site.neoslam")]) == 0
    stored = load_map_file(tmp_path / "site.neoslam")["stages"]
    assert {"C", "D", "pose_cells", "experience_map"} <= set(stored)
    # the same drive again, on the exported map
    second = start_run(tmp_path, cfg, "--map", str(tmp_path / "site.neoslam"), run_dir=tmp_path / "second")
    out = finish(second, timeout=600)
    assert second.returncode == 0, out

    def templates(run):
        rows = [r.split(",") for r in (tmp_path / run / "templates.csv").read_text().splitlines()[1:]]
        return [int(r[2]) for r in rows], [int(r[3]) for r in rows]

    ids1, loops1 = templates("first")
    ids2, loops2 = templates("second")
    assert len(ids2) == frames  # a new session: its own frames only
    n_known = max(ids1) + 1
    # the places are known: most frames close a loop with the first session's templates, and
    # hardly any new template is made (a fresh run makes n_known of them)
    assert sum(loops2) > frames // 2 > sum(loops1)
    assert sum(1 for i in ids2 if i >= n_known) < n_known // 2
    rep1, rep2 = _report(tmp_path / "first"), _report(tmp_path / "second")
    assert rep2["stages"]["experience_map"]["info"]["experiences"] >= \
        rep1["stages"]["experience_map"]["info"]["experiences"]


def test_map_file_errors_are_clear(tmp_path):
    import msgpack

    from neoslam_stream.cli import main
    from neoslam_stream.runtime.checkpoint import load_map_file, save_state_file

    (tmp_path / "not_a_map").write_bytes(msgpack.packb({"format": "something else", "stages": {}}))
    with pytest.raises(ValueError, match="not a neoslam map"):
        load_map_file(tmp_path / "not_a_map")
    save_state_file(tmp_path / "a_state", {"stages": {}})  # a node's state file is no map either
    with pytest.raises(ValueError, match="not a neoslam map"):
        load_map_file(tmp_path / "a_state")
    (tmp_path / "future").write_bytes(msgpack.packb({"format": "neoslam-map", "version": 99, "stages": {}}))
    with pytest.raises(ValueError, match="version 99"):
        load_map_file(tmp_path / "future")
    assert main(["map", "export", str(tmp_path / "empty_run")]) == 1  # no state: a clear error, no traceback


# ------------------------------------------------------------------------------ bridged ROS 2 camera
def test_bad_cdr_samples_from_a_bridged_camera_are_counted_and_skipped(tmp_path):
    """A zenoh-bridged ROS 2 camera sending unsupported encodings, cut and foreign samples among
    good frames: the source counts each with its cause, the good frames go through A-D."""
    from rosbags.typesys import Stores, get_typestore

    from neoslam_stream.runtime.bus import open_session, wait_for_peers
    from neoslam_stream.runtime.ports import free_port
    from neoslam_stream.sources import cdr

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(5)

    def image(i, encoding="rgb8", channels=3):
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=100 + i, nanosec=0),
                                          frame_id="cam")
        px = rng.integers(0, 256, (48, 64, channels), dtype=np.uint8)
        return cdr.serialize(T["sensor_msgs/msg/Image"](header=header, height=48, width=64, encoding=encoding,
                                                        is_bigendian=0, step=64 * channels, data=px.reshape(-1)),
                             "sensor_msgs/msg/Image")

    good = [image(i) for i in range(8)]
    bad = [(image(50, "yuv422", 2), "yuv422"), (bytes(good[0])[:60], "truncated"),
           (b"\x00\x01\x00\x00garbage", "truncated"), (bytes(good[1])[:2], "shorter than its 4-byte header")]
    ep = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / "run"
    proc = start_run(tmp_path, _cfg("realtime", {"kind": "zenoh-ros2", "rate": 5.0, "params": {
        "image_topic": "/cam/image_raw", "listen": [ep], "timeout_s": 5.0, "capacity": 64}}))
    session, run_id = attach(run_dir)
    pub = open_session(connect=[ep])
    try:
        assert wait_for_peers(pub, 1, 60.0)
        wait_stats(session, run_id, "source")
        time.sleep(1.0)
        sequence = [g for pair in zip(good, [b for b, _ in bad] + [None] * 4, strict=True) for g in pair if g]
        for payload in sequence:
            pub.put("cam/image_raw", bytes(payload))
            time.sleep(0.2)
        time.sleep(1.0)
    finally:
        pub.close()
        session.close()
    out = finish(proc)
    assert proc.returncode == 0, out
    rep = _report(run_dir)
    assert rep["restarts"] == {}
    assert rep["source_errors"] == len(bad)
    causes = " | ".join(rep["source_error_causes"])
    for _payload, cause in bad:
        assert cause in causes, causes
    assert rep["frames_in"] == len(good)
    assert rep["stages"]["D"]["processed"] == len(good)


def test_unreadable_recording_fails_the_run_with_a_clear_message(tmp_path):
    bag = tmp_path / "broken.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)  # a header, then nothing readable
    proc = start_run(tmp_path, _cfg("lossless", {"kind": "bag", "params": {
        "path": str(bag), "image_topic": "/camera/image_raw"}}))
    seen: dict[int, psutil.Process] = {}
    while proc.poll() is None:  # every process the run starts
        try:
            seen.update({c.pid: c for c in psutil.Process(proc.pid).children(recursive=True)})
        except psutil.NoSuchProcess:
            break
        time.sleep(0.2)
    out = finish(proc)
    assert proc.returncode == 1, out
    assert "the source failed" in out and "cannot read bag" in out and "broken.mcap" in out
    assert "Traceback" not in out.split("the source failed")[-1]
    assert len(seen) >= 7  # monitor, six workers (and the source)
    time.sleep(0.5)
    assert not [p for p in seen.values() if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
