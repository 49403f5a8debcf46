"""The run served to Foxglove (``neoslam run --foxglove``, ``neoslam view RUN_DIR --foxglove``),
checked by an independent client (tests/foxglove_client.py: the WebSocket protocol spoken by hand,
JSON checked against the advertised JSON schemas, protobuf parsed by Google's runtime from the
advertised descriptors), against the run's own files."""

from __future__ import annotations

import asyncio
import csv
import json
import math
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("foxglove")
pytest.importorskip("websockets")
pytest.importorskip("google.protobuf")

import foxglove_client as fc  # noqa: E402
from runhelpers import attach, light_config  # noqa: E402

from neoslam_stream.runtime.ports import free_port  # noqa: E402

FRAMES = 80


def _t(stamp: str) -> float:
    """A protobuf Timestamp as MessageToDict writes it (RFC 3339) -> seconds."""
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def _xyq(pose: dict) -> tuple[float, float, float, float]:
    """x, y, qz, qw of a foxglove.Pose decoded to a dict (zero fields are left out)."""
    p, q = pose.get("position", {}), pose.get("orientation", {})
    return p.get("x", 0.0), p.get("y", 0.0), q.get("z", 0.0), q.get("w", 0.0)


def _rows(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def _values(got: fc.Received, topic: str) -> list:
    return [m for _, m in got.messages.get(topic, [])]


# --------------------------------------------------------------------------- the view alone
def test_the_view_sends_what_it_is_given_in_the_advertised_schemas():
    """No run: the view's calls, received by the independent client."""
    from neoslam_stream.viewer.foxglove import TOPICS, FoxgloveView

    fv = FoxgloveView("127.0.0.1", 0, backlog=10_000)
    got: dict = {}

    def client() -> None:
        got["r"] = asyncio.run(fc.collect(fv.url, until_s=6.0, connect_timeout=20.0, publish_attempt=True))

    th = threading.Thread(target=client)
    th.start()
    assert fv.listener.subscribed.wait(20.0)
    time.sleep(0.5)
    fv.template(0, 1.0, 7, False)
    fv.template(1, 1.5, 7, True)  # a closure before its frame's pose: sent when the pose comes
    fv.pose(0, 1.0, np.array([1.0, 2.0, 0.0]), exp_id=0, local=np.array([0.0, 0.0, 0.0]))
    # experience 1 lies where pose o local^-1 puts it: at (3, 4) facing pi/2, the robot 1 m ahead of it
    fv.pose(1, 1.5, np.array([3.0, 5.0, math.pi / 2]), exp_id=1, local=np.array([1.0, 0.0, 0.0]))
    fv.stage_stats(2.0, "A", 12.5, {"processed": 3, "received": 4, "tau_p50_ms": 1.5,
                                    "inputs": {"image": {"evicted": 2}}})
    fv.log_line(1700000000.0, "WARNING", "source", "neoslam.source", "a warning")
    fv.jpeg(0, 1.0, cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))[1].tobytes())
    fv.run_ended({"frames_in": 2, "loss": 0.0, "status": "completed"})
    th.join(30)
    fv.close()
    r = got["r"]
    assert r.subprotocol in fc.SUBPROTOCOLS and r.server_info["capabilities"] == []
    # read-only: the server refused the client's channel, and had nothing to publish it to
    assert any(s["level"] == 2 and "clientPublish" in s["message"] for s in r.status)
    assert set(r.channels) == set(TOPICS)
    assert {t: c.schema_name for t, c in r.channels.items()} == TOPICS
    assert [(m["frame"], m["template_id"], m["is_loop_closure"]) for m in _values(r, "/neoslam/template")] == \
        [(0, 7, False), (1, 7, True)]
    (closure,) = _values(r, "/neoslam/loop_closure")
    assert (closure["frame"], closure["exp_id"], closure["x"], closure["y"]) == (1, 1, 3.0, 5.0)
    poses = [_xyq(m["pose"]) for m in _values(r, "/neoslam/pose")]
    assert poses[0] == (1.0, 2.0, 0.0, 1.0) and poses[1][:2] == (3.0, 5.0)
    assert math.isclose(poses[1][2], math.sin(math.pi / 4)) and math.isclose(poses[1][3], math.cos(math.pi / 4))
    scene = _values(r, "/neoslam/map")[-1]["entities"]
    spheres = {e["id"]: e.get("spheres", []) for e in scene}
    xy = sorted((round(s["pose"]["position"].get("x", 0.0), 9), round(s["pose"]["position"].get("y", 0.0), 9))
                for s in spheres["experiences"])
    assert xy == [(1.0, 2.0), (3.0, 4.0)]
    assert len(spheres["loop_closures"]) == 1
    (stats,) = _values(r, "/neoslam/stats")
    assert (stats["stage"], stats["rate_hz"], stats["processed"], stats["dropped"]) == ("A", 12.5, 3, 2)
    (line,) = _values(r, "/neoslam/log")
    assert (line["level"], line["message"], line["name"]) == ("WARNING", "a warning", "source: neoslam.source")
    (img,) = _values(r, "/camera/image")
    import base64

    assert img["format"] == "jpeg" and cv2.imdecode(np.frombuffer(base64.b64decode(img["data"]), np.uint8),
                                                    cv2.IMREAD_COLOR).shape == (8, 8, 3)
    assert _values(r, "/neoslam/run")[-1]["status"] == "completed"


