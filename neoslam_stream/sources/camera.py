"""``--source camera``: a live camera by device, URL or GStreamer pipeline, read through OpenCV.

The camera is opened when the source is built, so a wrong device or address ends the run at once
with one line saying what to check; from then on it is read by :class:`~.capture.LiveCapture`'s
thread, which keeps only the newest frame and reopens a lost stream with backoff. A live camera
is a live source: a run with it defaults to real-time mode (``Source.live``). A camera
gives no wheel odometry: each frame carries zero motion, as an image folder without
``odometry.tum`` does (``odometry: visual`` measures the motion from the images instead).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

from ..runtime.pixels import fit
from .base import Source, SourceFrame
from .capture import CameraError, LiveCapture, camera_target, frame_encoding, loss_causes
from .imaging import DEFAULT_MAX_SIDE
from .odometry import OdometrySubscription, frame_odometry

log = logging.getLogger("neoslam.sources.camera")

__all__ = ["CameraError", "CameraSource"]


class CameraSource(Source):
    """Frames of a live camera, stamped with their capture time (seconds since the epoch).

    Exactly one of ``device`` (0, or /dev/video0), ``url`` (rtsp://, http://...mjpg, udp://, any
    input OpenCV's FFmpeg reads) or ``gstreamer`` (a pipeline ending in appsink). A device is asked
    for ``width``, ``height``, ``rate_hz`` and ``fourcc`` (e.g. MJPG). ``max_side`` bounds the long
    side of a frame; ``stall_timeout_s``: a stream without a frame for that long is reopened;
    ``open_timeout_s`` bounds each opening; ``timeout_s`` ends the stream after that long without
    a frame (None: only the run's end does). Odometry: none (the run measures visual odometry), or
    the robot's ``odom`` messages on ``odom_key`` (``sources/odometry.py``; ``connect`` / ``listen``:
    the endpoints where the robot publishes them), summed into each frame's motion.
    """

    live = True

    def __init__(self, device: int | str | None = None, url: str | None = None, gstreamer: str | None = None,
                 width: int | None = None, height: int | None = None, rate_hz: float | None = None,
                 fourcc: str | None = None, max_side: int | None = DEFAULT_MAX_SIDE, stall_timeout_s: float = 3.0,
                 open_timeout_s: float = 10.0, timeout_s: float | None = None, odom_key: str | None = None,
                 connect: list[str] | None = None, listen: list[str] | None = None) -> None:
        self.capture = LiveCapture(camera_target(device, url, gstreamer), width=width, height=height,
                                   rate_hz=rate_hz, fourcc=fourcc, stall_timeout_s=stall_timeout_s,
                                   open_timeout_s=open_timeout_s)
        self.max_side = max_side
        self.timeout_s = timeout_s
        self.length = None
        self.rate_hz = rate_hz or self.capture.opened.get("fps")
        self.ended_by_timeout = False
        self.odometry = OdometrySubscription(odom_key, connect=connect, listen=listen) if odom_key else None

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        """With ``odom_key``: the robot's odometry messages; else frames only (visual odometry)."""
        return bool(params.get("odom_key"))

    def __iter__(self) -> Iterator[SourceFrame]:
        frame = 0
        prev: float | None = None
        cap = self.capture
        while True:
            item = cap.take(0.25)
            if item is None:
                if cap.closed:
                    return
                if self.timeout_s is not None and cap.seconds_without_frame() > self.timeout_s:
                    log.warning("camera %s: no frame for %g s (timeout_s): the stream ends", cap.target.label,
                                self.timeout_s)
                    self.ended_by_timeout = True
                    return
                continue
            dt = 0.0 if prev is None else max(0.0, item.stamp - prev)
            prev = item.stamp
            odom = frame_odometry(self.odometry.take(), dt) if self.odometry is not None else None
            yield SourceFrame(frame, item.stamp, image=fit(item.image, self.max_side),
                              encoding=frame_encoding(item.image) or "bgr8", odom=odom)
            frame += 1

    @property
    def errors(self) -> dict[str, int]:
        """The frames the camera skipped, per cause (a snapshot: the capture thread adds to them)."""
        return dict(self.capture.figures()["skipped"])

    def info(self) -> dict[str, Any]:
        """For report.json: the camera's figures, its drops (``dropped``: replaced before they
        were taken) and the frames it lost per cause (``lost``: outages, skipped frames)."""
        figures = self.capture.figures()
        return {"kind": "camera", "target": figures["target"], "opened": figures["opened"],
                "rate_hz": self.rate_hz, "dropped": figures["dropped"], "lost": loss_causes(figures),
                "outages": figures["outages"], "camera": figures, "ended_by_timeout": self.ended_by_timeout,
                "odometry_received": self.odometry.received if self.odometry is not None else 0}

    def interrupt(self) -> None:
        """End the iteration soon (the run's stop or duration while the camera is silent)."""
        self.capture.close()

    def close(self) -> None:
        self.capture.close()
        if self.odometry is not None:
            self.odometry.close()
