"""The viewer (``neoslam view``, ``neoslam run --view``): what it records, read back from the .rrd
with rerun's own reader. No window: ``--save`` (and no display) records to a file only."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

rerun_chunk = pytest.importorskip("rerun.chunk")

from runhelpers import light_config  # noqa: E402

from neoslam_stream.cli import main  # noqa: E402
from neoslam_stream.tum import write_tum  # noqa: E402


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """Entity path -> its rows (time columns and component values), in the order they were logged
    per chunk; static rows (no time) included."""
    rows: dict[str, list[dict]] = {}
    for ch in rerun_chunk.RrdReader(path).stream():
        batch = ch.to_record_batch()
        cols = {}
        for name in batch.schema.names:
            if name.startswith("rerun.") or name == "log_time":
                continue
            col = batch.column(name)
            if str(col.type).startswith("timestamp") or str(col.type).startswith("duration"):
                cols[name] = col.cast("int64").to_pylist()
            else:
                cols[name] = col.to_pylist()
        for i in range(ch.num_rows):
            rows.setdefault(ch.entity_path, []).append({k: v[i] for k, v in cols.items()})
    return rows


def _column(rows: list[dict], suffix: str) -> list:
    key = next(k for k in rows[0] if k.endswith(suffix))
    return [r[key] for r in rows]


# --------------------------------------------------------------------------- a finished run
def _run_folder(root: Path) -> dict:
    """A run folder written by hand, with known content: 6 frames, 2 loop closures, a 3-node map,
    two stages in timeline.csv."""
    root.mkdir()
    frames = list(range(10, 16))
    stamps = [0.5 * i for i in range(6)]
    ids = [0, 1, 2, 0, 1, 3]
    loops = [0, 0, 0, 1, 1, 0]
    (root / "templates.csv").write_text(
        "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
        + "".join(f"{f},{s:.6f},{t},{lc},-1,0\n" for f, s, t, lc in zip(frames, stamps, ids, loops, strict=True)))
    traj = [(s, 1.0 + i, 2.0 * i, 0.1 * i) for i, s in enumerate(stamps)]
    write_tum(root / "trajectory.tum", traj)
    write_tum(root / "groundtruth.tum", [(s, -float(i), 0.5, 0.0) for i, s in enumerate(stamps)])
    write_tum(root / "odometry.tum", [(s, float(i), -1.0, 0.0) for i, s in enumerate(stamps)])
    (root / "map.json").write_text(json.dumps({
        "nodes": [{"id": 0, "x": 0.0, "y": 0.0, "theta": 0.0, "stamp": 0.0},
                  {"id": 1, "x": 1.0, "y": 0.0, "theta": 0.0, "stamp": 1.0},
                  {"id": 2, "x": 1.0, "y": 1.0, "theta": 0.0, "stamp": 2.0}],
        "links": [{"from": 0, "to": 1}, {"from": 1, "to": 2}]}))
    # stage A: processed 0, 10, 30 at 1, 2, 4 s -> rates 10 and 10 Hz; B: 0, 5, 20 at 1, 2, 3 s -> 5, 15 Hz
    rows = [(1.0, "A", 0), (1.0, "B", 0), (2.0, "A", 10), (2.0, "B", 5), (3.0, "B", 20), (4.0, "A", 30)]
    (root / "timeline.csv").write_text(
        "t_s,stage,received,processed,tau_p50_ms,tau_p95_ms,queue_depth,dropped,errors,cpu_percent,rss_mb,pss_mb\n"
        + "".join(f"{t},{s},{n},{n},1,1,0,0,0,1,1,1\n" for t, s, n in rows))
    return {"frames": frames, "ids": ids, "loops": loops, "traj": traj,
            "rates": {"A": [10.0, 10.0], "B": [5.0, 15.0]}}


def test_view_of_a_finished_run_records_its_files(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    want = _run_folder(tmp_path / "run")
    out = tmp_path / "out.rrd"
    assert main(["view", str(tmp_path / "run"), "--save", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    rec = read_rrd(out)

    tid = rec["/template/id"]
    assert _column(tid, "frame") == want["frames"]
    assert [v[0] for v in _column(tid, "scalars")] == [float(i) for i in want["ids"]]
    closing = [f for f, lc in zip(want["frames"], want["loops"], strict=True) if lc]
    assert len(rec["/events"]) == len(closing)
    # the closures sit on the map at the trajectory's pose of their frame
    closure_xy = sorted(tuple(r[0]) for r in _column(rec["/map/loop_closures"], "positions"))
    assert closure_xy == sorted((want["traj"][want["frames"].index(f)][1],
                                 want["traj"][want["frames"].index(f)][2]) for f in closing)

    traj = rec["/map/trajectory"]
    assert _column(traj, "frame") == want["frames"]  # stamps mapped to frames through templates.csv
    xy = [tuple(r[0]) for r in _column(traj, "positions")]
    np.testing.assert_allclose(xy, [(x, y) for _s, x, y, _t in want["traj"]], atol=1e-6)
    assert len(rec["/map/groundtruth"]) == len(rec["/map/odometry"]) == 6
    # the robot's arrow points along its heading
    arrows = _column(rec["/map/robot"], "vectors")
    for (_s, _x, _y, th), v in zip(want["traj"], arrows, strict=True):
        assert math.isclose(math.atan2(v[0][1], v[0][0]), th, abs_tol=1e-5)

    assert len(_column(rec["/map/experiences"], "positions")[0]) == 3
    assert len(_column(rec["/map/links"], "strips")[0]) == 2
    for stage, rates in want["rates"].items():
        got = [v[0] for v in _column(rec[f"/stats/{stage}/rate_hz"], "scalars")]
        assert got == pytest.approx(rates)


def test_view_of_a_finished_run_records_its_camera_and_log_lines(tmp_path, capsys):
    from neoslam_stream.runtime.camera_log import CameraLog

    _run_folder(tmp_path / "run")
    cam = CameraLog(period_s=1.0)
    for f in range(6):  # a frame every 0.5 s: every second one kept, frames 0, 2, 4
        cam.add(f, 0.5 * f, np.full((24, 32, 3), 40 * f, np.uint8))
    cam.write(tmp_path / "run")
    (tmp_path / "run" / "log.jsonl").write_text(json.dumps(
        {"t_s": 0.5, "t": 1.7e9, "level": "WARNING", "process": "source", "name": "neoslam.source",
         "message": "no odometry.tum"}) + "\n")
    out = tmp_path / "out.rrd"
    assert main(["view", str(tmp_path / "run"), "--save", str(out)]) == 0
    assert "3 camera frames" in capsys.readouterr().out
    rec = read_rrd(out)
    assert _column(rec["/camera/image"], "frame") == [0, 2, 4]
    assert any("no odometry.tum" in str(v) for v in _column(rec["/log"], "text"))


def test_view_skips_a_damaged_file_and_shows_the_rest(tmp_path, caplog):
    want = _run_folder(tmp_path / "run")
    (tmp_path / "run" / "trajectory.tum").write_text("0.0 1 2\n")  # too few columns
    out = tmp_path / "out.rrd"
    assert main(["view", str(tmp_path / "run"), "--save", str(out)]) == 0
    # the damaged row is skipped with its file and line named (tum.read_tum), the rest is shown
    assert "trajectory.tum line 1" in caplog.text and "row skipped" in caplog.text
    rec = read_rrd(out)
    assert "/map/trajectory" not in rec
    assert len(rec["/template/id"]) == len(want["frames"])


def test_view_of_a_run_whose_router_is_gone_shows_its_files(tmp_path):
    # endpoints.json and no report.json: a run killed without its report; nothing listens there
    want = _run_folder(tmp_path / "run")
    (tmp_path / "run" / "endpoints.json").write_text(json.dumps(
        {"run": "rgone", "connect": ["tcp/127.0.0.1:9"], "mode": "client"}))
    out = tmp_path / "out.rrd"
    assert main(["view", str(tmp_path / "run"), "--save", str(out)]) == 0
    assert len(read_rrd(out)["/template/id"]) == len(want["frames"])


def test_view_of_a_folder_without_outputs_is_one_error_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--save", str(tmp_path / "x.rrd")]) == 2
    assert "no run outputs" in capsys.readouterr().err


# --------------------------------------------------------------------------- a live run
@pytest.mark.zenoh
@pytest.mark.slow
def test_run_with_view_records_the_live_run(tmp_path):
    frames = 30
    cfg = light_config("lossless", {"kind": "synthetic", "params": {"seed": 0, "frames": frames}})
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}  # no window
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(tmp_path / "cfg.yaml"),
                           "--out", str(run_dir), "--view"], env=env, capture_output=True, text=True,
                          timeout=500)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "recording:" in proc.stdout  # the viewer's own summary line
    rec = read_rrd(run_dir / "view.rrd")
    # camera frames came live (the viewer may skip some, never invent one)
    img_frames = _column(rec["/camera/image"], "frame")
    assert 1 <= len(img_frames) <= frames and set(img_frames) <= set(range(frames))
    # every template id it logged is the one the recorder wrote for that frame
    import csv

    with (run_dir / "templates.csv").open() as f:
        written = {int(r["frame"]): float(r["template_id"]) for r in csv.DictReader(f)}
    tid = rec["/template/id"]
    logged = dict(zip(_column(tid, "frame"), (v[0] for v in _column(tid, "scalars")), strict=True))
    assert logged and all(written[f] == v for f, v in logged.items())
    assert rec.get("/map/trajectory") and rec.get("/map/groundtruth") and rec.get("/map/odometry")
    # the rate of every stage of the report
    report = json.loads((run_dir / "report.json").read_text())
    for stage in report["stages"]:
        assert f"/stats/{stage}/rate_hz" in rec, stage
    assert "/map/experiences" in rec  # the final map, once the run ended


def test_the_live_views_draw_odometry_as_the_sources_write_odometry_tum():
    """LiveLogger dead-reckons the odom messages once for every view, by the rule of
    tum.integrate_odometry (the odometry.tum a run folder holds)."""
    from neoslam_stream.runtime.messages import Message, encode
    from neoslam_stream.tum import integrate_odometry
    from neoslam_stream.viewer.live import LiveLogger

    class View:
        def __init__(self):
            self.stats = type("S", (), {"bad_messages": 0})()
            self.poses = []

        def odometry_pose(self, frame, stamp, pose):
            self.poses.append((stamp, *pose))

    rng = np.random.default_rng(3)
    odom = np.column_stack([rng.uniform(0, 1, 40), rng.uniform(-1, 1, 40), np.full(40, 0.1)])
    view = View()
    logger = LiveLogger(view)
    for i, (v, w, dt) in enumerate(odom):
        logger.message("odom", encode(Message("odom", i, i * 0.1, {"vtrans": v, "vrot": w, "dt": dt})))
    assert view.stats.bad_messages == 0
    np.testing.assert_allclose(np.array(view.poses), integrate_odometry(np.arange(40) * 0.1, odom), atol=1e-9)