def test_the_client_can_fail_on_a_message_off_its_schema():
    with pytest.raises(fc.SchemaError):
        fc.check_json({"frame": "one"}, {"type": "object", "properties": {"frame": {"type": "integer"}}})
    with pytest.raises(fc.SchemaError):
        fc.check_json({}, {"type": "object", "required": ["frame"]})
    fc.check_json({"x": None}, {"type": "object", "properties": {"x": {"type": ["number", "null"]}}})


# --------------------------------------------------------------------------- a real run
@pytest.fixture(scope="module")
def served_run(tmp_path_factory):
    """``neoslam run --foxglove`` of a light lossless run, with two clients: the checker, and one
    that subscribes to everything and then reads nothing (a hung viewer); a log line published by
    another process of the run while it runs."""
    from neoslam_stream.runtime import runlog

    tmp = tmp_path_factory.mktemp("foxglove")
    port = free_port()
    cfg = light_config("lossless", {"kind": "synthetic", "params": {"seed": 0, "frames": FRAMES}, "rate": 20.0,
                                    "pacing": "fixed"})
    cfg["foxglove"] = {"backlog": 100_000, "image_hz": 5.0}
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    run_dir = tmp / "run"
    proc = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(tmp / "cfg.yaml"),
                             "--out", str(run_dir), "--foxglove", f"127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    session, run_id = attach(run_dir)
    logged = threading.Event()

    def a_log_line() -> None:  # as any process of the run logs: through the bus
        handler = runlog.BusLogHandler(session, run_id, "test")
        handler.emit(__import__("logging").makeLogRecord({"msg": "hello from the test", "levelname": "WARNING",
                                                           "name": "neoslam.test"}))
        handler.close()
        logged.set()

    async def both():
        stalled = asyncio.create_task(fc.stall(f"ws://127.0.0.1:{port}", hold_s=2.0))  # hangs, then leaves mid-run
        got = await fc.collect(f"ws://127.0.0.1:{port}", until_s=400.0, publish_attempt=True,
                               on_first=lambda: threading.Timer(1.0, a_log_line).start())
        await stalled
        return got

    got = asyncio.run(both())
    out, _ = proc.communicate(timeout=400)
    session.close()
    assert proc.returncode == 0, out
    assert logged.is_set()
    return run_dir, got, out


def _check_against_the_run_folder(run_dir: Path, got: fc.Received) -> None:
    """Poses, templates and loop closures as the run folder's files hold them; the final map."""
    traj = np.loadtxt(run_dir / "trajectory.tum", ndmin=2)
    poses = _values(got, "/neoslam/pose")
    assert len(poses) == len(traj) == FRAMES
    for m, row in zip(poses, traj, strict=True):
        assert _t(m["timestamp"]) == pytest.approx(row[0], abs=1e-6) and m["frame_id"] == "map"
        assert _xyq(m["pose"]) == pytest.approx((row[1], row[2], row[6], row[7]), abs=2e-6)
    templates = _rows(run_dir / "templates.csv")
    sent = _values(got, "/neoslam/template")
    assert [(m["frame"], m["template_id"], int(m["is_loop_closure"])) for m in sent] == \
        [(int(r["frame"]), int(r["template_id"]), int(r["is_loop_closure"])) for r in templates]
    closures = _rows(run_dir / "closures.csv")
    assert closures, "the run closed no loop: nothing to compare"
    assert sorted(m["frame"] for m in _values(got, "/neoslam/loop_closure")) == [int(r["frame"]) for r in closures]
    # the last map is the final map.json: every experience where map.json puts it
    nodes = json.loads((run_dir / "map.json").read_text())["nodes"]
    spheres = {e["id"]: e.get("spheres", []) for e in _values(got, "/neoslam/map")[-1]["entities"]}["experiences"]
    sent_xy = sorted((s["pose"]["position"].get("x", 0.0), s["pose"]["position"].get("y", 0.0)) for s in spheres)
    assert np.allclose(sent_xy, sorted((n["x"], n["y"]) for n in nodes), atol=1e-9)
    traj_msg = _values(got, "/neoslam/trajectory")[-1]
    assert _xyq(traj_msg["poses"][-1])[:2] == pytest.approx(tuple(traj[-1, 1:3]), abs=2e-6)
    assert len(_values(got, "/neoslam/groundtruth")[-1]["poses"]) == FRAMES


