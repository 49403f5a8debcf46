"""What the source process reads: the :class:`Source` protocol, the :class:`SourceFrame` it yields
and the messages a frame becomes (:func:`frame_messages`).

The runtime hosts a source as it hosts a node: built in its own process from a dotted factory path
(``SourceSpec``), iterated, paced and published by ``runtime.source_runner``. It never knows which
source it runs; ``launch`` resolves a source kind to its factory (``neoslam_stream.sources``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from .messages import Message

__all__ = ["Source", "SourceFrame", "frame_messages", "guarded"]


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


@runtime_checkable
class Source(Protocol):
    """Iterate to get frames in order. ``rate_hz``: the recorded/nominal rate; ``length``: the
    number of frames when known (progress bars), None for live/unbounded sources. A source may also
    have ``errors`` (records it skipped, counted per cause), which the runner reports; in ``info()``,
    ``dropped`` (frames its own ring dropped) and ``lost`` (frames it knows it lost, per cause: a
    camera's outages), which count as frames lost at the source; and ``interrupt()``, which makes a
    waiting iteration end soon (called from another thread at the run's stop or duration); and
    ``live`` (True: its frames come as they happen, and are published as they come, not paced by
    their stamps)."""

    rate_hz: float | None
    length: int | None

    def __iter__(self) -> Iterator[SourceFrame]: ...

    def info(self) -> dict[str, Any]:
        """Facts about the source for report.json (kind, path, size, rate...)."""
        ...

    def close(self) -> None: ...


def frame_messages(sf: SourceFrame, published_at: float) -> list[tuple[str, Message]]:
    """The messages a frame becomes: ``image`` (with the ``source`` trace entry stamped at
    ``published_at``), ``odom`` and ``groundtruth``, each where the frame has it."""
    out: list[tuple[str, Message]] = []
    if sf.image is not None or sf.compressed is not None:
        data: dict[str, Any] = {}
        if sf.image is not None:
            data["image"] = np.ascontiguousarray(sf.image)
            data["encoding"] = sf.encoding
        else:
            data["compressed"] = bytes(sf.compressed)
            data["format"] = sf.format or "jpeg"
        out.append(("image", Message("image", sf.frame, sf.stamp, data,
                                     [("source", published_at, published_at, published_at)])))
    if sf.odom is not None:
        vtrans, vrot, dt = sf.odom
        out.append(("odom", Message("odom", sf.frame, sf.stamp,
                                    {"vtrans": float(vtrans), "vrot": float(vrot), "dt": float(dt)})))
    if sf.groundtruth is not None:
        out.append(("groundtruth", Message("groundtruth", sf.frame, sf.stamp,
                                           {"pose": np.asarray(sf.groundtruth, dtype=np.float64)})))
    return out


def guarded(source: Source, record_error: Callable[[str], None]) -> Iterator[SourceFrame]:
    """Iterate ``source``; an exception while reading (a truncated bag, a corrupt container) is
    recorded as the source's error and ends the stream, so the frames read so far are processed
    and the run ends normally."""
    it = iter(source)
    while True:
        try:
            sf = next(it)
        except StopIteration:
            return
        except Exception as exc:
            record_error(f"reading stopped: {type(exc).__name__}: {exc}")
            return
        yield sf
