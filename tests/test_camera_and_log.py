"""What a run folder keeps for viewers: camera.zip (the camera, thinned and bounded) and the run's
log lines (published on the bus by every process, kept in log.jsonl)."""

from __future__ import annotations

import json
import logging
import threading
import time
import zipfile

import cv2
import numpy as np
import pytest

from neoslam_stream.runtime.bus import key_for, open_session, wait_for_peers
from neoslam_stream.runtime.camera_log import CAMERA_FILE, CameraLog, read_camera_zip
from neoslam_stream.runtime.ports import free_port


def test_the_camera_is_kept_thinned_and_bounded(tmp_path):
    cam = CameraLog(period_s=0.5, max_frames=4, max_side=64)
    for f in range(40):  # 10 Hz for 4 s: every 5th frame, until 4 are exceeded; then every 2nd of them
        cam.add(f, 0.1 * f, np.full((120, 160, 3), f, np.uint8))
    assert len(cam.frames) <= 4 and cam.period_s > 0.5
    kept = [f for f, _, _ in cam.frames]
    assert kept == sorted(kept) and kept[0] == 0
    path = cam.write(tmp_path)
    assert path == tmp_path / CAMERA_FILE
    with zipfile.ZipFile(path) as z:
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())
        assert "frames.csv" in z.namelist()
    back = read_camera_zip(path)
    assert [f for f, _, _ in back] == kept
    img = cv2.imdecode(np.frombuffer(back[0][2], np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (48, 64, 3)  # at most max_side on the longer side


def test_frames_it_cannot_read_are_counted_not_kept(tmp_path):
    cam = CameraLog(period_s=0.0 + 1e-9)
    cam.add(0, 0.0, compressed=b"\xff\xd8 not a jpeg")
    cam.add(1, 1.0, image=np.zeros((4, 4), np.float32))  # not uint8
    png = cv2.imencode(".png", np.zeros((10, 12), np.uint8))[1].tobytes()
    cam.add(2, 2.0, compressed=png)  # a grey PNG from an image folder: kept
    cam.add(3, 3.0, image=np.zeros((10, 12, 3), np.uint8), encoding="bgr8")
    assert cam.unreadable == 2 and [f for f, _, _ in cam.frames] == [2, 3]
    assert CameraLog(period_s=0).write(tmp_path) is None  # nothing kept: no file


def _session_pair():
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = open_session(listen=[ep])
    b = open_session(connect=[ep])
    assert wait_for_peers(b, 1, 10.0)
    return a, b


@pytest.mark.zenoh
def test_log_lines_go_on_the_bus_into_log_jsonl_bounded_per_second(tmp_path, monkeypatch):
    from neoslam_stream.runtime import runlog

    monkeypatch.setattr(runlog, "MAX_PER_S", 5)
    pub, sub = _session_pair()
    lines = runlog.LogFile(tmp_path, t0=time.time())
    s = sub.declare_subscriber(key_for("r1", "log"), lines.on_sample)
    time.sleep(0.5)
    handler = runlog.attach(pub, "r1", "worker A")
    log = logging.getLogger("neoslam.test_runlog")
    try:
        for i in range(12):  # within one second at most 5 pass; the rest are counted
            log.warning("line %d", i)
        deadline = time.monotonic() + 10
        while lines.lines < 12 - handler.suppressed and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
    finally:
        runlog.detach(handler)
        s.undeclare()
        sub.close()
        pub.close()
    rows = [json.loads(x) for x in (tmp_path / runlog.LOG_FILE).read_text().splitlines()]
    assert 1 <= len(rows) <= 10 and len(rows) + handler.suppressed == 12
    assert rows[0]["message"] == "line 0" and rows[0]["process"] == "worker A" and rows[0]["level"] == "WARNING"
    assert rows[0]["name"] == "neoslam.test_runlog" and rows[0]["t_s"] >= 0


def test_a_log_record_logged_while_publishing_is_not_published_again():
    from neoslam_stream.runtime import runlog

    class Publisher:
        def __init__(self):
            self.sent = 0

        def put(self, payload):
            self.sent += 1
            logging.getLogger("zenoh.inside").warning("logged while publishing")  # would loop

    class Session:
        def declare_publisher(self, key, congestion_control=None):
            return pub

    pub = Publisher()
    handler = runlog.BusLogHandler(Session(), "r", "p")
    logging.getLogger().addHandler(handler)
    try:
        logging.getLogger("neoslam.x").warning("once")
    finally:
        logging.getLogger().removeHandler(handler)
    assert pub.sent == 1


def test_log_jsonl_is_bounded(tmp_path, monkeypatch):
    from neoslam_stream.runtime import runlog
    from neoslam_stream.runtime.messages import LOG, Message, encode

    monkeypatch.setattr(runlog, "MAX_LINES", 3)
    lf = runlog.LogFile(tmp_path, t0=0.0)

    class Sample:
        def __init__(self, payload):
            self.payload = type("P", (), {"to_bytes": lambda _self: payload})()

    msg = encode(Message(str(LOG), 0, 5.0, {"level": "ERROR", "process": "p", "name": "n", "message": "m"}))
    threads = [threading.Thread(target=lf.on_sample, args=(Sample(msg),)) for _ in range(5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    lf.on_sample(Sample(b"not a message"))  # ignored
    lf.close()
    rows = [json.loads(x) for x in (tmp_path / runlog.LOG_FILE).read_text().splitlines()]
    assert len(rows) == 4 and rows[-1] == {"t_s": None, "skipped": 2}


def test_log_jsonl_is_readable_line_by_line_and_a_restarted_monitor_appends(tmp_path):
    from neoslam_stream.runtime import runlog
    from neoslam_stream.runtime.messages import LOG, Message, encode

    class Sample:
        def __init__(self, message):
            payload = encode(Message(str(LOG), 0, 5.0, {"level": "INFO", "process": "p", "name": "n",
                                                        "message": message}))
            self.payload = type("P", (), {"to_bytes": lambda _self: payload})()

    def messages():
        return [json.loads(x)["message"] for x in (tmp_path / runlog.LOG_FILE).read_text().splitlines()]

    first = runlog.LogFile(tmp_path, t0=0.0)
    first.on_sample(Sample("one"))
    assert messages() == ["one"]  # a viewer sees the line while the run goes on
    first.on_sample(Sample("two"))
    assert messages() == ["one", "two"]
    first.close()
    first.on_sample(Sample("after close"))  # a callback late after the monitor closed: dropped
    again = runlog.LogFile(tmp_path, t0=0.0)  # the monitor's second life
    again.on_sample(Sample("three"))
    again.close()
    assert messages() == ["one", "two", "three"]