@pytest.mark.zenoh
@pytest.mark.slow
def test_a_live_run_served_to_an_independent_client_equals_its_files(served_run):
    run_dir, got, out = served_run
    report = json.loads((run_dir / "report.json").read_text())
    # the hung client slowed and stopped nothing: every frame of the lossless run went through
    assert report["frames_out"] == FRAMES and report["loss"] == 0.0
    assert report["foxglove"]["clients"] == 2 and report["foxglove"]["status"] == "ended"
    assert "foxglove: ws://127.0.0.1:" in out
    # read-only: the client's attempt to publish was refused, and changed nothing
    assert any("clientPublish" in s["message"] for s in got.status)
    assert got.subprotocol in fc.SUBPROTOCOLS
    _check_against_the_run_folder(run_dir, got)
    # the camera: JPEG frames of the source's size, fewer than the frames (thinned to image_hz)
    images = _values(got, "/camera/image")
    import base64

    assert 1 <= len(images) < FRAMES
    assert cv2.imdecode(np.frombuffer(base64.b64decode(images[0]["data"]), np.uint8), cv2.IMREAD_COLOR).shape == \
        (240, 416, 3)
    # each stage's figures, its last count the report's
    stats = _values(got, "/neoslam/stats")
    for stage, row in report["stages"].items():
        mine = [m for m in stats if m["stage"] == stage]
        assert mine, stage
        assert max(m["processed"] for m in mine) == row["processed"], stage
    run = _values(got, "/neoslam/run")[-1]
    assert (run["frames_in"], run["frames_out"], run["loss"], run["status"]) == (FRAMES, FRAMES, 0.0, "completed")
    # the run's log lines: the test's, live, and in log.jsonl
    assert any(m["message"] == "hello from the test" and m["name"] == "test: neoslam.test"
               for m in _values(got, "/neoslam/log"))
    lines = [json.loads(x) for x in (run_dir / "log.jsonl").read_text().splitlines()]
    assert any(x.get("message") == "hello from the test" and x["process"] == "test" for x in lines)


@pytest.mark.zenoh
@pytest.mark.slow
def test_a_finished_run_served_from_its_files_equals_them(served_run, tmp_path):
    run_dir = served_run[0]
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "view", str(run_dir), "--foxglove",
                             f"127.0.0.1:{port}", "--speed", "0", "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # the replay starts once a client subscribed; the run's end (its status) comes after everything
    def ended(r: fc.Received) -> bool:
        run = r.messages.get("/neoslam/run")
        return bool(run) and run[-1][1]["status"] != "running"

    got = asyncio.run(fc.collect(f"ws://127.0.0.1:{port}", until_s=120.0, connect_timeout=120.0, stop_when=ended))
    proc.terminate()
    out, _ = proc.communicate(timeout=60)
    assert "served" in out, out
    _check_against_the_run_folder(run_dir, got)
    from neoslam_stream.runtime.camera_log import read_camera_zip

    kept = read_camera_zip(run_dir / "camera.zip")
    assert [_t(m["timestamp"]) for m in _values(got, "/camera/image")] == pytest.approx([s for _, s, _ in kept])
    assert any(m["message"] == "hello from the test" for m in _values(got, "/neoslam/log"))
    assert _values(got, "/neoslam/run")[-1]["status"] == "completed"


def test_the_shipped_layout_shows_only_served_topics_and_names_its_panels():
    import re

    from neoslam_stream.viewer.foxglove import LAYOUT, TOPICS

    layout = json.loads(LAYOUT.read_text())
    panels = set(layout["configById"])

    def leaves(node):
        return [node] if isinstance(node, str) else [*leaves(node["first"]), *leaves(node["second"])]

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    text = json.dumps(layout["configById"])
    named = set(re.findall(r'"(/(?:neoslam|camera)/[a-z_/]+)', text.replace('\\"', '"')))
    assert named and named <= set(TOPICS), named - set(TOPICS)
    assert {"/camera/image", "/neoslam/map", "/neoslam/log", "/neoslam/stats"} <= named
