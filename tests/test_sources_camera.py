"""``--source camera`` and ``neoslam camera`` against real streams on loopback (tests/camstreams.py):
an HTTP MJPEG server read through OpenCV's FFmpeg backend, stopped and started again mid-run;
MPEG-TS over UDP and RTSP served from ffmpeg's output where ffmpeg is installed. No V4L2 device can
be made here: the device path shares this code (docs/sources.md, "Live camera")."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from camstreams import (
    FFMPEG,
    NO_FFMPEG,
    MjpegServer,
    RtspServer,
    ffmpeg_testsrc,
    free_udp_port,
    gray_frame,
    jpeg,
)
from runhelpers import attach, still_running, wait_stats

from neoslam_stream.sources.camera import CameraSource
from neoslam_stream.sources.capture import (
    CameraError,
    LiveCapture,
    camera_target,
    frame_problem,
    gstreamer_available,
    loss_causes,
)


def _frames(src: CameraSource, n: int, timeout: float = 15.0) -> list:
    got, deadline = [], time.monotonic() + timeout
    for f in src:
        got.append(f)
        if len(got) >= n or time.monotonic() > deadline:
            break
    return got


def _wait(predicate, timeout: float = 15.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


# ----------------------------------------------------------------------------- in one process
def test_drops_after_the_stream_ended_are_not_the_runs_loss():
    """A camera's thread goes on replacing the frame in its slot while the run drains, until the
    source is closed: the source's stats keep its figures as they were when its stream ended."""
    from neoslam_stream.runtime.messages import decode
    from neoslam_stream.runtime.source_runner import SourceRunner, SourceRunSpec, SourceSpec

    class Camera:  # what the runner reads of a live camera: info() with its slot's drops
        dropped = 0
        errors: dict = {}

        def info(self):
            return {"kind": "camera", "dropped": self.dropped}

    class Session:
        def __init__(self):
            self.sent = []

        def put(self, key, payload):
            self.sent.append(decode(payload, expected_type="stats").data)

    cam = Camera()
    runner = SourceRunner(SourceRunSpec(source=SourceSpec("x:y", {}), run="r", run_dir=".", lossless=False,
                                        final_topic="t"), cam, None)
    runner.session = Session()
    cam.dropped = 2
    runner.publish_stats()  # streaming: the figures as they are
    runner.done = True  # the stream ended (duration, stop) with 3 drops
    cam.dropped = 3
    runner.publish_stats()
    cam.dropped = 60  # two seconds of a 30-FPS camera while the run drains
    runner.publish_stats(final=True)
    ring = [d["lost_at_source"].get(SourceRunner.RING) for d in runner.session.sent]
    assert ring == [2, 3, 3]
    assert runner.session.sent[-1]["info"]["dropped"] == 3


def test_the_camera_takes_the_robots_odometry_from_a_zenoh_key():
    """The robot publishes odom messages (as examples/publish_odometry.py does) while the camera
    streams: the frames carry the motion received since the frame before, as with the zenoh source."""
    from neoslam_stream.runtime.bus import open_session, wait_for_peers
    from neoslam_stream.runtime.messages import Message, encode
    from neoslam_stream.runtime.ports import free_port

    assert CameraSource.gives_odometry(url="http://x", odom_key="robot/odom") is True
    ep = f"tcp/127.0.0.1:{free_port()}"
    server = MjpegServer().start()
    robot = None
    try:
        src = CameraSource(url=server.url, odom_key="robot/odom", listen=[ep])
        robot = open_session(connect=[ep])
        wait_for_peers(robot, 1, 10.0)
        it = iter(src)
        first = next(it)
        assert first.odom == (0.0, 0.0, 0.0)  # the first frame moves nothing
        for i in range(4):  # 4 x 0.5 m at 1 m/s, 4 x 0.1 rad
            robot.put("robot/odom", encode(Message("odom", i, float(i), {"vtrans": 1.0, "vrot": 0.2, "dt": 0.5})))
        _wait(lambda: src.odometry.received == 4, what="the odometry messages")
        second = next(it)
        dt = second.odom[2]
        assert dt > 0 and second.odom[0] * dt == pytest.approx(2.0) and second.odom[1] * dt == pytest.approx(0.4)
        assert src.info()["odometry_received"] == 4
        src.close()
    finally:
        server.stop()
        if robot is not None:
            robot.close()


