"""Publish a robot's wheel odometry to neoslam over zenoh, without ROS: a short program to adapt.

It reads wheel speeds, one reading a line, from a CSV file or a serial line, turns each reading into
the robot's forward speed and yaw rate (a differential drive: v = (left + right) / 2 and
w = (right - left) / track), and publishes the motion between consecutive readings as neoslam's
``odom`` message on a zenoh key: ``{"vtrans": v, "vrot": w, "dt": seconds}``, the earlier
reading's speeds held until the next (as a ROS bag's twists are integrated). A live source of
neoslam (``--source zenoh -p odom_key=KEY``) sums them into each camera frame's odometry::

    neoslam run --realtime --source zenoh -p key=robot/camera -p odom_key=robot/odom \\
        -p 'listen=["tcp/0.0.0.0:7448"]'
    python examples/publish_odometry.py --csv wheels.csv --key robot/odom --connect tcp/SLAM_HOST:7448

A CSV line is ``stamp,left,right`` (seconds, m/s, m/s); a line ``left,right`` is stamped when it is
read. Blank lines, ``#`` comments and a header line are skipped. ``--serial /dev/ttyUSB0`` reads
the same lines from a serial port (needs ``pip install pyserial``). To adapt: change
:func:`speeds` for another drive (an Ackermann car: v from the wheel speed, w = v tan(steer) /
wheelbase) or :func:`readings` for another input; the message stays the same.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator

from neoslam_stream.runtime.bus import open_session, wait_for_peers
from neoslam_stream.runtime.messages import Message, encode


def speeds(left: float, right: float, track_m: float) -> tuple[float, float]:
    """(forward speed m/s, yaw rate rad/s) of a differential drive from its wheels' speeds."""
    return (left + right) / 2.0, (right - left) / track_m


def readings(lines: Iterator[str]) -> Iterator[tuple[float, float, float]]:
    """(stamp s, left m/s, right m/s) per line; lines without a stamp get the time they are read."""
    for raw in lines:
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            continue  # a header line
        if len(values) == 2:
            yield (time.time(), *values)
        elif len(values) >= 3:
            yield values[0], values[1], values[2]


def serial_lines(device: str, baud: int) -> Iterator[str]:
    import serial  # pyserial

    with serial.Serial(device, baud, timeout=1.0) as port:
        while True:
            line = port.readline()
            if line:
                yield line.decode("ascii", "replace")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Publish wheel odometry as neoslam odom messages on a zenoh key.")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--csv", help="a file of 'stamp,left,right' lines (m/s)")
    src.add_argument("--serial", help="a serial device sending 'left right' or 'stamp,left,right' lines")
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--track", type=float, default=0.5, help="distance between the wheels (m)")
    ap.add_argument("--key", default="robot/odom", help="the zenoh key (the source's odom_key)")
    ap.add_argument("--connect", action="append", default=[], help="zenoh endpoint of the run's source")
    ap.add_argument("--pace", action="store_true", help="replay the readings at the pace of their stamps")
    args = ap.parse_args(argv)

    session = open_session(connect=args.connect)
    if args.connect and not wait_for_peers(session, 1, 30.0):
        print(f"nobody at {args.connect}", file=sys.stderr)
        return 1
    time.sleep(0.5)  # let the source's subscription reach this session
    pub = session.declare_publisher(args.key)
    lines = open(args.csv) if args.csv else serial_lines(args.serial, args.baud)
    prev: tuple[float, float, float] | None = None
    sent, start = 0, None
    for stamp, left, right in readings(lines):
        start = start or (stamp, time.monotonic())
        if args.pace:  # the reading at `stamp` ends an interval: send it that long after the first
            time.sleep(max(0.0, (stamp - start[0]) - (time.monotonic() - start[1])))
        if prev is not None and stamp > prev[0]:
            vtrans, vrot = speeds(prev[1], prev[2], args.track)
            pub.put(encode(Message("odom", sent, stamp, {"vtrans": vtrans, "vrot": vrot, "dt": stamp - prev[0]})))
            sent += 1
        prev = (stamp, left, right)
    time.sleep(0.5)  # let the last messages leave before the session closes
    session.close()
    print(f"published {sent} odometry messages on {args.key}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
