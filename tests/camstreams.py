"""Real camera streams on loopback for the camera tests: an HTTP MJPEG server (bench/mjpeg_server.py's,
shared with bench/camera_soak.py: a thread writing multipart/x-mixed-replace JPEGs, as IP cameras
and ESP32 boards do), an RTSP server that an OpenCV client pulls from (RTP over the RTSP
connection, MPEG-TS payload encoded by ffmpeg, as an IP camera serves it), and ffmpeg sending
MPEG-TS over UDP. No mock: OpenCV's FFmpeg backend reads each of them as it would a camera's."""

from __future__ import annotations

import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from mjpeg_server import MjpegServer as _MjpegServer  # noqa: E402
from mjpeg_server import jpeg  # noqa: E402

__all__ = ["FFMPEG", "NO_FFMPEG", "MjpegServer", "RtspServer", "ffmpeg_testsrc", "free_udp_port", "gray_frame",
           "jpeg"]

FFMPEG = shutil.which("ffmpeg")
NO_FFMPEG = "ffmpeg is not installed (apt-get install -y ffmpeg): no UDP or RTSP stream to read"


def gray_frame(i: int, width: int = 160, height: int = 120) -> np.ndarray:
    """Frame ``i`` of a test stream: a flat grey level that changes with i, and a white square."""
    img = np.full((height, width, 3), (40 + 7 * i) % 200, np.uint8)
    img[10:30, 10:30] = 255
    return img


class MjpegServer(_MjpegServer):
    """bench/mjpeg_server.py's MJPEG stream on http://127.0.0.1:PORT/feed.mjpg (``stop()``: the
    camera is gone, ``start()``: back on the same port); ``frame(i)`` gives the JPEG bytes of frame
    i (a test can send another size, or a broken one), :func:`gray_frame`'s by default."""

    def __init__(self, rate: float = 20.0, frame: Callable[[int], bytes] | None = None) -> None:
        super().__init__(rate, frame or (lambda i: jpeg(gray_frame(i))))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ffmpeg_testsrc(out: list[str], size: str = "160x120") -> subprocess.Popen:
    """ffmpeg encoding its test pattern (MPEG-1 in MPEG-TS, 25 fps, real time) to ``out``."""
    assert FFMPEG
    return subprocess.Popen([FFMPEG, "-nostdin", "-loglevel", "error", "-re", "-f", "lavfi", "-i",
                             f"testsrc=size={size}:rate=25", "-c:v", "mpeg1video", "-g", "5", "-f", "mpegts", *out],
                            stdout=subprocess.PIPE if out == ["pipe:1"] else subprocess.DEVNULL)


class RtspServer:
    """rtsp://127.0.0.1:PORT/live served to one client at a time: OPTIONS, DESCRIBE (an SDP of one
    MPEG-TS track), SETUP (RTP interleaved on the RTSP connection), PLAY, then RTP packets
    holding ffmpeg's MPEG-TS output. Enough of RFC 2326 for FFmpeg's RTSP client."""

    def __init__(self) -> None:
        self._sock = socket.socket()
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(2)
        self._sock.settimeout(0.5)
        self.port = self._sock.getsockname()[1]
        self._stop = threading.Event()
        self._procs: list[subprocess.Popen] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"rtsp://127.0.0.1:{self.port}/live"

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                continue
            threading.Thread(target=self._session, args=(conn,), daemon=True).start()

    def _session(self, conn: socket.socket) -> None:
        with conn:
            reader = conn.makefile("rb")
            if not self._handshake(conn, reader):
                return
            proc = ffmpeg_testsrc(["pipe:1"])
            self._procs.append(proc)
            seq = 0
            try:
                while not self._stop.is_set():
                    chunk = proc.stdout.read(188 * 7)  # seven MPEG-TS packets per RTP packet
                    if not chunk:
                        return
                    rtp = struct.pack("!BBHII", 0x80, 33, seq & 0xFFFF, int(time.monotonic() * 90000) & 0xFFFFFFFF,
                                      0x5EED) + chunk
                    conn.sendall(b"$\x00" + struct.pack("!H", len(rtp)) + rtp)
                    seq += 1
            except OSError:
                return
            finally:
                proc.kill()
                proc.wait()

    def _handshake(self, conn: socket.socket, reader) -> bool:
        """Answer requests up to PLAY; False when the client went away first."""
        while True:
            line = reader.readline().decode(errors="replace")
            if not line:
                return False
            method, url = (line.split(" ") + ["", ""])[:2]
            headers = {}
            while (h := reader.readline().decode(errors="replace").strip()):
                k, _, v = h.partition(":")
                headers[k.strip().lower()] = v.strip()
            extra, body, status = "", b"", "200 OK"
            if method == "DESCRIBE":
                body = (b"v=0\r\no=- 0 0 IN IP4 127.0.0.1\r\ns=test\r\nc=IN IP4 0.0.0.0\r\nt=0 0\r\n"
                        b"m=video 0 RTP/AVP 33\r\na=rtpmap:33 MP2T/90000\r\na=control:track0\r\n")
                extra = f"Content-Base: {url}/\r\nContent-Type: application/sdp\r\n"
            elif method == "SETUP":
                if "TCP" not in headers.get("transport", ""):
                    status = "461 Unsupported Transport"
                else:
                    extra = "Transport: RTP/AVP/TCP;unicast;interleaved=0-1\r\nSession: 4711\r\n"
            elif method in ("PLAY", "OPTIONS"):
                extra = "Session: 4711\r\n" if method == "PLAY" else "Public: OPTIONS, DESCRIBE, SETUP, PLAY\r\n"
            conn.sendall(f"RTSP/1.0 {status}\r\nCSeq: {headers.get('cseq', '0')}\r\n{extra}"
                         f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
            if method == "PLAY":
                return True

    def stop(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(5)
        for p in self._procs:
            if p.poll() is None:
                p.kill()
                p.wait()
