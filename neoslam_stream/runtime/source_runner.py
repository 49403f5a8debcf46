"""The source process: reads a :class:`~neoslam_stream.runtime.source.Source`, paces it and
publishes its frames.

Each :class:`SourceFrame` becomes an ``image`` message (with a ``source`` trace entry stamped at
publication), plus ``odom`` and ``groundtruth`` messages with the same frame number. Pacing:
``fixed`` (``rate`` frames per second, a live camera), ``recorded`` (the source's own stamps,
times ``rate_multiplier``) or ``asap`` (lossless only: publishers block, and a credit window keeps
the source at most ``window`` frames ahead of the last frame seen on the run's final topic, so
queues and memory stay bounded whatever the pipeline's speed).

After its last frame the source keeps its session open until the supervisor tells it to stop
(once the pipeline has drained): zenoh loses samples still in flight when a publisher closes.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..tum import write_tum
from . import runlog
from .bus import Bus, ControlGate, key_for, open_session, wait_for_peers, wait_for_subscribers
from .camera_log import CameraLog
from .credit_window import CreditWindow
from .messages import Message, MessageError, Topic, encode, register_topics
from .node import load_factory
from .source import Source, SourceFrame, frame_messages, guarded

log = logging.getLogger("neoslam.source")


@dataclass
class SourceSpec:
    """How to build a :class:`Source` in the source process: ``factory`` is ``"module:callable"``."""

    factory: str
    params: dict[str, Any] = field(default_factory=dict)

    def build(self) -> Source:
        src = load_factory(self.factory)(**self.params)
        if not isinstance(src, Source):
            raise TypeError(f"{self.factory} returned {type(src).__name__}, not a Source")
        return src


@dataclass
class SourceRunSpec:
    """Everything the source process needs; plain data so it crosses a ``spawn``."""

    source: SourceSpec
    run: str
    run_dir: str
    lossless: bool
    #: the topic whose arrival marks a frame as done (the plan's): the credit window counts on it
    final_topic: str
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    shm: bool = False
    pacing: str = "fixed"  # fixed | recorded | asap
    rate: float | None = 10.0
    rate_multiplier: float = 1.0
    max_frames: int | None = None
    duration: float | None = None
    window: int = 8
    stall_timeout: float = 60.0
    #: after the last frame, wait at most this long for the supervisor's stop
    linger_timeout: float = 600.0
    progress: bool = False
    #: frames below this number are skipped (resume from a checkpoint)
    start_frame: int = 0
    stats_hz: float = 2.0
    #: processes (workers, monitor, supervisor) to be linked to before the first frame
    expected_peers: int = 0
    #: the source topics the pipeline consumes: each must have a matching subscriber before the
    #: first frame; ``odom`` is published only when listed (a pipeline that measures visual
    #: odometry publishes its own, and a second odometry of the same frame would be refused)
    wait_topics: list[str] = field(default_factory=lambda: ["image"])
    #: pause between "everyone is linked" and the first frame of a live run
    settle_s: float = 1.0
    #: the run's control secret (bus.ControlGate): control messages without it are refused
    control_token: str = ""
    #: the message types of the run with their schemas (the plan's): the final topic's among them
    topics: list[Topic] = field(default_factory=list)
    #: the run's epoch (bus.LinkTag): a lossless run split over hosts starts a new one when it rolls back
    epoch: int = 0
    #: camera.zip: a JPEG every this many seconds of source time (0: none), at most this many
    camera_log_s: float = 0.5
    camera_log_frames: int = 600


class SourceRunner:
    """The body of the source process (module docstring): it links to the run, paces the
    source's frames and publishes them, keeps what its stats report (frames published as ranges
    of frame numbers, frames lost before leaving, its own faults by cause) and, at the end, the
    ground truth and dead-reckoned odometry it published (groundtruth.tum, odometry.tum).
    ``stop`` is set by a signal or by the supervisor's ``stop`` control message."""

    #: why frames never left the source, and why a published frame cannot reach the end
    GAP = "gap in the source's frame numbers (frames it skipped)"
    RING = "source ring full (camera faster than the run: oldest frames dropped)"
    UNPUBLISHABLE = "image not publishable"
    NO_ODOMETRY = "published without odometry (its row refused or missing at the source): no pose"

    def __init__(self, spec: SourceRunSpec, source: Source, stop: threading.Event) -> None:
        self.spec = spec
        self.source = source
        self.stop = stop
        self.progress = CreditWindow(spec.start_frame)
        self.gate = ControlGate(spec.control_token, "source")
        self.session: Any = None
        self.bus: Bus | None = None
        self.token: Any = None
        self.counts = {"image": 0, "odom": 0, "groundtruth": 0}
        self.first_pub: float | None = None
        self.last_pub: float | None = None
        self.last_frame = -1
        self.done = False
        self.info: Any = {}
        #: the source's figures when its stream ended (source_figures)
        self.figures_at_end: tuple[Any, dict[str, int]] | None = None
        # the source's own faults (unreadable records, a truncated file, a frame that cannot be
        # encoded): counted per cause, logged once, reported like a stage's errors
        self.errors: dict[str, int] = {}
        # which frames were published, as [first, last] ranges of frame numbers (the monitor counts
        # loss by frame numbers: a frame published and never seen on the final topic is lost), and
        # the frames the camera produced that never left the source, per cause
        self.ranges: list[list[int]] = []
        self.lost: dict[str, int] = {}
        # frames published that cannot reach the end, known here: the pipeline needs their odometry
        # and the source had none to send (its row refused or missing), by cause
        self.doomed: dict[str, int] = {}
        self.doomed_frames: list[int] = []
        # [frame, time published] about once a second (where a frame lies in time: outages)
        self.frame_times: list[list[float]] = []
        # the clock starts when the first frame is ready: a source's first frame can be slow
        # (loading, building caches), and a schedule started earlier would make it catch up in a
        # burst, which a small real-time ring turns into lost frames
        self.t0: float | None = None
        self.stamp0: float | None = None
        self.n_sent = 0
        #: frames read, from frame 0 (those below ``start_frame`` too): ``max_frames`` bounds the
        #: run's frame count, so a resumed run stops where the uninterrupted run would have
        self.n_read = 0
        self.prev_frame: int | None = None
        # what the source published, for evaluation: ground truth and dead-reckoned wheel odometry
        self.gt_rows: list[tuple[float, float, float, float]] = []
        self.odo_rows: list[tuple[float, float, float, float]] = []
        self.pose = (0.0, 0.0, 0.0)
        self.bar: Any = None
        self.bar_task: Any = None
        self.logs: Any = None
        self.camera = CameraLog(spec.camera_log_s, spec.camera_log_frames)

    # ------------------------------------------------------------------ links and control
    def connect(self) -> None:
        """Open the session, follow the final topic and the control topic, declare the publishers,
        wait until the run is linked and subscribed, then announce readiness."""
        spec = self.spec
        self.session = open_session(spec.listen, spec.connect, spec.shm)
        self.logs = runlog.attach(self.session, spec.run, "source")  # the run's log lines, on the bus
        self.bus = bus = Bus(self.session, spec.run, spec.lossless, epoch=spec.epoch)
        bus.subscribe_callback(key_for(spec.run, spec.final_topic), self.progress.on_sample)
        bus.subscribe_callback(key_for(spec.run, "control"), self.on_control)
        for t in ("image", "odom", "groundtruth"):
            bus.publisher(t)
        # a frame put before the links are up, or before the consumers' subscriptions have travelled
        # to us, is silently lost: wait for both (bounded, so a misconfigured run still starts)
        if not wait_for_peers(self.session, spec.expected_peers, timeout=20.0):
            log.warning("linked to fewer than %d processes after 20 s; starting anyway", spec.expected_peers)
        if not wait_for_subscribers([bus.publisher(t) for t in spec.wait_topics], timeout=20.0):
            log.warning("no subscriber matched %s after 20 s; starting anyway", spec.wait_topics)
        # workers announce readiness, then finish starting (first stats, garbage collection of their
        # set-up): a live run gives them a moment, so that its first frames do not meet a busy machine
        # and drop; a lossless run loses nothing to a busy machine and starts at once
        if not spec.lossless:
            time.sleep(spec.settle_s)
        self.token = self.session.liveliness().declare_token(key_for(spec.run, "alive/source"))

    def on_control(self, sample: Any) -> None:
        """The supervisor's ``stop`` (for everyone or for the source) ends the stream."""
        data = self.gate.check(sample.payload.to_bytes())  # None: not from this run's supervisor
        if data is not None and data["command"] == "stop" and data.get("target") in (None, "source"):
            self.stop.set()

    # ------------------------------------------------------------------ what the stats say
    def mark_published(self, frame: int) -> None:
        ranges = self.ranges
        if ranges and frame == ranges[-1][1] + 1:
            ranges[-1][1] = frame
        elif len(ranges) < 100_000:  # bounded: a source numbering at random costs no memory
            ranges.append([frame, frame])

    def record_error(self, cause: str) -> None:
        cause = cause[:300]
        if cause not in self.errors:
            log.warning("source: %s", cause)
        self.errors[cause] = self.errors.get(cause, 0) + 1

    def record_rows(self, sf: SourceFrame, gt_ok: bool, odom_ok: bool) -> None:
        """The frame's ground truth and integrated odometry rows (those it published)."""
        if sf.groundtruth is not None and gt_ok:
            self.gt_rows.append((sf.stamp, *sf.groundtruth))
        if sf.odom is not None and odom_ok:
            vt, vr, dt = sf.odom
            ox, oy, oth = self.pose
            oth += vr * dt
            ox += vt * dt * math.cos(oth)
            oy += vt * dt * math.sin(oth)
            self.pose = (ox, oy, oth)
            self.odo_rows.append((sf.stamp, ox, oy, oth))

    def source_figures(self) -> tuple[Any, dict[str, int]]:
        """The source's ``info()`` and its skipped records per cause; once its stream has ended
        (``done``), as they were then: a live source goes on receiving until it is closed (a
        camera's thread replaces the frame in its slot while the run drains), and what it counts
        after the run stopped taking frames is not the run's loss."""
        if self.figures_at_end is not None:
            return self.figures_at_end
        done = self.done
        try:
            info = self.source.info()
        except Exception as exc:  # diagnostics only
            info = {"info_error": str(exc)}
        figures = (info, dict(getattr(self.source, "errors", {}) or {}))
        if done:
            self.figures_at_end = figures
        return figures

    def publish_stats(self, final: bool = False) -> None:
        spec = self.spec
        self.info, skipped = self.source_figures()
        info = self.info
        causes = dict(self.errors)
        for cause, n in skipped.items():  # records the source skipped
            causes[cause] = causes.get(cause, 0) + int(n)
        lost_now = dict(self.lost)
        ring = info.get("dropped") if isinstance(info, dict) else None
        if isinstance(ring, int) and not isinstance(ring, bool) and ring > 0:
            lost_now[self.RING] = ring
        known = info.get("lost") if isinstance(info, dict) else None
        for cause, n in (known.items() if isinstance(known, dict) else ()):  # a live camera's outages...
            if isinstance(n, int) and not isinstance(n, bool) and n > 0:
                lost_now[str(cause)[:300]] = lost_now.get(str(cause)[:300], 0) + n
        data = {"stage": "source", "pid": os.getpid(), "frames_in": self.counts["image"],
                "odom": self.counts["odom"], "published_ranges": [list(r) for r in self.ranges],
                "lost_at_source": lost_now, "published_doomed": dict(self.doomed),
                "doomed_frames": list(self.doomed_frames), "epoch": spec.epoch,
                "frame_times": [list(x) for x in self.frame_times],
                "control_refused": self.gate.refused, "control_refused_causes": dict(self.gate.causes),
                "errors": sum(causes.values()), "error_causes": causes,
                "groundtruth": self.counts["groundtruth"], "first_publish": self.first_pub,
                "last_publish": self.last_pub, "last_frame": self.last_frame, "done": self.done or final,
                "final": final, "info": info, "time": time.time(), "pacing": spec.pacing,
                "rate": spec.rate, "frames_done": self.progress.count}
        self.session.put(key_for(spec.run, "stats/source"), encode(Message("stats", 0, time.time(), data),
                                                                    validate=False))

    def stats_loop(self) -> None:
        """Stats on their own clock (a thread): a live source may wait a long time for its next frame."""
        while not self.stop.wait(1.0 / self.spec.stats_hz) and not self.done:
            try:
                self.publish_stats()
            except Exception as exc:  # stats must never stop the source
                log.debug("source stats not published: %s", exc)

    def watch_end(self, began: float) -> None:
        """A live source can wait long for its next frame (a camera being reopened), and the
        stream loop sees the run's stop and ``duration`` only between frames: on either, a source
        with ``interrupt()`` is told to end its iteration (a thread)."""
        interrupt = getattr(self.source, "interrupt", None)
        if interrupt is None:
            return
        duration = self.spec.duration
        while not self.done:
            if self.stop.wait(0.2):
                break
            start = self.t0 if self.t0 is not None else began
            if duration is not None and time.monotonic() - start >= duration:
                break
        if not self.done:
            interrupt()

    # ------------------------------------------------------------------ progress bar
    def start_bar(self) -> None:
        """A rich progress bar of the frames published, when asked for and stderr is a terminal."""
        if not (self.spec.progress and sys.stderr.isatty()):
            return
        from rich.progress import Progress

        length, most = self.source.length, self.spec.max_frames
        total = length if most is None or length is None else min(most, length)
        self.bar = Progress(transient=False)
        self.bar.start()
        self.bar_task = self.bar.add_task("frames", total=total)

    # ------------------------------------------------------------------ frames
    def pace(self, sf: SourceFrame) -> bool:
        """Wait until frame ``sf`` is due (fixed rate, recorded timing, or the lossless credit
        window); False when the run was stopped meanwhile."""
        spec = self.spec
        assert self.t0 is not None
        if spec.pacing == "fixed" and spec.rate:
            target = self.t0 + self.n_sent / spec.rate
        elif spec.pacing == "recorded" and not getattr(self.source, "live", False):
            # a live source's frames come as they happen: pacing them by their stamps would hold
            # every frame back by as long as the first one waited
            self.stamp0 = sf.stamp if self.stamp0 is None else self.stamp0
            target = self.t0 + (sf.stamp - self.stamp0) / max(spec.rate_multiplier, 1e-9)
        else:
            target = None
            if spec.lossless:
                ok = self.progress.wait_until(sf.frame - spec.window, spec.stall_timeout, self.stop)
                if not ok:
                    log.warning("no progress on %s for %.0f s; sending on", spec.final_topic,
                                spec.stall_timeout)
                    self.progress.last_change = time.monotonic()
        if target is not None:
            delay = target - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)
                if self.stop.is_set():
                    return False
        return True

    def publish_frame(self, sf: SourceFrame) -> None:
        """Publish the frame's image, odometry and ground truth, and note what was sent."""
        spec = self.spec
        assert self.bus is not None
        now = time.time()
        sent: set[str] = set()
        for topic, msg in frame_messages(sf, now):
            if topic == "odom" and "odom" not in spec.wait_topics:
                continue
            try:
                payload = encode(msg)
            except (MessageError, ValueError, TypeError) as exc:  # e.g. NaN odometry, a bad stamp
                self.record_error(f"{topic} of frame {sf.frame} not published: {type(exc).__name__}: {exc}")
                if topic == "image":
                    self.lost[self.UNPUBLISHABLE] = self.lost.get(self.UNPUBLISHABLE, 0) + 1
                continue
            self.bus.put(topic, payload, sf.frame)
            self.counts[topic] += 1
            sent.add(topic)
            if topic == "image":
                self.mark_published(sf.frame)
                self.camera.add(sf.frame, sf.stamp, sf.image, sf.encoding, sf.compressed)
                times = self.frame_times
                if (not times or now - times[-1][1] >= 1.0) and len(times) < 100_000:
                    times.append([sf.frame, now])
        if "image" in sent and "odom" in spec.wait_topics and "odom" not in sent:
            self.doomed[self.NO_ODOMETRY] = self.doomed.get(self.NO_ODOMETRY, 0) + 1
            if len(self.doomed_frames) < 100_000:
                self.doomed_frames.append(sf.frame)
        self.record_rows(sf, "groundtruth" in sent, "odom" in sent)
        self.first_pub = now if self.first_pub is None else self.first_pub
        self.last_pub = now
        self.last_frame = sf.frame
        self.n_sent += 1
        if self.bar is not None:
            self.bar.update(self.bar_task, advance=1)

    def stream(self) -> None:
        """Every frame of the source up to the run's limits, paced and published."""
        spec = self.spec
        for sf in guarded(self.source, self.record_error):
            if self.stop.is_set():
                break
            if spec.max_frames is not None and self.n_read >= spec.max_frames:
                break
            self.n_read += 1
            prev = self.prev_frame
            if prev is not None and sf.frame > prev + 1 and sf.frame > spec.start_frame:
                # frames the source numbered but never yielded (an unreadable record...): lost
                self.lost[self.GAP] = self.lost.get(self.GAP, 0) + sf.frame - max(prev + 1, spec.start_frame)
            self.prev_frame = sf.frame if prev is None else max(prev, sf.frame)
            if sf.frame < spec.start_frame:
                # not published (the resumed state holds them), but in groundtruth.tum and
                # odometry.tum like in the run it continues: its trajectory starts at frame 0 too
                self.record_rows(sf, True, True)
                continue
            if self.t0 is None:
                self.t0 = time.monotonic()
            if spec.duration is not None and time.monotonic() - self.t0 >= spec.duration:
                break
            if not self.pace(sf):
                break
            self.publish_frame(sf)

    # ------------------------------------------------------------------ the process
    def run(self) -> None:
        """Link, stream, then keep the session open until the supervisor's stop; always write the
        TUM files, send final stats and close."""
        self.connect()
        self.info = self.source.info()
        self.start_bar()
        self.publish_stats()  # "linked and about to read": tools waiting for the source see it now
        threading.Thread(target=self.stats_loop, name="source-stats", daemon=True).start()
        threading.Thread(target=self.watch_end, args=(time.monotonic(),), name="source-end", daemon=True).start()
        try:
            self.stream()
            self.done = True
            self.publish_stats()
            # Keep the session (and any shared-memory buffers) alive until the supervisor has seen the
            # pipeline drain: zenoh loses samples in flight when their publisher closes.
            deadline = time.monotonic() + self.spec.linger_timeout
            while not self.stop.is_set() and time.monotonic() < deadline:
                self.stop.wait(0.5)
                self.publish_stats()
        finally:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
        for name, rows in (("groundtruth.tum", self.gt_rows), ("odometry.tum", self.odo_rows)):
            if rows:
                write_tum(Path(self.spec.run_dir) / name, rows)
        self.camera.write(self.spec.run_dir)
        self.publish_stats(final=True)
        time.sleep(0.3)
        self.token.undeclare()
        runlog.detach(self.logs)
        assert self.bus is not None
        self.bus.close()
        self.session.close()
        self.source.close()


def run_source(spec: SourceRunSpec) -> None:
    """Process entry: build the source (a failure is one line in source_error.txt and exit code
    3), then run it until its end or the supervisor's stop."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s source %(levelname)s %(message)s")
    stop = threading.Event()

    def _stop(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    register_topics(spec.topics)
    try:
        source = spec.source.build()
    except Exception as exc:  # a missing file, an unreadable bag, a bad parameter: say it plainly
        cause = f"{type(exc).__name__}: {exc}"
        log.error("the source cannot start: %s", cause)
        Path(spec.run_dir, "source_error.txt").write_text(cause + "\n")
        sys.exit(3)
    SourceRunner(spec, source, stop).run()