def test_camera_reads_an_http_mjpeg_stream_and_stamps_each_frame_when_captured():
    server = MjpegServer().start()
    try:
        before = time.time()
        src = CameraSource(url=server.url)
        got = _frames(src, 15)
        after = time.time()
        info = src.info()
        src.close()
    finally:
        server.stop()
    assert [f.frame for f in got] == list(range(15)) and src.length is None
    assert all(f.image.shape == (120, 160, 3) and f.encoding == "bgr8" for f in got)
    stamps = [f.stamp for f in got]
    assert before <= stamps[0] and stamps[-1] <= after and stamps == sorted(stamps)  # capture times
    # no wheel odometry: the run measures visual odometry (it knows before the run starts)
    assert got[0].odom is None and CameraSource.gives_odometry(url=server.url) is False
    assert abs(int(got[3].image[60, 100, 0]) - int(got[4].image[60, 100, 0])) > 0  # frames differ
    assert info["kind"] == "camera" and info["opened"]["backend"] == "FFMPEG"
    cam = info["camera"]
    assert cam["captured"] >= cam["taken"] == 15 and cam["outage_count"] == 0 and cam["skipped"] == {}
    assert info["lost"] == {} and info["dropped"] == cam["dropped"]


def test_a_stream_that_goes_away_is_reopened_with_backoff_and_its_outage_reported():
    server = MjpegServer().start()
    cap = LiveCapture(camera_target(url=server.url), stall_timeout_s=1.0, open_timeout_s=2.0)
    try:
        _wait(lambda: cap.take(0.5) is not None and cap.figures()["captured"] >= 10, what="frames")
        server.stop()  # the camera is unplugged
        _wait(lambda: cap.figures()["state"] == "reopening", what="the loss to be seen")
        assert cap.take(0.3) is None  # nothing to take, and no hang
        time.sleep(1.5)
        server.start()  # plugged back, same address
        _wait(lambda: cap.figures()["state"] == "streaming" and cap.take(0.5) is not None, what="reopening")
        figures = cap.figures()
    finally:
        cap.close()
        server.stop()
    assert not cap._thread.is_alive()  # close() ended the capture thread
    assert figures["outage_count"] == 1
    (outage,) = figures["outages"]
    assert outage["attempts"] >= 2 and "reads failed" in outage["cause"]
    # the outage runs from the last frame before the stop to the first after the start
    assert outage["length_s"] >= 1.0
    assert outage["frames_missed"] > 0  # at the stream's measured rate
    (cause, frames), = loss_causes(figures).items()
    assert cause.startswith("camera outages: 1, ") and "s without frames" in cause and frames == outage["frames_missed"]


