"""An HTTP MJPEG stream on loopback, as IP cameras and ESP32 boards serve one: a thread writing
``multipart/x-mixed-replace`` JPEGs to each client. Used by ``bench/camera_soak.py`` (the
synthetic route served as a camera) and by the camera tests (``tests/camstreams.py``); OpenCV's
FFmpeg backend reads it as it reads a camera's stream, no mock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np


def jpeg(img: np.ndarray, quality: int = 95) -> bytes:
    """``img`` (BGR or gray uint8) as JPEG bytes."""
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])[1].tobytes()


class MjpegServer:
    """An MJPEG stream on http://127.0.0.1:PORT/feed.mjpg at ``rate`` frames per second.

    ``frame(i)`` gives the JPEG bytes (or any bytes: a test may send a broken frame) of frame i,
    where i counts the frames served so far (``sent``, over every client and opening). A client's
    frames go out on its own clock, frame k at ``k / rate`` after it connected; a client that falls
    more than a frame behind (its socket full) skips ahead, as a camera does, rather than getting a
    burst. ``connections`` counts the clients served (a camera that reopens the stream is one more).
    ``stop()`` closes the listening socket and every open stream (the camera is gone); ``start()``
    serves again on the same port (the camera is back). ``keep_times``: note when each frame was
    written (``sent_times``, time.time())."""

    def __init__(self, rate: float = 20.0, frame: Callable[[int], bytes] | None = None,
                 keep_times: bool = False) -> None:
        if frame is None:
            blank = jpeg(np.zeros((120, 160, 3), np.uint8))
            frame = lambda i: blank  # noqa: E731
        self.rate = rate
        self.frame = frame
        self.port = 0
        self.sent = 0
        self.connections = 0
        #: time.time() when the first frame was written (None before)
        self.first_sent_at: float | None = None
        self.sent_times: list[float] | None = [] if keep_times else None
        self._lock = threading.Lock()
        self._server: ThreadingHTTPServer | None = None
        self._stopped = threading.Event()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/feed.mjpg"

    def _serve_client(self, wfile, stopped: threading.Event) -> None:
        period = 1.0 / self.rate
        due = time.monotonic()
        with self._lock:
            self.connections += 1
        while not stopped.is_set():
            with self._lock:
                data = self.frame(self.sent)
            try:
                wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(data)
                            + data + b"\r\n")
            except OSError:
                return
            now = time.time()
            with self._lock:
                self.sent += 1
                if self.first_sent_at is None:
                    self.first_sent_at = now
                if self.sent_times is not None:
                    self.sent_times.append(now)
            due += period
            now = time.monotonic()
            if due < now - period:  # a frame or more behind: the next one is now, no burst
                due = now
            stopped.wait(max(0.0, due - now))

    def start(self) -> MjpegServer:
        owner = self
        self._stopped = stopped = threading.Event()

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                owner._serve_client(self.wfile, stopped)

            def log_message(self, *args) -> None:
                pass

        ThreadingHTTPServer.allow_reuse_address = True
        self._server = ThreadingHTTPServer(("127.0.0.1", self.port), Handler)
        self._server.daemon_threads = True
        self.port = self._server.server_address[1]
        threading.Thread(target=self._server.serve_forever, name="mjpeg-server", daemon=True).start()
        return self

    def stop(self) -> None:
        self._stopped.set()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None
