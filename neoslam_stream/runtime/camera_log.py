"""camera.zip: what the camera saw, thinned, in the run folder (the source process keeps it).

The source holds every frame it publishes as pixels already, so it keeps one JPEG copy every
``period_s`` of source time (0.5 s), at most ``max_side`` pixels on its longer side, and at most
``max_frames`` of them: beyond that every second one is dropped and the period doubles, so a long
run's file stays the size of a short one's (a few MB). It is written at the end with the TUM files,
as a plain (stored, uncompressed) zip: ``NNNNNNNN.jpg`` per kept frame (the frame number) and
``frames.csv`` (``frame,stamp,name``). ``neoslam view`` shows it, any unzip opens it.
"""

from __future__ import annotations

import io
import logging
import zipfile
from pathlib import Path

import numpy as np

from .pixels import decode_bounded, fit

log = logging.getLogger("neoslam.source")

#: the run folder's thinned camera frames
CAMERA_FILE = "camera.zip"


def _bgr(image: np.ndarray | None, encoding: str, compressed: bytes | None,
         max_side: int) -> np.ndarray | None:
    """The frame as BGR pixels for OpenCV, or None when it cannot be read cheaply and safely
    (compressed bytes are decoded as the sources decode them, already bounded to ``max_side``)."""
    import cv2

    if image is not None:
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim not in (2, 3):
            return None
        if img.ndim == 2 or img.shape[2] == 1:
            return cv2.cvtColor(img.reshape(img.shape[0], img.shape[1]), cv2.COLOR_GRAY2BGR)
        enc = encoding.lower()
        if img.shape[2] == 4:
            img = img[:, :, :3]
        return img if enc.startswith("bgr") else img[:, :, ::-1]
    return decode_bounded(compressed, max_side) if compressed else None


def encode_jpeg(bgr: np.ndarray, max_side: int, quality: int) -> bytes | None:
    """BGR pixels as a JPEG of at most ``max_side`` pixels a side (shrunk by area averaging), or
    None when OpenCV cannot encode them."""
    import cv2

    bgr = np.ascontiguousarray(fit(np.ascontiguousarray(bgr), max_side))
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return jpeg.tobytes() if ok else None


class CameraLog:
    """The thinned JPEG frames of a run (module docstring); :meth:`add` per published frame."""

    def __init__(self, period_s: float = 0.5, max_frames: int = 600, max_side: int = 480,
                 quality: int = 75) -> None:
        self.period_s = float(period_s)
        self.max_frames = max(2, int(max_frames))
        self.max_side = int(max_side)
        self.quality = int(quality)
        self.frames: list[tuple[int, float, bytes]] = []
        self.last_stamp: float | None = None
        self.unreadable = 0

    def add(self, frame: int, stamp: float, image: np.ndarray | None = None, encoding: str = "rgb8",
            compressed: bytes | None = None) -> None:
        if self.period_s <= 0 or (self.last_stamp is not None and stamp - self.last_stamp < self.period_s):
            return
        bgr = _bgr(image, encoding, compressed, self.max_side)
        if bgr is None:
            self.unreadable += 1
            return
        self.last_stamp = stamp
        jpeg = encode_jpeg(bgr, self.max_side, self.quality)
        if jpeg is None:
            self.unreadable += 1
            return
        self.frames.append((int(frame), float(stamp), jpeg))
        if len(self.frames) > self.max_frames:  # thinned evenly: every second frame, twice the period
            self.frames = self.frames[::2]
            self.period_s *= 2

    def write(self, run_dir: str | Path) -> Path | None:
        """camera.zip in ``run_dir`` (nothing when no frame was kept); None when not written."""
        if not self.frames:
            return None
        path = Path(run_dir) / CAMERA_FILE
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as z:
            rows = ["frame,stamp,name\n"]
            for frame, stamp, jpeg in self.frames:
                name = f"{frame:08d}.jpg"
                z.writestr(name, jpeg)
                rows.append(f"{frame},{stamp:.6f},{name}\n")
            z.writestr("frames.csv", "".join(rows))
        try:
            tmp = path.with_suffix(".zip.tmp")
            tmp.write_bytes(buf.getvalue())
            tmp.replace(path)
        except OSError as exc:
            log.error("source: %s not written: %s", path, exc)
            return None
        return path


def read_camera_zip(path: str | Path, max_bytes: int = 4 << 20) -> list[tuple[int, float, bytes]]:
    """(frame, stamp, JPEG bytes) of every frame a camera.zip holds, in frame order; an entry
    larger than ``max_bytes`` or a malformed row is skipped."""
    out = []
    with zipfile.ZipFile(path) as z:
        names = set(z.namelist())
        for line in z.read("frames.csv").decode(errors="replace").splitlines()[1:]:
            parts = line.split(",")
            if len(parts) != 3 or parts[2] not in names or z.getinfo(parts[2]).file_size > max_bytes:
                continue
            try:
                out.append((int(parts[0]), float(parts[1]), z.read(parts[2])))
            except ValueError:
                continue
    return sorted(out, key=lambda r: r[0])
