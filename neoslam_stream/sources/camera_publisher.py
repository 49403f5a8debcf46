"""``neoslam camera``: a camera's frames published on zenoh, for a run's ``zenoh`` source on
another host.

A small robot computer then runs only the camera, and a base station the stages. The frames are
the messages the ``zenoh`` source reads (``runtime.messages`` ``image``: a raw ``bgr8``/``mono8``
array, or JPEG bytes with ``jpeg_quality``), numbered consecutively from 0 and stamped with their
capture time, so the source can count the frames the link lost. Once a second (and at the end) a
``stats`` message on ``<key>/stats`` carries the capture's figures (frames captured, published,
dropped, skipped, outages): the source puts them in the run's report and monitor table, which the
publisher's own counts could not reach otherwise. Puts drop rather than block when the link is
congested: a live camera must not fall behind.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import cv2
import numpy as np
import zenoh

from ..runtime.bus import open_session
from ..runtime.messages import Message, MessageError, encode
from ..runtime.pixels import fit
from .capture import LiveCapture, frame_encoding
from .imaging import DEFAULT_MAX_SIDE

log = logging.getLogger("neoslam.sources.camera")


def stats_key(key: str) -> str:
    """Where the figures of the camera publishing on ``key`` go (the zenoh source listens there)."""
    return f"{key}/stats"


def frame_data(img: np.ndarray, jpeg_quality: int | None) -> dict[str, Any]:
    """An ``image`` message's data for a camera frame: the array as it is (bgr8, bgra8, mono8) or,
    with ``jpeg_quality``, its JPEG bytes (alpha dropped)."""
    encoding = frame_encoding(img) or "bgr8"
    if jpeg_quality is None:
        return {"image": np.ascontiguousarray(img), "encoding": encoding}
    if encoding == "bgra8":
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise MessageError(f"JPEG encoding of a {img.shape} frame failed")
    return {"compressed": buf.tobytes(), "format": "jpeg"}


class CameraPublisher:
    """Takes the newest frame of ``capture`` and puts it on ``key`` until stopped (module
    docstring). ``max_side`` bounds a frame's long side before it is sent."""

    def __init__(self, capture: LiveCapture, key: str, listen: list[str] | None = None,
                 connect: list[str] | None = None, jpeg_quality: int | None = None,
                 max_side: int | None = DEFAULT_MAX_SIDE, stats_every_s: float = 1.0) -> None:
        if jpeg_quality is not None and not 1 <= int(jpeg_quality) <= 100:
            raise ValueError(f"JPEG quality {jpeg_quality} must be 1 to 100")
        self.capture = capture
        self.key = key
        self.jpeg_quality = jpeg_quality
        self.max_side = max_side
        self.stats_every_s = stats_every_s
        self.published = 0
        self.errors: dict[str, int] = {}
        self.first_put: float | None = None
        self.session = open_session(listen=listen or [], connect=connect or [])
        self._images = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self._stats = self.session.declare_publisher(stats_key(key))

    def figures(self) -> dict[str, Any]:
        """The capture's figures and the publisher's (frames published, its own errors)."""
        elapsed = time.monotonic() - self.first_put if self.first_put is not None else 0.0
        return {"stage": "camera", **self.capture.figures(), "key": self.key, "published": self.published,
                "publish_rate_hz": round(self.published / elapsed, 3) if elapsed > 0 else None,
                "format": "jpeg" if self.jpeg_quality is not None else "raw",
                "publish_errors": dict(self.errors)}

    def _put_stats(self, final: bool = False) -> None:
        data = {**self.figures(), "final": final}
        self._stats.put(encode(Message("stats", self.published, time.time(), data)))

    def _error(self, cause: str) -> None:
        if cause not in self.errors:
            log.warning("camera: frame not published: %s", cause)
        self.errors[cause] = self.errors.get(cause, 0) + 1

    def run(self, stop: threading.Event, duration: float | None = None) -> dict[str, Any]:
        """Publish until ``stop`` is set, ``duration`` seconds have passed or the capture ends;
        then send the final figures, close, and return them."""
        start = time.monotonic()
        next_stats = start
        try:
            while not stop.is_set() and not self.capture.closed:
                now = time.monotonic()
                if duration is not None and now - start >= duration:
                    break
                if now >= next_stats:
                    self._put_stats()
                    next_stats = now + self.stats_every_s
                item = self.capture.take(0.25)
                if item is None:
                    continue
                try:
                    data = frame_data(fit(item.image, self.max_side), self.jpeg_quality)
                    payload = encode(Message("image", self.published, item.stamp, data))
                except (MessageError, cv2.error) as exc:  # a frame beyond the message size limit...
                    self._error(f"{type(exc).__name__}: {exc}")
                    continue
                self._images.put(payload)
                self.first_put = time.monotonic() if self.first_put is None else self.first_put
                self.published += 1
        finally:
            figures = self.figures()
            try:
                self._put_stats(final=True)
                time.sleep(0.2)  # a sample still in the session's queue is lost when it closes
            finally:
                self.capture.close()
                self.session.close()
        return figures