def test_frames_of_another_encoding_or_broken_ones_mid_stream_are_counted_and_skipped():
    def frame(i):
        if i == 5:
            return jpeg(gray_frame(i, 80, 60))  # another size: FFmpeg scales it to the stream's
        if i == 8:
            return cv2.imencode(".png", gray_frame(i))[1].tobytes()  # another encoding
        if i == 11:
            return jpeg(gray_frame(i))[:400]  # cut short
        return jpeg(gray_frame(i))

    server = MjpegServer(frame=frame).start()
    src = CameraSource(url=server.url, stall_timeout_s=1.0)
    try:
        got = _frames(src, 14)
        _wait(lambda: server.sent >= 16, what="frames")
        info = src.info()
    finally:
        src.close()
        server.stop()
    assert {f.image.shape for f in got} == {(120, 160, 3)}
    cause = "unreadable frame (the backend's read failed, the stream went on)"
    assert src.errors == {cause: 2}  # the PNG and the cut JPEG, each counted, the stream going on
    assert info["lost"] == {f"camera: {cause}": 2}
    # what a backend that passes sizes through (GStreamer, V4L2) would give is checked the same way
    first = np.zeros((120, 160, 3), np.uint8)
    assert frame_problem(first, None) is None and frame_problem(first, first) is None
    assert "another size or encoding (80x60; the stream's is 160x120" in frame_problem(first[:60, :80], first)
    assert "1-channel uint8" in frame_problem(first[:, :, 0], first)
    assert "unsupported encoding" in frame_problem(np.zeros((4, 4, 3), np.uint16), None)


def test_parameters_name_one_camera_and_a_bad_one_says_what_to_do(tmp_path):
    from neoslam_stream.sources.files import VideoSource

    for kwargs, text in [({}, "name one camera"), ({"device": 0, "url": "rtsp://x/y"}, "given: device, url"),
                         ({"device": -1}, "0 or more"), ({"device": True}, "index"),
                         ({"device": "rtsp://x/y"}, "use -p url="), ({"url": "camera.mp4"}, "--source video"),
                         ({"device": str(tmp_path / "video9")}, "does not exist"),
                         ({"gstreamer": "videotestsrc"}, "ending in appsink")]:
        with pytest.raises(CameraError, match=text):
            camera_target(**kwargs)
    assert camera_target(device="0").address == 0
    if not gstreamer_available():  # this OpenCV build: one line naming what is missing
        with pytest.raises(CameraError, match="no GStreamer"):
            camera_target(gstreamer="videotestsrc ! appsink")
    with pytest.raises(CameraError, match="requested from a device"):
        CameraSource(url="http://127.0.0.1:9/feed.mjpg", width=640)
    with pytest.raises(CameraError, match="positive integer"):
        CameraSource(device=0, width="wide")
    started = time.monotonic()
    with pytest.raises(CameraError, match="cannot open http://127.0.0.1:9/feed.mjpg"):
        CameraSource(url="http://127.0.0.1:9/feed.mjpg", open_timeout_s=2.0)  # nothing serves there
    assert time.monotonic() - started < 15
    # the video source names the camera source for what is a camera, not a file
    for path, hint in [("/dev/video0", "device=/dev/video0"), (0, "device=0"),
                       ("udp://127.0.0.1:23000", "url=udp://127.0.0.1:23000")]:
        with pytest.raises(ValueError, match=f"--source camera -p {hint}"):
            VideoSource(path)


def test_a_live_source_runs_in_real_time_unless_the_mode_is_named():
    from neoslam_stream.config import load_config
    from neoslam_stream.sources import with_live_default

    def mode(over, config=None):
        return with_live_default(load_config(config, over)).run.mode

    assert mode({"source": {"kind": "camera"}}) == "realtime"
    assert mode({"source": {"kind": "zenoh"}}) == "realtime"
    assert mode({"source": {"kind": "camera"}, "run": {"mode": "lossless"}}) == "lossless"  # --lossless
    assert mode({"source": {"kind": "camera"}}, "paper") == "lossless"  # a config that names it
    assert mode({"source": {"kind": "video"}}) == mode({}) == "lossless"  # recorded data


@pytest.mark.skipif(FFMPEG is None, reason=NO_FFMPEG)
def test_camera_reads_an_mpegts_stream_over_udp():
    port = free_udp_port()
    sender = ffmpeg_testsrc([f"udp://127.0.0.1:{port}?pkt_size=1316"])
    try:
        src = CameraSource(url=f"udp://127.0.0.1:{port}", stall_timeout_s=2.0)
        got = _frames(src, 10)
        src.close()
    finally:
        sender.kill()
        sender.wait()
    assert [f.frame for f in got] == list(range(10)) and {f.image.shape for f in got} == {(120, 160, 3)}


