"""What every frame source yields, and how a source is described.

A source is any iterable of :class:`SourceFrame` (a synthetic world, an image folder, a video, a bag,
a zenoh camera). The runtime's source worker turns each frame into an ``image`` message, plus
``odom`` and ``groundtruth`` messages with the **same frame number** when present, paces them
(recorded rate, fixed rate, or as fast as the pipeline takes in lossless mode) and publishes them.
Sources know nothing about zenoh topics or processes.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class SourceFrame:
    """One camera frame and what was measured with it.

    ``frame`` is the source's sequence number, consecutive from 0 (a gap means the source itself
    lost a frame). ``stamp`` is source time in seconds. Exactly one of ``image`` (HxW or HxWxC uint8,
    ``encoding`` rgb8/bgr8/mono8) and ``compressed`` (JPEG/PNG bytes, ``format`` "jpeg"/"png") is set,
    or neither for odometry-only sources. ``odom`` is ``(vtrans m/s, vrot rad/s, dt s)`` over the
    interval ending at this frame; ``groundtruth`` is ``(x, y, theta)`` in metres/radians.
    """

    frame: int
    stamp: float
    image: np.ndarray | None = None
    encoding: str = "rgb8"
    compressed: bytes | None = None
    format: str | None = None
    odom: tuple[float, float, float] | None = None
    groundtruth: tuple[float, float, float] | None = None


class Source:
    """Base class: iterate to get frames in order. ``rate_hz`` is the recorded/nominal rate."""

    rate_hz: float | None = None
    #: Known length (frames) for progress bars, or None for live/unbounded sources.
    length: int | None = None

    def __iter__(self) -> Iterator[SourceFrame]:
        raise NotImplementedError

    @property
    def errors(self) -> dict[str, int]:
        """Records this source skipped, counted per cause (reported as the source's errors)."""
        if "_errors" not in self.__dict__:
            self.__dict__["_errors"] = {}
        return self.__dict__["_errors"]

    def record_error(self, cause: str) -> None:
        """Count a skipped record (an unreadable odometry row, an undecodable sample...)."""
        import logging

        if cause not in self.errors:
            logging.getLogger(type(self).__module__).warning("%s: %s", type(self).__name__, cause)
        self.errors[cause] = self.errors.get(cause, 0) + 1

    def info(self) -> dict[str, Any]:
        """Facts about the source for report.json (kind, path, size, rate...)."""
        return {"kind": type(self).__name__}

    def close(self) -> None:
        pass
