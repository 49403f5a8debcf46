"""The recorder's outputs: each row written when it comes, with the bytes a whole run would write;
kept across a crash and a restart from a checkpoint; a full disk never empties a file nor tears a
row, and the rows that waited are written once space comes back.

The recorder is driven in-process (its ``process`` is what its worker calls for every message);
the last test kills a real worker.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from neoslam_stream.nodes.recorder import RecorderNode
from neoslam_stream.nodes.run_folder import JOURNAL, RunFolder
from neoslam_stream.nodes.run_rows import TEMPLATES_HEADER
from neoslam_stream.nodes.topics import EXPERIENCE_MAP, EXPERIENCE_POSE, VISUAL_TEMPLATE
from neoslam_stream.runtime import files as files_mod
from neoslam_stream.runtime.messages import Message
from neoslam_stream.tum import write_tum


# ------------------------------------------------------------------------------ rows as they come
def _template_msg(f: int) -> Message:
    return Message(VISUAL_TEMPLATE, f, f * 0.1, {"id": f % 4, "is_loop_closure": f % 3 == 0,
                                                 "best_interval": f % 4 - 1, "best_score": f * 2})


def _pose_msg(f: int) -> Message:
    return Message(EXPERIENCE_POSE, f, f * 0.1, {"pose": np.array([0.1 * f, -0.2 * f, 0.3 * f - 2]),
                                                 "exp_id": f // 5})


def _expected(tmp_path: Path, frames: list[int]) -> tuple[str, str]:
    """The files as the recorder wrote them at the end of a run before (whole, from its rows)."""
    rows = "".join(f"{f},{f * 0.1:.6f},{f % 4},{int(f % 3 == 0)},{f % 4 - 1},{f * 2}\n" for f in frames)
    ref = tmp_path / "ref.tum"
    write_tum(ref, [(f * 0.1, 0.1 * f, -0.2 * f, 0.3 * f - 2) for f in frames])
    return TEMPLATES_HEADER + rows, ref.read_text()


def _recorder(run_dir: Path, run_id: str = "run-1") -> RecorderNode:
    rec = RecorderNode()
    rec.run_dir, rec.run_id = str(run_dir), run_id
    return rec


def _feed(rec: RecorderNode, frames) -> None:
    for f in frames:
        rec.process(VISUAL_TEMPLATE, _template_msg(f))
        rec.process(EXPERIENCE_POSE, _pose_msg(f))


def _files(run_dir: Path) -> tuple[str, str]:
    return (run_dir / "templates.csv").read_text(), (run_dir / "trajectory.tum").read_text()


def test_the_recorder_appends_each_row_when_it_comes_with_the_same_bytes(tmp_path):
    run = tmp_path / "run"
    rec = _recorder(run, run_id="")  # in-process: no journal
    _feed(rec, range(7))
    assert _files(run) == _expected(tmp_path, list(range(7)))  # before the end of the run
    _feed(rec, range(7, 12))
    rec.flush()
    rec.close()
    assert _files(run) == _expected(tmp_path, list(range(12)))
    assert not (run / JOURNAL).exists()


def test_a_restarted_recorder_keeps_the_rows_written_before_its_crash(tmp_path):
    run = tmp_path / "run"
    first = _recorder(run)
    _feed(first, range(10))  # then killed: no flush, no close
    # a crash mid-row: half a trajectory row, and a journal entry for a row that never came
    with open(run / "trajectory.tum", "a") as fh:
        fh.write("1.000000 0.1")
    with open(run / JOURNAL, "a") as fh:
        fh.write("t 10\n")
    # restarted from scratch (no checkpoint); the upstream replays frames 6..9 before new ones
    second = _recorder(run)
    _feed(second, range(6, 15))
    second.flush()
    second.close()
    assert _files(run) == _expected(tmp_path, list(range(15)))
    assert second.counters["rows_already_written"] == 2 * 4


def test_a_recorder_restarted_from_a_checkpoint_adds_the_rows_of_its_state_not_written(tmp_path):
    run = tmp_path / "run"
    first = _recorder(run)
    _feed(first, range(8))
    state = first.state_dict()  # the checkpoint: rows of frames 0..7
    _feed(first, range(8, 12))  # written, then killed
    # rows 10 and 11 never reached the trajectory file (e.g. a full disk): cut them
    lines = (run / "trajectory.tum").read_text().splitlines(keepends=True)
    (run / "trajectory.tum").write_text("".join(lines[:10]))
    second = _recorder(run)
    second.load_state_dict(state)
    _feed(second, range(12, 16))
    second.flush()
    second.close()
    templates, trajectory = _files(run)
    exp_t, _ = _expected(tmp_path, list(range(16)))
    assert templates == exp_t  # every row written before the crash kept, each once
    _, exp_p = _expected(tmp_path, [*range(10), *range(12, 16)])
    assert trajectory == exp_p  # 10, 11: neither written nor in the restored state


def test_a_run_resumed_into_another_folder_begins_with_the_rows_its_checkpoint_had(tmp_path):
    """A checkpoint holds no written row (the files are the record): resumed elsewhere, the new
    folder's files begin with the rows the checkpoint's folder held when it was cut, not with
    those written after it, and its journal names them (a restart there keeps them)."""
    part = tmp_path / "part"
    first = _recorder(part, "run-1")
    _feed(first, range(8))
    state = first.state_dict()  # the checkpoint, at frame 7
    _feed(first, range(8, 11))  # written after it, then stopped
    first.flush()
    first.close()
    resumed = _recorder(tmp_path / "resumed", "run-2")
    resumed.load_state_dict(state)
    _feed(resumed, range(8, 13))  # the resumed run replays from frame 8
    resumed.flush()
    resumed.close()
    assert _files(tmp_path / "resumed") == _expected(tmp_path, list(range(13)))
    journal = (tmp_path / "resumed" / JOURNAL).read_text().splitlines()
    closures = (tmp_path / "resumed" / "closures.csv").read_text().splitlines()[1:]
    assert journal[0] == "run run-2"
    assert [sum(e.startswith(tag + " ") for e in journal) for tag in "tpc"] == [13, 13, len(closures)]
    assert len(closures) == len([f for f in range(13) if f % 3 == 0])  # _template_msg's closures
    # a new session on that state is this session's outputs only
    today = _recorder(tmp_path / "today", "run-3")
    today.load_state_dict(state)
    today.new_session()
    _feed(today, range(3))
    today.flush()
    today.close()
    assert _files(tmp_path / "today") == _expected(tmp_path, list(range(3)))


def test_a_new_run_in_the_same_folder_starts_the_files_afresh(tmp_path):
    run = tmp_path / "run"
    first = _recorder(run, "run-1")
    _feed(first, range(5))
    first.flush()
    first.close()
    second = _recorder(run, "run-2")
    _feed(second, range(3))
    second.flush()
    second.close()
    assert _files(run) == _expected(tmp_path, list(range(3)))


# ------------------------------------------------------------------------------ 5. disk full
def disk_full_after(monkeypatch, fail: dict) -> None:
    """``write_all`` writes half of what it is given, then fails with ENOSPC, while fail["on"]."""
    real = files_mod.write_all

    def write_all(fd, data):
        if fail["on"]:
            os.write(fd, bytes(data)[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd, data)

    monkeypatch.setattr(files_mod, "write_all", write_all)


def test_a_full_disk_never_empties_map_json_nor_tears_a_row(tmp_path, monkeypatch, caplog):
    run = tmp_path / "run"
    run.mkdir()
    (run / "map.json").write_text('{"nodes": [], "links": []}')  # from an earlier flush
    fail = {"on": False}
    disk_full_after(monkeypatch, fail)
    monkeypatch.setattr(RunFolder, "RETRY_S", 0.0)
    rec = _recorder(run)
    _feed(rec, range(4))
    fail["on"] = True
    with caplog.at_level(logging.ERROR, logger="neoslam.recorder"):
        _feed(rec, range(4, 8))  # these wait
        rec.process(EXPERIENCE_MAP, Message(EXPERIENCE_MAP, 7, 0.7, {"export": {"nodes": [1], "links": []}}))
        rec.flush()
    # the earlier map is intact, no temporary file is left, the files hold whole rows only
    assert (run / "map.json").read_text() == '{"nodes": [], "links": []}'
    # (and, while the run goes on, the scratch files of its per-frame numbers)
    assert sorted(p.name for p in run.iterdir() if not p.name.endswith(".f64")) == sorted(
        ["map.json", "templates.csv", "trajectory.tum", "closures.csv", JOURNAL])
    assert _files(run) == _expected(tmp_path, list(range(4)))
    # 4 template rows, 4 trajectory rows and the closures.csv rows of the closures 0, 3 and 6 (f % 3 ==
    # 0), which waited for ground truth (none came) until the end of the run, when the disk was full
    assert rec.counters["write_errors"] >= 3 and rec.info()["rows_not_written"] == 4 + 4 + 3
    logged = [r.message for r in caplog.records]
    assert any(m.startswith(f"recorder: disk full writing {run / 'map.json'}: ") for m in logged)
    assert len([m for m in logged if "disk full writing" in m and "map.json" in m]) == 1  # once
    # space comes back: the rows that waited are written, in order, and the map
    fail["on"] = False
    rec.flush()
    rec.close()
    assert _files(run) == _expected(tmp_path, list(range(8)))
    assert (run / "map.json").read_text() == '{"nodes": [1], "links": []}'
    assert not list(run.glob("*.f64"))  # the scratch files go at close


# ------------------------------------------------------------------------------ a real crash
@pytest.mark.slow
@pytest.mark.zenoh
def test_killing_the_experience_map_without_checkpoints_keeps_the_trajectory_written(tmp_path):
    import json

    from runhelpers import attach, finish, light_config, start_run, wait_stats

    from neoslam_stream.evaluation import read_tum

    run_dir = tmp_path / "run"
    cfg = light_config("realtime", {"kind": "synthetic", "params": {"seed": 0, "loop": True}, "rate": 10.0,
                                    "pacing": "fixed", "duration": 30.0}, max_restarts=1)
    proc = start_run(tmp_path, cfg)
    session, run_id = attach(run_dir)
    try:
        st = wait_stats(session, run_id, "recorder", until=lambda s: s["info"].get("trajectory_rows", 0) >= 40)
        os.kill(st["pid"], signal.SIGKILL)
        rows_before = st["info"]["trajectory_rows"]
        wait_stats(session, run_id, "experience_map",
                   until=lambda s, pid=st["pid"]: s["pid"] != pid and s.get("processed", 0) >= 10)
        # the restarted worker writes again: a clean stop now instead of waiting for the source's
        # 30 s (kept as an upper bound); SIGTERM flushes every output as the end would
        proc.send_signal(signal.SIGTERM)
    finally:
        session.close()
    out = finish(proc, timeout=600)
    assert proc.returncode == 128 + signal.SIGTERM, out
    rep = json.loads((run_dir / "report.json").read_text())
    assert rep["restarts"] == {"experience_map": 1}
    traj = read_tum(run_dir / "trajectory.tum")
    # the rows written before the crash are there: the trajectory starts at the run's first frames
    assert traj[0, 0] < 0.5
    # and every row of the restarted recorder after them, none twice, none out of order
    after = rep["stages"]["recorder"]["info"]["trajectory_rows"]
    assert after > 0 and len(traj) >= rows_before + after
    assert np.all(np.diff(traj[:, 0]) > 0)
    rows = (run_dir / "templates.csv").read_text().splitlines()[1:]
    frames = [int(r.split(",")[0]) for r in rows]
    assert frames[0] < 5 and frames == sorted(set(frames))
