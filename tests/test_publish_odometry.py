"""examples/publish_odometry.py end to end: a robot without ROS publishes its wheel odometry on a zenoh
key while a camera publishes images, and a run with the ``zenoh`` source integrates that odometry.

The wheel speeds are hand-made: 2 s straight at 0.5 m/s (left = right = 0.5), then 1 s spinning on
the spot at 1 rad/s (left = -0.2, right = 0.2 on a 0.4 m track), each reading's speeds held until
the next reading, all between camera frames 0 and 1.
So frame 1 carries 1.0 m and 1.0 rad, and the experience map, which turns by a frame's rotation and
then advances by its distance, puts the robot at (cos 1, sin 1) from where it started facing +x."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from runhelpers import attach, finish, start_run, wait_stats

from neoslam_stream.runtime.bus import open_session, wait_for_peers
from neoslam_stream.runtime.messages import Message, encode
from neoslam_stream.runtime.ports import free_port
from neoslam_stream.tum import read_tum

pytestmark = pytest.mark.zenoh
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "publish_odometry.py"


def test_the_speeds_of_a_differential_drive():
    sys.path.insert(0, str(EXAMPLE.parent))
    from publish_odometry import readings, speeds

    assert speeds(0.5, 0.5, 0.4) == (0.5, 0.0)
    assert speeds(-0.2, 0.2, 0.4) == pytest.approx((0.0, 1.0))
    assert list(readings(["stamp,left,right", "# a comment", "", "1.5, 0.1, 0.2"])) == [(1.5, 0.1, 0.2)]


def test_a_run_integrates_the_odometry_the_example_publishes(tmp_path):
    # each reading's speeds hold until the next: 0.0-2.0 s straight, 2.0-3.0 s spinning
    rows = [(0.1 * i, 0.5, 0.5) for i in range(20)] + [(2.0 + 0.1 * i, -0.2, 0.2) for i in range(11)]
    csv = tmp_path / "wheels.csv"
    csv.write_text("stamp,left,right\n" + "".join(f"{t:.1f},{left},{right}\n" for t, left, right in rows))
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = {"base": "none", "run": {"pipeline": "ratslam", "mode": "realtime", "live": False, "drain_s": 1.0},
           "experience_map": {"exp_initial_em_deg": 0.0},
           "source": {"kind": "zenoh", "params": {"key": "robot/camera", "odom_key": "robot/odom", "listen": [ep],
                                                 "timeout_s": 3.0, "capacity": 16}}}
    proc = start_run(tmp_path, cfg)
    session, run_id = attach(tmp_path / "run")
    camera = open_session(connect=[ep])
    try:
        assert wait_for_peers(camera, 1, 120.0), "the run's source did not come up"
        rng = np.random.default_rng(0)
        image = rng.integers(0, 256, (96, 160, 3), dtype=np.uint8)

        def frame(i: int, stamp: float) -> None:
            camera.put("robot/camera", encode(Message("image", i, stamp, {"image": image, "encoding": "rgb8"})))
            wait_stats(session, run_id, "experience_map", until=lambda s: s.get("processed", 0) >= i + 1)

        frame(0, 0.0)
        sent = subprocess.run([sys.executable, str(EXAMPLE), "--csv", str(csv), "--key", "robot/odom",
                               "--connect", ep, "--track", "0.4"], capture_output=True, text=True, timeout=120)
        assert sent.returncode == 0, sent.stderr
        assert "published 30 odometry messages" in sent.stdout
        frame(1, 3.0)
        frame(2, 3.1)
    finally:
        camera.close()
        session.close()
    out = finish(proc, timeout=120)
    assert proc.returncode == 0, out
    traj = read_tum(tmp_path / "run" / "trajectory.tum")
    assert traj.shape[0] == 3
    # frame 1: 1.0 rad, then 1.0 m along the new heading; frame 2 did not move
    np.testing.assert_allclose(traj[1, 1:4], [math.cos(1.0), math.sin(1.0), 1.0], atol=1e-6)
    np.testing.assert_allclose(traj[2, 1:4], traj[1, 1:4], atol=1e-9)
