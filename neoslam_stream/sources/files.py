"""Sources reading files: an image folder (+ TUM odometry / ground truth) and a video file."""

from __future__ import annotations

import errno
import logging
import math
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..runtime.messages import MAX_MESSAGE_BYTES
from ..runtime.pixels import decode_bounded, fit
from ..tum import read_tum_rows
from .bag import interpolate_pose
from .base import Source, SourceFrame
from .imaging import DEFAULT_MAX_SIDE
from .params import ExistingDir, ExistingPath, PositiveFloat, PositiveInt

log = logging.getLogger("neoslam.sources.files")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm")
#: an image file larger than a message may be is refused before it is read
MAX_FILE_BYTES = MAX_MESSAGE_BYTES


def odometry_between(odo: np.ndarray, t0: float, t1: float) -> tuple[float, float, float]:
    """(vtrans, vrot, dt) moving from the odometry pose at t0 to the one at t1 (nearest samples)."""
    if t1 <= t0 or len(odo) == 0:
        return 0.0, 0.0, max(0.0, t1 - t0)
    i0 = int(np.clip(np.searchsorted(odo[:, 0], t0), 0, len(odo) - 1))
    i1 = int(np.clip(np.searchsorted(odo[:, 0], t1), 0, len(odo) - 1))
    dist = math.hypot(odo[i1, 1] - odo[i0, 1], odo[i1, 2] - odo[i0, 2])
    heading = math.atan2(odo[i1, 2] - odo[i0, 2], odo[i1, 1] - odo[i0, 1])
    if dist > 1e-12 and abs(math.remainder(heading - odo[i0, 3], 2 * math.pi)) > math.pi / 2:
        dist = -dist  # moving backwards
    dth = math.remainder(odo[i1, 3] - odo[i0, 3], 2 * math.pi)
    dt = t1 - t0
    return dist / dt, dth / dt, dt


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def read_image_file(path: Path, max_bytes: int = MAX_FILE_BYTES) -> bytes | str:
    """The bytes of a regular file, or why it cannot be used as an image (a string).

    Never opens anything but a regular file: a FIFO would block the reader until a writer
    comes, a device could stream forever. The check is made on the path (``stat`` follows
    symbolic links: a loop or a dangling link fails there) and again on the opened descriptor,
    which is opened non-blocking, so a file swapped for a FIFO in between cannot block either.
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        if os.path.islink(path) and exc.errno == errno.ENOENT:
            return f"dangling symbolic link (to {os.readlink(path)!r})"
        return exc.strerror or type(exc).__name__
    if not stat.S_ISREG(st.st_mode):
        return f"{_file_kind(st.st_mode)}, not an image file"
    if st.st_size > max_bytes:
        return f"{st.st_size} bytes, more than the {max_bytes} an image message may hold"
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # replaced after the first check
            return f"{_file_kind(st.st_mode)}, not an image file"
        chunks = []
        left = min(st.st_size, max_bytes) + 1  # a file growing meanwhile is read up to the limit
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
        data = b"".join(chunks)
        if len(data) > max_bytes:
            return f"more than the {max_bytes} bytes an image message may hold"
        return data
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    finally:
        os.close(fd)


class ImageFolderSource(Source):
    """Images of a folder in name order (``images/`` inside it if present), with optional
    ``odometry.tum`` and ``groundtruth.tum`` (or the files named by ``odometry`` / ``groundtruth``).

    ``odometry.tum`` holds one odometry pose per image (row i belongs to image i): it gives the
    frame stamps (else ``frame / rate_hz``) and each frame's (vtrans, vrot, dt) as the motion
    between consecutive poses. Ground truth is interpolated at each frame's stamp (any rate).
    Without an odometry file the frames carry no odometry (``gives_odometry`` says so before the
    run starts): the run then measures visual odometry from the images, as for every source
    without odometry.

    Files that are no image files (a directory, a FIFO, a symbolic-link loop or a dangling link,
    an unreadable file) are counted as source errors with their path and reason and skipped;
    the frames stay numbered without gaps, and a skipped file's motion goes to the next frame.
    Images whose long side exceeds ``max_side`` pixels are resized (a JPEG decoded at a reduced
    scale), see :mod:`.imaging`.
    """

    def __init__(self, path: ExistingDir, rate_hz: PositiveFloat = 10.0, odometry: ExistingPath | None = None,
                 groundtruth: ExistingPath | None = None, max_frames: PositiveInt | None = None,
                 groundtruth_max_gap_s: PositiveFloat = 5.0, max_side: PositiveInt | None = DEFAULT_MAX_SIDE) -> None:
        root = Path(path)
        if not root.is_dir():
            raise FileNotFoundError(f"image folder {root} does not exist")
        img_dir = root / "images" if (root / "images").is_dir() else root
        self.files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise FileNotFoundError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {img_dir}")
        if max_frames:
            self.files = self.files[:max_frames]
        self.rate_hz = rate_hz
        self.max_side = max_side
        self.length = len(self.files)
        odo_path = Path(odometry) if odometry else root / "odometry.tum"
        gt_path = Path(groundtruth) if groundtruth else root / "groundtruth.tum"
        self.odo: np.ndarray | None = None
        self.gt: np.ndarray | None = None
        if odo_path.exists():
            # one row per data line, bad rows NaN (row i belongs to image i): counted here, with
            # their line numbers, and their frames carry no motion
            self.odo, errors = read_tum_rows(odo_path)
            for _i, cause in errors:
                self.record_error(cause)
        if gt_path.exists():
            gt, errors = read_tum_rows(gt_path)
            for _i, cause in errors:
                self.record_error(cause)
            # sorted, headings unwrapped: ready for interpolation in time
            gt = gt[np.isfinite(gt).all(axis=1)]
            self.gt = gt[np.argsort(gt[:, 0], kind="stable")]
            self.gt[:, 3] = np.unwrap(self.gt[:, 3])
        self.groundtruth_max_gap_s = groundtruth_max_gap_s
        self.root = root

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        """With an odometry file: ``odometry``, or ``odometry.tum`` in the folder."""
        return bool(params.get("odometry")) or (Path(params.get("path", "")) / "odometry.tum").is_file()

    def __iter__(self) -> Iterator[SourceFrame]:
        prev_t: float | None = None
        prev_row: np.ndarray | None = None
        frame = 0
        for i, f in enumerate(self.files):
            raw = read_image_file(f)
            if isinstance(raw, str):  # no image file: nothing is published, nothing moves
                self.record_error(f"image file {f} skipped: {raw}")
                continue
            t = i / self.rate_hz if prev_t is None else prev_t + 1.0 / self.rate_hz
            odom = gt = None
            if self.odo is None:
                pass  # no odometry file: the run measures visual odometry
            elif i < len(self.odo):
                row = self.odo[i]
                if not np.all(np.isfinite(row)):
                    pass  # counted when the file was read, with its line number
                elif prev_row is not None and row[0] <= prev_row[0]:
                    self.record_error(f"odometry row {i}: stamp {row[0]:.6f} is not after the previous "
                                      f"{prev_row[0]:.6f}: skipped")
                else:
                    t = float(row[0])
                    # the motion since the previous good pose (none for the first frame)
                    odom = odometry_between(np.stack([prev_row, row]), float(prev_row[0]), t) \
                        if prev_row is not None else (0.0, 0.0, 0.0)
                    prev_row = row
            else:  # a short odometry file: the images beyond it have no motion
                self.record_error(f"odometry file has {len(self.odo)} rows for {len(self.files)} images: "
                                  f"images beyond row {len(self.odo) - 1} have no motion")
            # a header claiming gigapixels, or bytes that do not decode, are passed on undecoded:
            # the stage refuses them with their cause instead of the decoder allocating here
            img = decode_bounded(raw, self.max_side)
            if self.gt is not None:
                gt = interpolate_pose(self.gt, t, self.groundtruth_max_gap_s)
            prev_t = t
            if img is None:
                yield SourceFrame(frame, t, compressed=raw, format=f.suffix.lstrip("."), odom=odom,
                                  groundtruth=gt)
            else:
                yield SourceFrame(frame, t, image=np.ascontiguousarray(img[:, :, ::-1]), encoding="rgb8",
                                  odom=odom, groundtruth=gt)
            frame += 1

    def info(self) -> dict[str, Any]:
        return {"kind": "folder", "path": str(self.root), "frames": self.length,
                "odometry": self.odo is not None, "groundtruth": self.gt is not None,
                "max_side": self.max_side}


def camera_hint(path: Any) -> str | None:
    """The ``--source camera`` parameter for a video ``path`` that names a camera (an index, a
    /dev/video device, an address such as rtsp://...), or None for a file name."""
    if isinstance(path, int) and not isinstance(path, bool):
        return f"-p device={path}"
    if isinstance(path, str) and "://" in path:
        return f"-p url={path}"
    if isinstance(path, str) and path.startswith("/dev/"):
        return f"-p device={path}"
    return None


class VideoSource(Source):
    """Frames of a video file (OpenCV), stamped by the container's frame rate; frames whose long
    side exceeds ``max_side`` pixels are resized."""

    def __init__(self, path: str, rate_hz: PositiveFloat | None = None, max_frames: PositiveInt | None = None,
                 max_side: PositiveInt | None = DEFAULT_MAX_SIDE) -> None:
        camera = camera_hint(path)
        if camera:
            raise ValueError(f"{path!r} names a camera or a stream, not a video file: read it with --source camera {camera}")
        self.path = Path(path)
        self.max_side = max_side
        if not self.path.is_file():
            raise FileNotFoundError(f"video file {self.path} does not exist")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise ValueError(f"OpenCV cannot open {self.path} as a video")
        fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        cap.release()
        self.rate_hz = rate_hz or (fps if fps > 0 else 10.0)
        self.length = min(n, max_frames) if max_frames and n else (n or max_frames)
        self.max_frames = max_frames

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool:
        return False  # frames only: the run measures visual odometry

    def __iter__(self) -> Iterator[SourceFrame]:
        cap = cv2.VideoCapture(str(self.path))
        i = 0
        try:
            while self.max_frames is None or i < self.max_frames:
                ok, bgr = cap.read()
                if not ok:
                    break
                bgr = fit(bgr, self.max_side)
                yield SourceFrame(i, i / self.rate_hz, image=np.ascontiguousarray(bgr[:, :, ::-1]), encoding="rgb8")
                i += 1
        finally:
            cap.release()

    def info(self) -> dict[str, Any]:
        return {"kind": "video", "path": str(self.path), "frames": self.length, "rate_hz": self.rate_hz}
