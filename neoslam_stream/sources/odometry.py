"""Odometry from a robot without ROS, for any live source: our msgpack ``odom`` messages on a zenoh key.

A robot publishes, for each interval of its wheel odometry, ``encode(Message("odom", seq, stamp,
{"vtrans": m/s, "vrot": rad/s, "dt": s}))`` on a key of its choice (``examples/publish_odometry.py``
does it from wheel speeds read from a serial line or a CSV file). :class:`OdometrySubscription`
sums the motions received (vtrans dt, vrot dt) until a camera frame takes them (:meth:`take`), and
:func:`frame_odometry` turns that sum into the frame's ``(vtrans, vrot, dt)`` over the frame
interval, so that summing vtrans dt over the frames reproduces the odometry path, as with every
source (docs/sources.md). A message that fails validation is handed to ``on_error`` and skipped.
A live source of any kind (the ``zenoh`` source, a camera read here) takes its odometry this way.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from ..runtime.bus import open_session
from ..runtime.messages import MessageError
from ..runtime.messages import decode as decode_message

log = logging.getLogger("neoslam.sources.odometry")

__all__ = ["OdometrySubscription", "frame_odometry"]


def frame_odometry(motion: tuple[float, float], dt: float) -> tuple[float, float, float]:
    """A frame's ``(vtrans, vrot, dt)`` from the motion ``(distance m, heading change rad)`` since
    the previous frame, ``dt`` seconds ago; the first frame (``dt`` 0) moves nothing."""
    d, th = motion
    return (d / dt, th / dt, dt) if dt > 0 else (0.0, 0.0, 0.0)


class OdometrySubscription:
    """Our ``odom`` messages on ``key``, summed until :meth:`take`. ``session``: an open zenoh
    session to subscribe on (a live source's own), else one is opened with ``connect`` /
    ``listen`` / ``mode`` and closed by :meth:`close`."""

    def __init__(self, key: str, session: Any = None, on_error: Callable[[str], None] | None = None,
                 connect: list[str] | None = None, listen: list[str] | None = None, mode: str = "peer") -> None:
        self.key = key
        self._own = session is None
        self.session = open_session(listen=listen or [], connect=connect or [], mode=mode) if session is None \
            else session
        self._on_error = on_error or (lambda cause: log.warning("odometry on %s: %s", key, cause))
        self._lock = threading.Lock()
        self._motion = [0.0, 0.0]
        #: messages summed so far
        self.received = 0
        self._sub = self.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            msg = decode_message(sample.payload.to_bytes(), expected_type="odom")
        except MessageError as exc:
            self._on_error(str(exc))
            return
        dt = float(msg.data.get("dt") or 0.0)
        with self._lock:
            self._motion[0] += float(msg.data["vtrans"]) * dt
            self._motion[1] += float(msg.data["vrot"]) * dt
            self.received += 1

    def take(self) -> tuple[float, float]:
        """The motion (distance m, heading change rad) received since the last call."""
        with self._lock:
            motion = (self._motion[0], self._motion[1])
            self._motion = [0.0, 0.0]
        return motion

    def close(self) -> None:
        try:
            self._sub.undeclare()
            if self._own:
                self.session.close()
        except Exception:  # the session may be closed already
            pass
