"""Sources reading files: an image folder (+ TUM odometry / ground truth) and a video file."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..runtime.imageinfo import too_large, truncation
from ..tum import read_tum
from .bag import interpolate_pose
from .base import Source, SourceFrame

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm")


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


class ImageFolderSource(Source):
    """Images of a folder in name order (``images/`` inside it if present), with optional
    ``odometry.tum`` and ``groundtruth.tum`` (or the files named by ``odometry`` / ``groundtruth``).

    ``odometry.tum`` holds one odometry pose per image (row i belongs to image i): it gives the
    frame stamps (else ``frame / rate_hz``) and each frame's (vtrans, vrot, dt) as the motion
    between consecutive poses. Ground truth is interpolated at each frame's stamp (any rate).
    """

    def __init__(self, path: str, rate_hz: float = 10.0, odometry: str | None = None,
                 groundtruth: str | None = None, max_frames: int | None = None,
                 groundtruth_max_gap_s: float = 5.0) -> None:
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
        self.length = len(self.files)
        odo_path = Path(odometry) if odometry else root / "odometry.tum"
        gt_path = Path(groundtruth) if groundtruth else root / "groundtruth.tum"
        self.odo = read_tum(odo_path) if odo_path.exists() else None
        self.gt = read_tum(gt_path) if gt_path.exists() else None
        if self.gt is not None:  # sorted, headings unwrapped: ready for interpolation in time
            self.gt = self.gt[np.argsort(self.gt[:, 0], kind="stable")]
            self.gt[:, 3] = np.unwrap(self.gt[:, 3])
        self.groundtruth_max_gap_s = groundtruth_max_gap_s
        self.root = root

    def __iter__(self) -> Iterator[SourceFrame]:
        prev_t: float | None = None
        prev_row: np.ndarray | None = None
        for i, f in enumerate(self.files):
            t = i / self.rate_hz if prev_t is None else prev_t + 1.0 / self.rate_hz
            odom = gt = None
            if self.odo is not None and i < len(self.odo):
                row = self.odo[i]
                if not np.all(np.isfinite(row)):
                    self.record_error(f"odometry row {i} holds NaN or infinite values: skipped")
                elif prev_row is not None and row[0] <= prev_row[0]:
                    self.record_error(f"odometry row {i}: stamp {row[0]:.6f} is not after the previous "
                                      f"{prev_row[0]:.6f}: skipped")
                else:
                    t = float(row[0])
                    # the motion since the previous good pose (none for the first frame)
                    odom = odometry_between(np.stack([prev_row, row]), float(prev_row[0]), t) \
                        if prev_row is not None else (0.0, 0.0, 0.0)
                    prev_row = row
            raw = f.read_bytes()
            # a header claiming gigapixels is passed on undecoded: the stage refuses it with its
            # cause instead of the decoder allocating the whole frame here
            img = None
            if raw and not too_large(raw) and truncation(raw) is None:
                try:
                    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR)
                except cv2.error:
                    img = None
            if self.gt is not None:
                gt = interpolate_pose(self.gt, t, self.groundtruth_max_gap_s)
            prev_t = t
            if img is None:  # unreadable file: pass the bytes on, the stage reports the fault
                yield SourceFrame(i, t, compressed=raw, format=f.suffix.lstrip("."), odom=odom,
                                  groundtruth=gt)
                continue
            yield SourceFrame(i, t, image=np.ascontiguousarray(img[:, :, ::-1]), encoding="rgb8", odom=odom,
                              groundtruth=gt)

    def info(self) -> dict[str, Any]:
        return {"kind": "folder", "path": str(self.root), "frames": self.length,
                "odometry": self.odo is not None, "groundtruth": self.gt is not None}


class VideoSource(Source):
    """Frames of a video file (OpenCV), stamped by the container's frame rate."""

    def __init__(self, path: str, rate_hz: float | None = None, max_frames: int | None = None) -> None:
        self.path = Path(path)
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

    def __iter__(self) -> Iterator[SourceFrame]:
        cap = cv2.VideoCapture(str(self.path))
        i = 0
        try:
            while self.max_frames is None or i < self.max_frames:
                ok, bgr = cap.read()
                if not ok:
                    break
                yield SourceFrame(i, i / self.rate_hz, image=np.ascontiguousarray(bgr[:, :, ::-1]), encoding="rgb8")
                i += 1
        finally:
            cap.release()

    def info(self) -> dict[str, Any]:
        return {"kind": "video", "path": str(self.path), "frames": self.length, "rate_hz": self.rate_hz}
