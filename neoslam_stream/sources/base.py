"""The base class of the built-in sources, on the runtime's :class:`~neoslam_stream.runtime.source.Source`
protocol.

A source is any iterable of :class:`SourceFrame` (a synthetic world, an image folder, a video, a bag,
a zenoh camera). The runtime's source process turns each frame into an ``image`` message, plus
``odom`` and ``groundtruth`` messages with the **same frame number** when present, paces and
publishes them. Sources know nothing about zenoh topics or processes.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

from ..runtime.source import SourceFrame

__all__ = ["Source", "SourceFrame"]


class Source:
    """Base class: iterate to get frames in order. ``rate_hz`` is the recorded/nominal rate."""

    rate_hz: float | None = None
    #: Known length (frames) for progress bars, or None for live/unbounded sources.
    length: int | None = None
    #: frames that come as they happen (a camera, a network stream): a run defaults to real time,
    #: and each frame is published as it comes, never paced by its stamps
    live: bool = False

    def __iter__(self) -> Iterator[SourceFrame]:
        raise NotImplementedError

    @classmethod
    def gives_odometry(cls, **params: Any) -> bool | None:
        """Whether a source built with ``params`` gives odometry with its frames, known before it is
        built (None: it does not say, and a run takes its config's word). A run whose source gives
        none measures visual odometry (``neoslam_stream.sources.odometry_rule``)."""
        return None

    @property
    def errors(self) -> dict[str, int]:
        """Records this source skipped, counted per cause (reported as the source's errors)."""
        if "_errors" not in self.__dict__:
            self.__dict__["_errors"] = {}
        return self.__dict__["_errors"]

    def record_error(self, cause: str) -> None:
        """Count a skipped record (an unreadable odometry row, an undecodable sample...)."""
        if cause not in self.errors:
            logging.getLogger(type(self).__module__).warning("%s: %s", type(self).__name__, cause)
        self.errors[cause] = self.errors.get(cause, 0) + 1

    def info(self) -> dict[str, Any]:
        """Facts about the source for report.json (kind, path, size, rate...)."""
        return {"kind": type(self).__name__}

    def close(self) -> None:
        pass