@pytest.mark.skipif(FFMPEG is None, reason=NO_FFMPEG)
def test_camera_pulls_an_rtsp_stream():
    server = RtspServer()
    try:
        src = CameraSource(url=server.url, stall_timeout_s=2.0)
        got = _frames(src, 10)
        src.close()
    finally:
        server.stop()
    assert [f.frame for f in got] == list(range(10)) and {f.image.shape for f in got} == {(120, 160, 3)}


# ----------------------------------------------------------------------------- whole runs
def _run(tmp_path: Path, url: str, *extra: str) -> tuple[subprocess.Popen, Path]:
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "run", "--pipeline", "ratslam",
                             "--topology", "monolithic", "--source", "camera", "-p", f"url={url}",
                             "-p", "stall_timeout_s=1", "--no-live", "--out", str(run_dir), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return proc, run_dir


def _camera_state(session, run_id: str, state: str) -> dict:
    return wait_stats(session, run_id, "source", timeout=60,
                      until=lambda s: (s.get("info") or {}).get("camera", {}).get("state") == state
                      and s.get("frames_in", 0) >= 10)


@pytest.mark.slow
@pytest.mark.zenoh
def test_a_run_outlives_its_camera_going_away_and_reports_the_outage(tmp_path):
    """The camera stops mid-run and comes back: the run goes on, --duration ends it normally with
    every output, and report.json names the outage as a loss cause with its length."""
    import psutil

    server = MjpegServer().start()
    proc, run_dir = _run(tmp_path, server.url, "--duration", "7")
    try:
        session, run_id = attach(run_dir)
        children = psutil.Process(proc.pid).children(recursive=True)
        _camera_state(session, run_id, "streaming")
        server.stop()
        _camera_state(session, run_id, "reopening")
        time.sleep(1.0)
        server.start()
        session.close()
        out, _ = proc.communicate(timeout=120)
    finally:
        server.stop()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-3000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["mode"] == "realtime" and report["status"] == "completed"
    (outage,) = report["source"]["outages"]
    assert outage["length_s"] >= 1.0 and outage["frames_missed"] > 0
    causes = report["loss_breakdown"]["source"]
    (cause,) = [c for c in causes if c.startswith("camera outages: 1, ")]
    assert causes[cause] == outage["frames_missed"] and f"{outage['length_s']:.1f} s without frames" in cause
    poses = [r for r in (run_dir / "trajectory.tum").read_text().splitlines() if r and not r.startswith("#")]
    assert len(poses) == report["frames_out"] > 0
    assert "camera outages: 1" in out  # the summary's loss by cause
    time.sleep(0.5)
    assert still_running(children) == []


