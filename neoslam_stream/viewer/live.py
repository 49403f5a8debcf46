"""A running pipeline, logged live to a :class:`RunView`.

The viewer attaches in client mode to the run's router (``endpoints.json``, as ``neoslam monitor``)
and subscribes to :data:`LIVE_TOPICS`. Its zenoh callbacks only queue: images in a ring of
:data:`IMAGE_RING` (the oldest dropped and counted, so a slow viewer never back-pressures a
lossless run through zenoh's blocking congestion control; with an image interval, those that come
sooner than it after the last one kept are let pass before they are even copied, counted), the
small messages in a deque of at most :data:`SMALL_MAX` (beyond, dropped and counted). One thread
decodes and logs them, until the run's report.json (or part.json) appears.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from .recording import RunView

log = logging.getLogger("neoslam.viewer")

#: images waiting to be logged; beyond this the oldest is dropped (counted in ``ViewStats``)
IMAGE_RING = 4
#: small messages waiting to be logged, at most (beyond: dropped, counted)
SMALL_MAX = 100_000
#: the run's topics the live viewer subscribes to (the stats of every stage come on stats/**)
LIVE_TOPICS = ("image", "odom", "groundtruth", "visual_template", "experience_map/pose",
               "experience_map/map", "stats/**", "log")


class LiveFeed:
    """Subscriptions to a running pipeline; callbacks only queue (see the module docstring).
    ``image_interval_s``: keep at most one image per this many seconds (0: every one)."""

    def __init__(self, run: str, connect: list[str], image_interval_s: float = 0.0) -> None:
        from ..runtime.bus import key_for, open_session

        self.session = open_session(listen=[], connect=connect, mode="client")
        self.run = run
        self.images: deque[bytes] = deque(maxlen=IMAGE_RING)
        self.images_dropped = self.images_thinned = self.small_dropped = 0
        self.image_interval_s = image_interval_s
        self._image_at = -float("inf")
        self.small: deque[tuple[str, bytes]] = deque()
        self.cond = threading.Condition()
        self.subs = []
        for topic in LIVE_TOPICS:
            self.subs.append(self.session.declare_subscriber(key_for(run, topic), self._callback(topic)))

    def _callback(self, topic: str) -> Any:
        def on(sample: Any) -> None:
            if topic == "image" and self.image_interval_s > 0:
                now = time.monotonic()
                if now - self._image_at < self.image_interval_s:
                    self.images_thinned += 1
                    return
                self._image_at = now
            payload = sample.payload.to_bytes()
            with self.cond:
                if topic == "image":
                    if len(self.images) == self.images.maxlen:
                        self.images_dropped += 1
                    self.images.append(payload)
                elif len(self.small) >= SMALL_MAX:
                    self.small_dropped += 1
                else:
                    self.small.append((topic, payload))
                self.cond.notify()
        return on

    def announce(self, name: str) -> Any:
        """A liveliness token ``alive/<name>`` once subscribed: a run told to wait for this tool
        (``run.wait_for``) starts its source now."""
        from ..runtime.bus import key_for

        return self.session.liveliness().declare_token(key_for(self.run, f"alive/{name}"))

    def take(self, timeout: float) -> tuple[list[tuple[str, bytes]], list[bytes]]:
        with self.cond:
            if not self.small and not self.images:
                self.cond.wait(timeout)
            small, self.small = list(self.small), deque()
            images = list(self.images)
            self.images.clear()
        return small, images

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


class LiveLogger:
    """Decodes the queued messages and logs them to a :class:`RunView`."""

    def __init__(self, view: RunView) -> None:
        # the algorithms' topics this viewer decodes: registered, so decoding validates them
        from ..nodes.topics import ALGORITHM_TOPICS
        from ..runtime.messages import register_topics

        register_topics(ALGORITHM_TOPICS)

        self.view = view
        self.t0 = time.monotonic()
        self.last_stats: dict[str, tuple[float, int]] = {}
        self._bad_logged = False
        self._odo = (0.0, 0.0, 0.0)  # the odometry's dead-reckoned x, y, theta

    def odometry_step(self, vtrans: float, vrot: float, dt: float) -> np.ndarray:
        """One odometry sample dead-reckoned by the rule of the sources' odometry.tum
        (:func:`neoslam_stream.tum.integrate_odometry`: turn by vrot*dt, then advance vtrans*dt)."""
        x, y, th = self._odo
        th += vrot * dt
        self._odo = (x + vtrans * dt * math.cos(th), y + vtrans * dt * math.sin(th), th)
        return np.array(self._odo)

    def _bad(self, what: str, exc: Exception) -> None:
        self.view.stats.bad_messages += 1
        if not self._bad_logged:  # once: a stream of bad messages must not flood the log
            log.warning("viewer: skipping a bad %s message: %s", what, exc)
            self._bad_logged = True

    def image(self, payload: bytes) -> None:
        from ..nodes.camera import decode_rgb
        from ..runtime.messages import decode

        try:
            msg = decode(payload, expected_type="image")
            rgb = decode_rgb(msg.data)
        except ValueError as exc:  # MessageError and InvalidInput are ValueErrors
            self._bad("image", exc)
            return
        self.view.image(msg.frame, msg.stamp, rgb)

    def message(self, topic: str, payload: bytes) -> None:
        from ..runtime.messages import decode

        try:
            msg = decode(payload)
        except ValueError as exc:
            self._bad(topic, exc)
            return
        d = msg.data
        try:
            if topic == "visual_template":
                self.view.template(msg.frame, msg.stamp, int(d["id"]), bool(d.get("is_loop_closure")))
            elif topic == "experience_map/pose":
                self.view.pose(msg.frame, msg.stamp, np.asarray(d["pose"], dtype=np.float64),
                               int(d.get("exp_id", -1)), d.get("local"))
            elif topic == "groundtruth":
                self.view.groundtruth(msg.frame, msg.stamp, np.asarray(d["pose"], dtype=np.float64))
            elif topic == "odom":
                self.view.odometry_pose(msg.frame, msg.stamp, self.odometry_step(
                    float(d["vtrans"]), float(d["vrot"]), float(d.get("dt") or 0.0)))
            elif topic == "experience_map/map":  # the final map's export, or a viewer's arrays
                self.view.experience_map(d.get("export") or {"nodes": np.asarray(d["nodes"]).tolist(),
                                                             "links": np.asarray(d.get("links", [])).tolist()},
                                         msg.frame)
            elif msg.type == "stats":
                self.stats(d)
            elif msg.type == "log":
                self.view.log_line(msg.stamp, d["level"], d["process"], d["name"], d["message"])
        except (KeyError, TypeError, ValueError) as exc:
            self._bad(topic, exc)

    def stats(self, d: dict[str, Any]) -> None:
        stage = d.get("stage")
        if stage == "source":
            self.view.source_stats(d)
            return
        if not isinstance(stage, str) or "processed" not in d:
            return
        now = time.monotonic() - self.t0
        done = int(d["processed"])
        prev = self.last_stats.get(stage)
        self.last_stats[stage] = (now, done)
        if prev is not None and now > prev[0]:
            self.view.stage_stats(now, stage, (done - prev[1]) / (now - prev[0]), d)


def watch_live(run_dir: Path, view: RunView, duration: float | None = None,
               connect: list[str] | None = None, image_interval_s: float = 0.0, announce: str = "",
               stop: Any = None, ready: Any = None) -> None:
    """Log a running pipeline until its report.json (or part.json) appears (the run ended),
    ``duration`` seconds pass or Ctrl-C; then log the final map from map.json when the run wrote one,
    and hand the view the run's report. ``view``: a :class:`RunView` or any view with its calls
    (foxglove.FoxgloveView); ``announce``: the liveliness name declared once subscribed (and once
    ``ready()`` returned, when given); ``stop``: a callable, true to stop watching."""
    ep = json.loads((run_dir / "endpoints.json").read_text())
    feed = LiveFeed(ep["run"], list(ep["connect"]) + list(connect or []), image_interval_s)
    if ready is not None:
        ready()
    token = feed.announce(announce) if announce else None
    logger = LiveLogger(view)
    t_end = None if duration is None else time.monotonic() + duration
    ended_at: float | None = None
    try:
        while t_end is None or time.monotonic() < t_end:
            small, images = feed.take(0.2)
            for topic, payload in small:
                logger.message(topic, payload)
            for payload in images:
                logger.image(payload)
            view.tick()
            if stop is not None and stop():
                break
            if not small and not images:
                if ended_at is None and _ended(run_dir):
                    ended_at = time.monotonic()
                if ended_at is not None and time.monotonic() - ended_at > 1.0:
                    break
    except KeyboardInterrupt:
        pass
    finally:
        view.stats.images_dropped = feed.images_dropped
        view.stats.images_thinned = feed.images_thinned
        view.stats.messages_dropped = feed.small_dropped
        if token is not None:
            token.undeclare()
        feed.close()
    map_path = run_dir / "map.json"
    if ended_at is not None and map_path.exists() and not view.stats.map_nodes:
        try:
            view.experience_map(json.loads(map_path.read_text()))
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("map.json not shown: %s", exc)
    report = run_dir / "report.json"
    if ended_at is not None and report.exists():
        try:
            view.run_ended(json.loads(report.read_text()))
        except (OSError, ValueError) as exc:
            log.warning("report.json not shown: %s", exc)


def _started(run_dir: Path) -> float:
    """When this run started (endpoints.json is written at start): a report older than that
    belongs to an earlier run in the same folder."""
    return (run_dir / "endpoints.json").stat().st_mtime


#: what a run writes into its folder when it ends: report.json (the host with the source), or
#: part.json (a host running only some stages of a run split over hosts: runtime/share.py)
END_FILES = ("report.json", "part.json")


def _ended(run_dir: Path) -> bool:
    started = _started(run_dir)
    return any((run_dir / f).exists() and (run_dir / f).stat().st_mtime >= started for f in END_FILES)


def is_running(run_dir: Path) -> bool:
    """A run folder whose run has not ended: endpoints.json and no end file newer than it."""
    return (run_dir / "endpoints.json").exists() and not _ended(run_dir)
