"""``neoslam camera``: publish a camera's frames on zenoh for a run's ``zenoh`` source elsewhere
(the camera on the robot, the stages on a base station; docs/hosts.md)."""

from __future__ import annotations

import argparse
import signal
import threading
from typing import Any

from .report import error
from .run import _source_params

CAMERA_PARAMS = ("device", "url", "gstreamer", "width", "height", "rate_hz", "fourcc", "stall_timeout_s",
                 "open_timeout_s")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("camera", help="publish a camera's frames on zenoh for a run on another host",
                       description="Read a camera (a device, an RTSP/HTTP/UDP address, or a GStreamer "
                                   "pipeline) and publish its newest frames on a zenoh key, as the "
                                   "`zenoh` source of a run on another host reads them; its figures "
                                   "(rate, drops, outages) go to <KEY>/stats, which that run reports.")
    p.add_argument("-p", "--param", action="append", metavar="KEY=VALUE", default=[],
                   help="the camera, as for --source camera: -p device=0 (or /dev/videoN), -p url=rtsp://..., "
                        "-p gstreamer='... ! appsink'; also width, height, rate_hz, fourcc (a device's "
                        "requests), stall_timeout_s, open_timeout_s")
    p.add_argument("--key", required=True, help="zenoh key to publish on, e.g. robot1/camera "
                                                "(the run's --source zenoh -p key=...)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", default=[],
                   help="zenoh endpoint to connect to, e.g. the run's source listening on tcp/10.0.0.5:7450")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", default=[],
                   help="zenoh endpoint to listen on for the run's source to connect to")
    p.add_argument("--jpeg", nargs="?", type=int, const=90, metavar="QUALITY",
                   help="send JPEG of this quality (default 90) instead of raw frames")
    p.add_argument("--max-side", type=int, default=1920, metavar="N",
                   help="shrink frames whose long side exceeds N pixels before sending (default 1920)")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: Ctrl-C)")
    p.set_defaults(func=cmd_camera)


def _camera_kwargs(pairs: list[str]) -> dict[str, Any]:
    params = _source_params(pairs)
    unknown = sorted(set(params) - set(CAMERA_PARAMS))
    if unknown:
        raise ValueError(f"unknown camera parameter(s) {', '.join(unknown)}; known: {', '.join(CAMERA_PARAMS)}")
    return params


def cmd_camera(args: argparse.Namespace) -> int:
    from ..sources.camera_publisher import CameraPublisher
    from ..sources.capture import CameraError, LiveCapture, camera_target

    if not args.connect and not args.listen:
        return error("give --connect ENDPOINT (the run's zenoh source listens there) or --listen ENDPOINT", 2)
    try:
        params = _camera_kwargs(args.param)
        target = camera_target(*(params.pop(k, None) for k in ("device", "url", "gstreamer")))
        capture = LiveCapture(target, **params)
    except (CameraError, ValueError) as exc:
        return error(exc, 2)
    try:
        publisher = CameraPublisher(capture, args.key, listen=args.listen, connect=args.connect,
                                    jpeg_quality=args.jpeg, max_side=args.max_side)
    except Exception as exc:  # a bad endpoint or JPEG quality: one line
        capture.close()
        return error(exc, 2)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    opened = capture.figures()["opened"]
    print(f"camera {target.label} ({opened.get('width')}x{opened.get('height')}, {opened.get('backend')}) "
          f"publishing on {args.key} ({'JPEG q' + str(args.jpeg) if args.jpeg else 'raw'}), figures on "
          f"{args.key}/stats; Ctrl-C to stop", flush=True)
    f = publisher.run(stop, args.duration)
    print(f"published {f['published']} frames of {f['captured']} captured ({f['dropped']} dropped before "
          f"sending, {sum(f['skipped'].values())} skipped), {f['outage_count']} outages "
          f"({f['outage_s']:.1f} s without frames)")
    return 0