@pytest.mark.slow
@pytest.mark.zenoh
def test_ctrl_c_ends_a_run_whose_camera_is_gone_with_complete_outputs(tmp_path):
    """The camera goes away for good and the run is waiting for it: Ctrl-C still ends the run at
    once, flushing every output, and the outage in progress is counted."""
    import psutil

    server = MjpegServer().start()
    proc, run_dir = _run(tmp_path, server.url)
    try:
        session, run_id = attach(run_dir)
        children = psutil.Process(proc.pid).children(recursive=True)
        _camera_state(session, run_id, "streaming")
        server.stop()
        _camera_state(session, run_id, "reopening")
        session.close()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        server.stop()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out[-3000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["status"] == "interrupted" and report["frames_out"] > 0
    assert report["source"]["camera"]["state"] in ("reopening", "closed")
    assert report["source"]["camera"]["outage_count"] == 1
    assert (run_dir / "map.json").stat().st_size > 0 and (run_dir / "trajectory.tum").exists()
    time.sleep(0.5)
    assert still_running(children) == []


# ----------------------------------------------------------------------------- neoslam camera
@pytest.mark.zenoh
@pytest.mark.parametrize("jpeg_quality", [None, 80])
def test_neoslam_camera_publishes_what_the_zenoh_source_reads_with_its_figures(jpeg_quality):
    """The robot's side (``neoslam camera``, a process) and the base's (the ``zenoh`` source): the
    frames arrive numbered and stamped, and the camera's figures reach the source's info and the
    monitor table's camera row."""
    from rich.console import Console

    from neoslam_stream.runtime.monitor import stats_table
    from neoslam_stream.runtime.ports import free_port
    from neoslam_stream.sources.zenoh_camera import ZenohImageSource

    ep = f"tcp/127.0.0.1:{free_port()}"
    src = ZenohImageSource("robot1/camera", listen=[ep], capacity=64, timeout_s=20)
    server = MjpegServer().start()
    cmd = [sys.executable, "-m", "neoslam_stream.cli", "camera", "-p", f"url={server.url}", "--key", "robot1/camera",
           "--connect", ep, "--duration", "4", "--max-side", "80"]
    cam = subprocess.Popen(cmd + (["--jpeg", str(jpeg_quality)] if jpeg_quality else []),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    got = []
    try:
        for f in src:
            got.append(f)
            if len(got) >= 20:
                break
        out, _ = cam.communicate(timeout=60)
        time.sleep(0.3)  # its final figures
        info = src.info()
    finally:
        src.close()
        server.stop()
        if cam.poll() is None:
            cam.kill()
    assert cam.returncode == 0, out
    assert "publishing on robot1/camera" in out and "published" in out.splitlines()[-1]
    assert [f.frame for f in got] == list(range(20))
    if jpeg_quality:
        assert {f.format for f in got} == {"jpeg"} and cv2.imdecode(np.frombuffer(got[0].compressed, np.uint8),
                                                                    cv2.IMREAD_COLOR).shape == (60, 80, 3)
    else:
        assert {f.image.shape for f in got} == {(60, 80, 3)} and {f.encoding for f in got} == {"bgr8"}
    camera = info["camera"]
    assert camera["stage"] == "camera" and camera["final"] is True and camera["published"] >= 20
    assert camera["captured"] >= camera["published"] and camera["rate_hz"] > 0
    assert info["lost_before_source"] == 0
    console = Console(record=True, width=150)
    console.print(stats_table({"source": {"frames_in": 20, "first_publish": 0.0, "last_publish": 1.9,
                                          "lost_at_source": {}, "info": info}}))
    row = next(line for line in console.export_text().splitlines() if "camera" in line)
    assert str(camera["captured"]) in row and f"{camera['rate_hz']:.1f}" in row


def test_the_documented_camera_commands_parse_and_a_missing_camera_is_one_line(capsys):
    """Every ``neoslam camera`` line of the documents is a valid command line (the runs above use
    the same options), and a camera that is not there ends it with one line and exit code 2."""
    import shlex

    from test_documented_commands import COMMANDS

    from neoslam_stream.cli import build_parser, main

    documented = [c for _, c in COMMANDS if c.startswith("neoslam camera ")]
    assert len(documented) >= 2
    for cmd in documented:
        args = build_parser().parse_args(shlex.split(cmd.replace("ENDPOINT", "tcp/10.0.0.5:7450"))[1:])
        assert args.func.__name__ == "cmd_camera"
    args = build_parser().parse_args(["camera", "-p", "device=0", "--key", "k", "--connect", "tcp/h:1", "--jpeg"])
    assert args.jpeg == 90 and args.max_side == 1920
    assert main(["camera", "-p", "device=/dev/video77", "--key", "k", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "camera device /dev/video77 does not exist" in capsys.readouterr().err
    assert main(["camera", "-p", "device=0", "-p", "path=x", "--key", "k", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "unknown camera parameter(s) path" in capsys.readouterr().err
