"""Before a run starts: every source's parameters are checked (an unknown name or a bad value is one
line and exit 2, and no run folder is left), the odometry rule is applied (a source without odometry
makes the run measure visual odometry, and the run says so), and the run says which robot it assumes."""

from __future__ import annotations

from pathlib import Path

import pytest

from neoslam_stream.config import load_config
from neoslam_stream.launch import prepare
from neoslam_stream.sources import check_source, gives_odometry
from neoslam_stream.sources.params import PositiveFloat, SourceParamError


class CameraOfMine:
    """A source of one's own (``--source test_source_params:CameraOfMine``), checked by its annotations."""

    def __init__(self, device: int, rate_hz: PositiveFloat = 30.0) -> None:
        pass


@pytest.mark.parametrize("kind,params,says", [
    ("folder", {"path": "."}, None),
    ("folder", {"path": ".", "rate": 5}, r"source folder: unknown parameter 'rate' \(it takes path, rate_hz"),
    ("folder", {"path": ".", "rate_hz": -5}, r"source folder: rate_hz = -5: Input should be greater than 0"),
    ("folder", {"rate_hz": 5}, r"parameter 'path' is missing"),
    ("folder", {"path": "nowhere"}, r"path = 'nowhere': nowhere does not exist"),
    ("folder", {"path": ".", "odometry": "none.tum"}, r"odometry = 'none.tum'"),
    ("video", {"path": "v.mp4", "max_frames": 0}, r"max_frames = 0: Input should be greater than 0"),
    ("bag", {"path": "nowhere.bag", "image_topic": "/cam"}, r"nowhere.bag does not exist"),
    ("synthetic", {"frames": 10, "speeed": 1}, r"unknown parameter 'speeed'"),
    ("synthetic", {"laps_cw": 0, "laps_ccw": 0}, r"at least one lap"),
    ("zenoh", {"key": "cam", "capacity": 0}, r"capacity = 0"),
    ("zenoh", {"key": "cam", "timeout_s": -1}, r"timeout_s = -1"),
    ("zenoh", {"key": "cam", "mode": "router"}, r"mode = 'router'"),
    ("zenoh-ros2", {"image_topic": "/cam", "namespace": 1}, r"rmw-zenoh -p domain_id"),
    ("rmw-zenoh", {"image_topic": "/cam", "domain_id": 300}, r"domain_id = 300"),
    ("test_source_params:CameraOfMine", {"device": 0, "rate_hz": 0}, r"rate_hz = 0"),
    ("test_source_params:CameraOfMine", {"rate_hz": 5}, r"parameter 'device' is missing"),
    ("test_source_params:CameraOfMine", {"device": 0, "fps": 5}, r"unknown parameter 'fps' \(it takes device, rate_hz\)"),
])
def test_every_source_checks_its_parameters_before_it_is_built(kind, params, says, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if says is None:
        check_source(kind, params)
        return
    with pytest.raises(SourceParamError, match=says) as exc:
        check_source(kind, params)
    assert "\n" not in str(exc.value)


def test_a_host_without_the_source_does_not_look_for_its_files():
    check_source("folder", {"path": "on/the/robot"}, files=False)
    with pytest.raises(SourceParamError, match="rate_hz"):
        check_source("folder", {"path": "on/the/robot", "rate_hz": 0}, files=False)


@pytest.mark.parametrize("flag", [["-p", "rate=5"], ["-p", "rate_hz=-5"], ["-p", "path=nowhere"]])
def test_a_bad_source_parameter_ends_neoslam_run_with_one_line_and_no_run_folder(flag, tmp_path, capsys,
                                                                                 monkeypatch):
    from neoslam_stream.cli import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["run", "--source", "folder", "-p", "path=.", *flag, "--out", "runs/x", "--no-live"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: source folder:") and len(err.splitlines()) == 1
    assert not (tmp_path / "runs").exists()


# ---------------------------------------------------------------------------- the odometry rule
def _folder(tmp_path: Path, odometry: bool) -> str:
    (tmp_path / "images").mkdir(exist_ok=True)
    if odometry:
        (tmp_path / "odometry.tum").write_text("0 0 0 0 0 0 0 1\n")
    return str(tmp_path)


@pytest.mark.parametrize("kind,params,odometry", [
    ("synthetic", {}, True),
    ("video", {"path": "robot.mp4"}, False),
    ("zenoh", {"key": "cam"}, False),
    ("zenoh", {"key": "cam", "odom_key": "odo"}, True),
    ("zenoh-ros2", {"image_topic": "/cam"}, False),
    ("rmw-zenoh", {"image_topic": "/cam", "odom_topic": "/odom"}, True),
    ("bag", {"path": "x.bag", "image_topic": "/cam"}, False),
    ("bag", {"path": "x.bag", "image_topic": "/cam", "odom_topic": "/odom"}, True),
    ("test_source_params:CameraOfMine", {"device": 0}, None),  # it does not say
])
def test_each_source_says_whether_it_gives_odometry(kind, params, odometry):
    assert gives_odometry(kind, params) is odometry


def test_a_source_without_odometry_makes_the_run_measure_visual_odometry_and_say_so(tmp_path):
    with_odo = load_config("default", {"source": {"kind": "folder", "params": {"path": _folder(tmp_path, True)}}})
    cfg, notes = prepare(with_odo)
    assert cfg.odometry == "wheel" and notes == []
    no_odo = tmp_path / "no"
    no_odo.mkdir()
    cfg, notes = prepare(load_config("default", {"source": {"kind": "folder",
                                                            "params": {"path": _folder(no_odo, False)}}}))
    assert cfg.odometry == "visual" and len(notes) == 1
    assert notes[0].startswith("source folder gives no odometry: this run measures visual odometry")
    assert "0.3 m/s" in notes[0] and "camera_fov_deg" in notes[0]
    assert prepare(cfg) == (cfg, [])  # said once: the config now says visual
    with pytest.raises(SourceParamError, match="oracle"):
        prepare(load_config("default", {"run": {"pipeline": "oracle"},
                                        "source": {"kind": "folder", "params": {"path": str(no_odo)}}}))


def test_the_run_says_which_robot_it_assumes(tmp_path):
    from neoslam_stream.cli.report import platform_lines

    default = load_config("default")
    assert platform_lines(default) == ["platform: typical speed 0.3 m/s, shortest loop 23.7 m, area 10 m"]
    folder = load_config("default", {"source": {"kind": "folder", "params": {"path": str(tmp_path)}}})
    lines = platform_lines(folder)  # another source with the synthetic world's robot: say how to set it
    assert len(lines) == 2 and "the synthetic world's robot" in lines[1] and "platform: {speed_mps:" in lines[1]
    own = load_config("default", {"source": {"kind": "folder", "params": {"path": str(tmp_path)}},
                                  "platform": {"speed_mps": 1.2}})
    assert platform_lines(own) == ["platform: typical speed 1.2 m/s, shortest loop 23.7 m, area 10 m"]


@pytest.mark.slow
@pytest.mark.zenoh
def test_a_video_runs_to_its_end_on_visual_odometry(tmp_path):
    """A video has no odometry: the run measures it from the images (it used to wait for odometry
    that never came), says so at its start, and the robot moves by what the images show."""
    import subprocess
    import sys

    import cv2
    import numpy as np

    from neoslam_stream.sources.synthetic import SyntheticWorldSource
    from neoslam_stream.tum import read_tum

    video = tmp_path / "robot.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 96))
    for f in SyntheticWorldSource(frames=40, width=160, height=96):
        writer.write(np.ascontiguousarray(f.image[:, :, ::-1]))
    writer.release()
    r = subprocess.run([sys.executable, "-m", "neoslam_stream.cli", "run", "--source", "video", "-p",
                        f"path={video}", "--no-live", "--out", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "source video gives no odometry: this run measures visual odometry" in r.stdout
    traj = read_tum(tmp_path / "run" / "trajectory.tum")
    assert len(traj) == 40
    # 39 intervals at the platform's typical speed, read from the images: the robot went somewhere
    assert np.hypot(*np.diff(traj[:, 1:3], axis=0).T).sum() > 0.1 * 39 * 0.3
