"""A live camera read by OpenCV in its own thread, which keeps only the newest frame.

A camera does not wait for its reader: a reader that falls behind must get the newest frame, not a
growing backlog (OpenCV's FFmpeg backend would otherwise buffer seconds of a network stream). So a
capture thread reads as fast as the camera delivers, stamps each frame with its capture time and
puts it in a one-frame slot; a frame replaced there before it was taken is a drop, counted (the
run's drop-oldest rule). Both ``--source camera`` (camera.py) and ``neoslam camera``
(camera_publisher.py) read through :class:`LiveCapture`.

Faults are causes, not crashes: a stream that stalls (no frame for ``stall_timeout_s``), ends or
fails to read three times in a row is released and reopened with backoff (0.5 s doubling to 5 s),
for as long as the reader runs; each outage is kept with its length and the frames the camera
would have sent meanwhile, estimated from the stream's own rate (:func:`loss_causes`). A frame of
another size or encoding than the stream's (set by the first frame after each opening) is counted
and skipped. Nothing here was tried on a V4L2 device (docs/sources.md, "Live camera").
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

log = logging.getLogger("neoslam.sources.camera")

#: reopening waits this long first, then doubles the wait after each failed attempt, up to the max
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 5.0
#: consecutive failed reads that end a stream (a single corrupt frame does not)
FAILED_READS_LOST = 3
#: outages logged one by one; later ones are counted in the report only
LOGGED_OUTAGES = 20
#: outages kept in the figures (the totals count them all)
KEPT_OUTAGES = 20
#: the stream's rate is measured over this many of its last frames
RATE_WINDOW = 50


class CameraError(RuntimeError):
    """A camera that cannot be opened or a parameter that names none; the text says what to do."""


@dataclass(frozen=True)
class CameraTarget:
    """What to open: ``kind`` device | url | gstreamer, ``address`` as VideoCapture takes it,
    ``api`` the OpenCV backend, ``label`` for messages."""

    kind: str
    address: int | str
    api: int
    label: str


def gstreamer_available() -> bool:
    """Whether this OpenCV build reads GStreamer pipelines (its build information says so)."""
    m = re.search(r"^\s*GStreamer:\s*(\S+)", cv2.getBuildInformation(), re.M)
    return bool(m) and m.group(1).upper() != "NO"


def _video_devices() -> str:
    found = sorted(str(p) for p in Path("/dev").glob("video*")) if sys.platform.startswith("linux") else []
    return ", ".join(found) if found else "none"


def camera_target(device: int | str | None = None, url: str | None = None,
                  gstreamer: str | None = None) -> CameraTarget:
    """The camera that exactly one of ``device`` (an index such as 0, or a path such as
    /dev/video0), ``url`` (rtsp://, http://, udp://... any input OpenCV's FFmpeg reads) or
    ``gstreamer`` (a pipeline ending in appsink) names; a CameraError says what is wrong."""
    given = [n for n, v in (("device", device), ("url", url), ("gstreamer", gstreamer)) if v is not None]
    if len(given) != 1:
        raise CameraError("name one camera: -p device=0 (or /dev/videoN), -p url=rtsp://... or "
                          f"-p gstreamer='... ! appsink' (given: {', '.join(given) or 'none'})")
    linux = sys.platform.startswith("linux")
    if device is not None:
        if isinstance(device, bool) or not isinstance(device, (int, str)):
            raise CameraError(f"device {device!r} must be an index (0) or a device path (/dev/video0)")
        if isinstance(device, str) and device.isdigit():
            device = int(device)
        if isinstance(device, int):
            if device < 0:
                raise CameraError(f"device index {device} must be 0 or more")
            return CameraTarget("device", device, cv2.CAP_V4L2 if linux else cv2.CAP_ANY, f"device {device}")
        if "://" in device:
            raise CameraError(f"device {device!r} is an address: use -p url={device}")
        if not Path(device).exists():
            raise CameraError(f"camera device {device} does not exist (video devices here: {_video_devices()})")
        return CameraTarget("device", device, cv2.CAP_V4L2 if linux else cv2.CAP_ANY, f"device {device}")
    if url is not None:
        if not isinstance(url, str) or "://" not in url:
            raise CameraError(f"url {url!r} must be an address such as rtsp://host/path, http://host/feed.mjpg "
                              "or udp://@:5000 (a video file is --source video -p path=FILE)")
        return CameraTarget("url", url, cv2.CAP_FFMPEG, _without_password(url))
    if not isinstance(gstreamer, str) or "appsink" not in gstreamer:
        raise CameraError(f"gstreamer {gstreamer!r} must be a pipeline ending in appsink, e.g. "
                          "'v4l2src device=/dev/video0 ! videoconvert ! appsink'")
    if not gstreamer_available():
        raise CameraError("this OpenCV build has no GStreamer (cv2.getBuildInformation() says GStreamer: NO): "
                          "use -p url=... for RTSP/HTTP/UDP streams or -p device=N, or install an OpenCV "
                          "built with GStreamer")
    return CameraTarget("gstreamer", gstreamer, cv2.CAP_GSTREAMER, "gstreamer pipeline")


def _without_password(url: str) -> str:
    """``url`` as logs and reports may show it: a password in it is masked."""
    return re.sub(r"(://[^/:@]*:)[^/@]*@", r"\1***@", url)


@dataclass
class CapturedFrame:
    """A frame as the camera gave it (BGR, BGRA or gray uint8), stamped when it was read."""

    image: np.ndarray
    stamp: float


def frame_encoding(img: np.ndarray) -> str | None:
    """The message encoding of a frame OpenCV gave (bgr8, mono8), None when it is none of them."""
    if img.dtype != np.uint8:
        return None
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        return "mono8"
    if img.ndim == 3 and img.shape[2] in (3, 4):
        return "bgr8" if img.shape[2] == 3 else "bgra8"
    return None


def frame_problem(img: np.ndarray, first: np.ndarray | None) -> str | None:
    """Why ``img`` cannot go on as a frame of the stream whose first frame (since it was opened)
    was ``first``, or None when it can. The first frame sets the stream's size, channels and
    dtype; a later frame that differs in any of them is of another size or encoding."""
    if first is None:
        if frame_encoding(img) is None:
            return f"frame of an unsupported encoding ({shape_text(img)}; 8-bit gray, BGR or BGRA expected)"
        return None
    if img.shape != first.shape or img.dtype != first.dtype:
        return (f"frame of another size or encoding ({shape_text(img)}; the stream's is {shape_text(first)}, "
                "set by its first frame)")
    return None


def shape_text(img: np.ndarray) -> str:
    """``WxH``, with the channels and dtype when they are not plain 8-bit colour."""
    h, w = img.shape[:2]
    extra = "" if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 else (
        f" {'x'.join(str(s) for s in img.shape[2:]) or '1'}-channel {img.dtype}")
    return f"{w}x{h}{extra}"


class LiveCapture:
    """A camera opened now (a CameraError when it cannot be) and read by a thread until
    :meth:`close` (module docstring). ``take`` gives the newest frame; ``figures`` what happened.

    ``width``, ``height``, ``rate_hz``, ``fourcc`` are requested from a device (the driver may
    grant others: ``figures()["opened"]`` says what it gave). ``stall_timeout_s``: a stream
    without a frame for that long is reopened; ``open_timeout_s`` bounds each opening of a stream.
    """

    def __init__(self, target: CameraTarget, width: int | None = None, height: int | None = None,
                 rate_hz: float | None = None, fourcc: str | None = None, stall_timeout_s: float = 3.0,
                 open_timeout_s: float = 10.0) -> None:
        if target.kind != "device" and any(v is not None for v in (width, height, rate_hz, fourcc)):
            raise CameraError("width, height, rate_hz and fourcc are requested from a device; a stream's "
                              "size and rate are its sender's (max_side bounds the size)")
        for name, value in (("width", width), ("height", height), ("rate_hz", rate_hz)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0
                                      or (name != "rate_hz" and int(value) != value)):
                raise CameraError(f"{name} {value!r} must be a positive {'number' if name == 'rate_hz' else 'integer'}")
        if fourcc is not None and (not isinstance(fourcc, str) or len(fourcc) != 4):
            raise CameraError(f"fourcc {fourcc!r} must be four characters, e.g. MJPG or YUYV")
        if stall_timeout_s <= 0 or open_timeout_s <= 0:
            raise CameraError("stall_timeout_s and open_timeout_s must be positive")
        self.target = target
        self.request = {"width": width, "height": height, "rate_hz": rate_hz, "fourcc": fourcc}
        self.stall_timeout_s = float(stall_timeout_s)
        self.open_timeout_s = float(open_timeout_s)
        # OpenCV's V4L2 backend waits this many seconds for a frame (10 by default), read at its first use
        os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", str(max(1, math.ceil(stall_timeout_s))))
        # each reopening attempt of a lost stream would print FFmpeg's and OpenCV's own lines: the
        # outage is logged here once, with its cause and length (set OPENCV_FFMPEG_LOGLEVEL to see them)
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        # stamps: the wall clock at start, advanced by the monotonic clock (a clock step moves no stamp)
        self._wall0, self._mono0 = time.time(), time.monotonic()
        self._cond = threading.Condition()
        self._closed = threading.Event()
        self._slot: CapturedFrame | None = None
        self._taking = False  # frames replaced before the reader's first take are no drops
        self.captured = self.taken = self.dropped = self.discarded_at_start = 0
        self.skipped: dict[str, int] = {}
        self.outages: list[dict[str, Any]] = []
        self.outage_count = 0
        self.outage_s = 0.0
        self.outage_frames = 0
        self._outage: dict[str, Any] | None = None  # the one in progress
        self._period: float | None = None  # the stream's frame interval (over its recent frames)
        self._recent: deque[float] = deque(maxlen=RATE_WINDOW)
        self._last_mono: float | None = None
        self._backoff = BACKOFF_FIRST_S
        self.opened: dict[str, Any] = {}
        self._stream_size: str | None = None
        cap = self._open()
        if cap is None:
            raise CameraError(self._cannot_open())
        self._thread = threading.Thread(target=self._run, args=(cap,), name="camera-capture", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ opening
    def _cannot_open(self) -> str:
        t = self.target
        if t.kind == "device":
            return (f"cannot open camera {t.label} (video devices here: {_video_devices()}; is it in use by "
                    f"another program, and may this user read it?)")
        if t.kind == "url":
            return (f"cannot open {t.label} within {self.open_timeout_s:g} s through OpenCV's FFmpeg backend "
                    "(is the stream served there, and is the address, port and path right?)")
        return "cannot open the gstreamer pipeline (check it with gst-launch-1.0 and a fakesink)"

    def _open(self) -> Any | None:
        """One attempt to open the camera, with the device's requests applied; None when it fails."""
        t = self.target
        ms = int(self.open_timeout_s * 1000)
        params = ([cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                   int(self.stall_timeout_s * 1000)] if t.kind != "device" else [])
        try:
            cap = cv2.VideoCapture(t.address, t.api, params)
        except cv2.error as exc:  # a backend that refuses the address outright
            log.debug("opening %s failed: %s", t.label, exc)
            return None
        if not cap.isOpened():
            cap.release()
            return None
        req = self.request
        if req["fourcc"]:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*req["fourcc"]))
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, req["width"]), (cv2.CAP_PROP_FRAME_HEIGHT, req["height"]),
                            (cv2.CAP_PROP_FPS, req["rate_hz"])):
            if value is not None:
                cap.set(prop, float(value))
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.opened = {"backend": cap.getBackendName(), "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                       "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                       "fps": round(fps, 3) if fps and math.isfinite(fps) and 0 < fps < 1000 else None}
        return cap

    # ------------------------------------------------------------------ the capture thread
    def _stamp(self) -> float:
        return self._wall0 + (time.monotonic() - self._mono0)

    def _run(self, cap: Any) -> None:
        try:
            while not self._closed.is_set():
                if cap is None:
                    cap = self._reopen()
                    if cap is None:
                        return
                self._read(cap)
                cap.release()
                cap = None
        except Exception as exc:  # never a silent death: what stopped the camera is said and kept
            log.exception("camera %s: capture stopped", self.target.label)
            self._count_skip(f"capture stopped: {type(exc).__name__}: {exc}")
            self._closed.set()
        finally:
            if cap is not None:
                cap.release()
            with self._cond:
                self._cond.notify_all()

    def _reopen(self) -> Any | None:
        """Reopen after the backoff, doubling it after each failure; None once closed."""
        while not self._closed.wait(self._backoff):
            if self._outage is not None:
                self._outage["attempts"] += 1
            cap = self._open()
            if cap is not None:
                return cap
            self._backoff = min(self._backoff * 2, BACKOFF_MAX_S)
        return None

    def _read(self, cap: Any) -> None:
        """Read one opening of the stream until it is lost (or the capture is closed)."""
        failures = 0
        last_good = time.monotonic()
        ref: np.ndarray | None = None  # the first frame of this opening: it sets the stream's size
        while not self._closed.is_set():
            ok = cap.grab()
            stamp, now = self._stamp(), time.monotonic()
            img = cap.retrieve()[1] if ok else None
            if img is None:
                failures += 1
                stalled = now - last_good >= self.stall_timeout_s
                if failures >= FAILED_READS_LOST or stalled:
                    self._lost(f"no frame for {self.stall_timeout_s:g} s (stalled)" if stalled
                               else "reads failed (the stream ended, dropped or was unplugged)", last_good)
                    return
                continue
            if failures:  # the stream went on: those reads were unreadable frames
                self._count_skip("unreadable frame (the backend's read failed, the stream went on)", failures)
                failures = 0
            last_good = now
            self._backoff = BACKOFF_FIRST_S
            problem = frame_problem(img, ref)
            if problem is not None:
                self._count_skip(problem)
                continue
            if ref is None:
                ref = img
                self._opened_stream(img)
            self._end_outage(stamp)
            self._note_interval(now)
            self._store(CapturedFrame(img, stamp))

    def _opened_stream(self, img: np.ndarray) -> None:
        """The first frame of an opening sets the stream's size; a camera that comes back at
        another size is taken as it is (the run's front end resizes every frame), and said."""
        size = shape_text(img)
        if self._stream_size is not None and self._stream_size != size:
            log.warning("camera %s: reopened at %s (was %s)", self.target.label, size, self._stream_size)
        self._stream_size = size
        self.opened = {**self.opened, "frames": size}

    def _note_interval(self, now: float) -> None:
        """The stream's frame interval over its recent frames (a window, so that a burst of
        buffered frames after an opening does not make it look faster than it is)."""
        recent = self._recent
        recent.append(now)
        if len(recent) >= 3 and recent[-1] > recent[0]:
            self._period = (recent[-1] - recent[0]) / (len(recent) - 1)
        self._last_mono = now

    def _store(self, item: CapturedFrame) -> None:
        with self._cond:
            if self._slot is not None:
                if self._taking:
                    self.dropped += 1
                else:
                    self.discarded_at_start += 1
            self._slot = item
            self.captured += 1
            self._cond.notify_all()

    def _count_skip(self, cause: str, n: int = 1) -> None:
        with self._cond:
            if cause not in self.skipped:
                log.warning("camera %s: %s: skipped", self.target.label, cause)
            self.skipped[cause] = self.skipped.get(cause, 0) + n

    def _lost(self, cause: str, last_good: float) -> None:
        """The stream is gone: an outage starts at its last good frame (monotonic ``last_good``;
        the opening's time when it gave none)."""
        self._last_mono = None
        self._recent.clear()
        if self._outage is not None:  # reopened, but lost again before a frame: the same outage
            return
        last = self._wall0 + (last_good - self._mono0)
        with self._cond:
            self._outage = {"start": last, "cause": cause, "attempts": 0}
            self.outage_count += 1
        if self.outage_count <= LOGGED_OUTAGES:
            log.warning("camera %s: %s; reopening (every %g s at first, up to every %g s)", self.target.label,
                        cause, BACKOFF_FIRST_S, BACKOFF_MAX_S)
        if self.outage_count == LOGGED_OUTAGES:
            log.warning("camera %s: further outages are counted in the report only", self.target.label)

    def _missed(self, length: float) -> int:
        """Frames the camera would have sent in ``length`` seconds at its own rate (beyond the one
        interval a frame takes anyway)."""
        if not self._period:
            return 0
        return max(0, round(length / self._period) - 1)

    def _end_outage(self, stamp: float) -> None:
        o = self._outage
        if o is None:
            return
        length = max(0.0, stamp - o["start"])
        done = {"start": round(o["start"], 3), "length_s": round(length, 3), "cause": o["cause"],
                "attempts": o["attempts"], "frames_missed": self._missed(length)}
        with self._cond:
            self._outage = None
            self.outage_s += length
            self.outage_frames += done["frames_missed"]
            self.outages = [*self.outages, done][-KEPT_OUTAGES:]
        if self.outage_count <= LOGGED_OUTAGES:
            log.warning("camera %s: back after %.1f s (%d reopening attempts)", self.target.label, length,
                        o["attempts"])

    # ------------------------------------------------------------------ the reader's side
    def take(self, timeout: float) -> CapturedFrame | None:
        """The newest frame not taken yet, waiting up to ``timeout`` s; None when there is none
        (or the capture is closed)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            self._taking = True
            while self._slot is None and not self._closed.is_set():
                left = deadline - time.monotonic()
                if left <= 0 or not self._cond.wait(left):
                    break
            item, self._slot = self._slot, None
            if item is not None:
                self.taken += 1
            return item

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def seconds_without_frame(self) -> float:
        """Since the last frame read (or the last loss of the stream)."""
        outage, last = self._outage, self._last_mono  # the capture thread replaces them
        if outage is not None:
            return max(0.0, self._stamp() - outage["start"])
        return 0.0 if last is None else time.monotonic() - last

    def close(self) -> None:
        """Stop reading (a reader waiting in ``take`` returns) and release the camera."""
        self._closed.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(self.open_timeout_s + self.stall_timeout_s + 1.0)

    def figures(self) -> dict[str, Any]:
        """What the camera did: frames captured, taken, dropped (replaced before they were
        taken), skipped per cause, its rate, and its outages (the one in progress counted too)."""
        with self._cond:
            ongoing = self._outage
            length = max(0.0, self._stamp() - ongoing["start"]) if ongoing else 0.0
            out = {"target": self.target.label, "kind": self.target.kind, "opened": dict(self.opened),
                   "state": "reopening" if ongoing else ("closed" if self.closed else "streaming"),
                   "captured": self.captured, "taken": self.taken, "dropped": self.dropped,
                   "discarded_at_start": self.discarded_at_start,
                   "rate_hz": round(1.0 / self._period, 3) if self._period else None,
                   "skipped": dict(self.skipped), "outage_count": self.outage_count,
                   "outage_s": round(self.outage_s + length, 3),
                   "outage_frames_missed": self.outage_frames + self._missed(length),
                   "outages": list(self.outages)}
            if ongoing:
                out["outage_now_s"] = round(length, 3)
            return out


def loss_causes(figures: dict[str, Any], baseline: dict[str, Any] | None = None, where: str = "camera") -> dict[str, int]:
    """Frames the camera made or would have made that never left it, per cause, from
    :meth:`LiveCapture.figures` (less a ``baseline`` taken earlier): its outages (estimated at its
    own rate, with their count and length in the cause) and its skipped frames. Drops in its slot
    are not here: a source reports them as ``dropped``."""
    base = baseline or {}
    out: dict[str, int] = {}
    n = int(figures.get("outage_count", 0)) - int(base.get("outage_count", 0))
    if n > 0:
        secs = float(figures.get("outage_s", 0.0)) - float(base.get("outage_s", 0.0))
        frames = int(figures.get("outage_frames_missed", 0)) - int(base.get("outage_frames_missed", 0))
        out[f"{where} outages: {n}, {secs:.1f} s without frames, reopened "
            f"(frames estimated at the stream's rate)"] = max(0, frames)
    before = base.get("skipped") or {}
    for cause, k in (figures.get("skipped") or {}).items():
        if int(k) - int(before.get(cause, 0)) > 0:
            out[f"{where}: {cause}"] = int(k) - int(before.get(cause, 0))
    return out
