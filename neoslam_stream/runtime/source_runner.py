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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..tum import write_tum
from .bus import Bus, ControlGate, key_for, open_session, wait_for_peers, wait_for_subscribers
from .messages import Message, MessageError, Topic, decode, encode, register_topics
from .node import load_factory
from .source import Source

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


class _Progress:
    """Frames seen on the final topic (credit window and end-of-run drain). ``start_frame``: the
    first frame this run publishes (a resumed run starts at its checkpoint's cut): the credit
    window counts from there, not from 0, or the first frame would wait ``stall_timeout`` for
    frames that will never come."""

    def __init__(self, start_frame: int = 0) -> None:
        self.last_frame = start_frame - 1
        self.count = 0
        self.last_change = time.monotonic()
        self.cond = threading.Condition()
        self.refusal_logged = False

    def on_sample(self, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes())
        except MessageError as exc:  # an unregistered type says so here, once
            if not self.refusal_logged:
                self.refusal_logged = True
                log.warning("a message of the final topic was refused: %s", exc)
            return
        except Exception:
            return
        with self.cond:
            self.count += 1
            if msg.frame > self.last_frame:
                self.last_frame = msg.frame
            self.last_change = time.monotonic()
            self.cond.notify_all()

    def wait_until(self, frame: int, stall_timeout: float, stop: threading.Event) -> bool:
        with self.cond:
            while self.last_frame < frame and not stop.is_set():
                if time.monotonic() - self.last_change > stall_timeout:
                    return False
                self.cond.wait(0.1)
        return True


def frame_messages(sf: Any, published_at: float) -> list[tuple[str, Message]]:
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


def _guarded(source: Any, record_error: Any) -> Iterator[Any]:
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


def run_source(spec: SourceRunSpec) -> None:
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
    session = open_session(spec.listen, spec.connect, spec.shm)
    bus = Bus(session, spec.run, spec.lossless, epoch=spec.epoch)
    progress = _Progress(spec.start_frame)
    gate = ControlGate(spec.control_token, "source")
    bus.subscribe_callback(key_for(spec.run, spec.final_topic), progress.on_sample)

    def _on_control(sample: Any) -> None:
        data = gate.check(sample.payload.to_bytes())  # None: not from this run's supervisor
        if data is not None and data["command"] == "stop" and data.get("target") in (None, "source"):
            stop.set()

    bus.subscribe_callback(key_for(spec.run, "control"), _on_control)
    for t in ("image", "odom", "groundtruth"):
        bus.publisher(t)
    # a frame put before the links are up, or before the consumers' subscriptions have travelled
    # to us, is silently lost: wait for both (bounded, so a misconfigured run still starts)
    if not wait_for_peers(session, spec.expected_peers, timeout=20.0):
        log.warning("linked to fewer than %d processes after 20 s; starting anyway", spec.expected_peers)
    if not wait_for_subscribers([bus.publisher(t) for t in spec.wait_topics], timeout=20.0):
        log.warning("no subscriber matched %s after 20 s; starting anyway", spec.wait_topics)
    # workers announce readiness, then finish starting (first stats, garbage collection of their
    # set-up): a live run gives them a moment, so that its first frames do not meet a busy machine
    # and drop; a lossless run loses nothing to a busy machine and starts at once
    if not spec.lossless:
        time.sleep(spec.settle_s)
    token = session.liveliness().declare_token(key_for(spec.run, "alive/source"))

    counts = {"image": 0, "odom": 0, "groundtruth": 0}
    first_pub: float | None = None
    last_pub: float | None = None
    last_frame = -1
    done = False
    info = source.info()

    # the source's own faults (unreadable records, a truncated file, a frame that cannot be
    # encoded): counted per cause, logged once, reported like a stage's errors
    errors: dict[str, int] = {}
    # which frames were published, as [first, last] ranges of frame numbers (the monitor counts
    # loss by frame numbers: a frame published and never seen on the final topic is lost), and
    # the frames the camera produced that never left the source, per cause
    ranges: list[list[int]] = []
    lost: dict[str, int] = {}
    # frames published that cannot reach the end, known here: the pipeline needs their odometry
    # and the source had none to send (its row refused or missing), by cause
    doomed: dict[str, int] = {}
    doomed_frames: list[int] = []
    NO_ODOMETRY = "published without odometry (its row refused or missing at the source): no pose"
    # [frame, time published] about once a second (where a frame lies in time: outages)
    frame_times: list[list[float]] = []
    GAP = "gap in the source's frame numbers (frames it skipped)"
    RING = "source ring full (camera faster than the run: oldest frames dropped)"
    UNPUBLISHABLE = "image not publishable"

    def mark_published(frame: int) -> None:
        if ranges and frame == ranges[-1][1] + 1:
            ranges[-1][1] = frame
        elif len(ranges) < 100_000:  # bounded: a source numbering at random costs no memory
            ranges.append([frame, frame])

    def record_error(cause: str) -> None:
        cause = cause[:300]
        if cause not in errors:
            log.warning("source: %s", cause)
        errors[cause] = errors.get(cause, 0) + 1

    def publish_stats(final: bool = False) -> None:
        nonlocal info
        try:
            info = source.info()
        except Exception as exc:  # diagnostics only
            info = {"info_error": str(exc)}
        causes = dict(errors)
        for cause, n in dict(getattr(source, "errors", {}) or {}).items():  # records the source skipped
            causes[cause] = causes.get(cause, 0) + int(n)
        lost_now = dict(lost)
        ring = info.get("dropped") if isinstance(info, dict) else None
        if isinstance(ring, int) and not isinstance(ring, bool) and ring > 0:
            lost_now[RING] = ring
        data = {"stage": "source", "pid": os.getpid(), "frames_in": counts["image"], "odom": counts["odom"],
                "published_ranges": [list(r) for r in ranges], "lost_at_source": lost_now,
                "published_doomed": dict(doomed), "doomed_frames": list(doomed_frames), "epoch": spec.epoch,
                "frame_times": [list(x) for x in frame_times],
                "control_refused": gate.refused, "control_refused_causes": dict(gate.causes),
                "errors": sum(causes.values()), "error_causes": causes,
                "groundtruth": counts["groundtruth"], "first_publish": first_pub,
                "last_publish": last_pub, "last_frame": last_frame, "done": done or final,
                "final": final, "info": info, "time": time.time(), "pacing": spec.pacing,
                "rate": spec.rate, "frames_done": progress.count}
        session.put(key_for(spec.run, "stats/source"), encode(Message("stats", 0, time.time(), data),
                                                               validate=False))

    bar = None
    if spec.progress and sys.stderr.isatty():
        from rich.progress import Progress

        total = source.length if spec.max_frames is None or source.length is None else \
            min(spec.max_frames, source.length)
        bar = Progress(transient=False)
        bar.start()
        task = bar.add_task("frames", total=total)

    # the clock starts when the first frame is ready: a source's first frame can be slow (loading,
    # building caches), and a schedule started earlier would make it catch up in a burst, which a
    # small real-time ring turns into lost frames
    t0: float | None = None
    stamp0: float | None = None
    n_sent = 0
    #: frames read, from frame 0 (those below ``start_frame`` too): ``max_frames`` bounds the run's
    #: frame count, so a resumed run stops where the uninterrupted run would have
    n_read = 0
    prev_frame: int | None = None
    # what the source published, for evaluation: ground truth and dead-reckoned wheel odometry
    gt_rows: list[tuple[float, float, float, float]] = []
    odo_rows: list[tuple[float, float, float, float]] = []
    ox = oy = oth = 0.0

    def record_rows(sf: Any, gt_ok: bool, odom_ok: bool) -> None:
        nonlocal ox, oy, oth
        if sf.groundtruth is not None and gt_ok:
            gt_rows.append((sf.stamp, *sf.groundtruth))
        if sf.odom is not None and odom_ok:
            vt, vr, dt = sf.odom
            oth += vr * dt
            ox += vt * dt * math.cos(oth)
            oy += vt * dt * math.sin(oth)
            odo_rows.append((sf.stamp, ox, oy, oth))
    publish_stats()  # "linked and about to read": tools waiting for the source see it now

    # stats go out on their own clock: a live source may wait a long time for its next frame
    def _stats_loop() -> None:
        while not stop.wait(1.0 / spec.stats_hz) and not done:
            try:
                publish_stats()
            except Exception as exc:  # stats must never stop the source
                log.debug("source stats not published: %s", exc)

    threading.Thread(target=_stats_loop, name="source-stats", daemon=True).start()
    try:
        for sf in _guarded(source, record_error):
            if stop.is_set():
                break
            if spec.max_frames is not None and n_read >= spec.max_frames:
                break
            n_read += 1
            if prev_frame is not None and sf.frame > prev_frame + 1 and sf.frame > spec.start_frame:
                # frames the source numbered but never yielded (an unreadable record...): lost
                lost[GAP] = lost.get(GAP, 0) + sf.frame - max(prev_frame + 1, spec.start_frame)
            prev_frame = sf.frame if prev_frame is None else max(prev_frame, sf.frame)
            if sf.frame < spec.start_frame:
                # not published (the resumed state holds them), but in groundtruth.tum and
                # odometry.tum like in the run it continues: its trajectory starts at frame 0 too
                record_rows(sf, True, True)
                continue
            if t0 is None:
                t0 = time.monotonic()
            if spec.duration is not None and time.monotonic() - t0 >= spec.duration:
                break
            # pacing
            if spec.pacing == "fixed" and spec.rate:
                target = t0 + n_sent / spec.rate
            elif spec.pacing == "recorded":
                stamp0 = sf.stamp if stamp0 is None else stamp0
                target = t0 + (sf.stamp - stamp0) / max(spec.rate_multiplier, 1e-9)
            else:
                target = None
                if spec.lossless:
                    ok = progress.wait_until(sf.frame - spec.window, spec.stall_timeout, stop)
                    if not ok:
                        log.warning("no progress on %s for %.0f s; sending on", spec.final_topic,
                                    spec.stall_timeout)
                        progress.last_change = time.monotonic()
            if target is not None:
                delay = target - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                    if stop.is_set():
                        break
            now = time.time()
            sent: set[str] = set()
            for topic, msg in frame_messages(sf, now):
                if topic == "odom" and "odom" not in spec.wait_topics:
                    continue
                try:
                    payload = encode(msg)
                except (MessageError, ValueError, TypeError) as exc:  # e.g. NaN odometry, a bad stamp
                    record_error(f"{topic} of frame {sf.frame} not published: {type(exc).__name__}: {exc}")
                    if topic == "image":
                        lost[UNPUBLISHABLE] = lost.get(UNPUBLISHABLE, 0) + 1
                    continue
                bus.put(topic, payload, sf.frame)
                counts[topic] += 1
                sent.add(topic)
                if topic == "image":
                    mark_published(sf.frame)
                    if (not frame_times or now - frame_times[-1][1] >= 1.0) and len(frame_times) < 100_000:
                        frame_times.append([sf.frame, now])
            if "image" in sent and "odom" in spec.wait_topics and "odom" not in sent:
                doomed[NO_ODOMETRY] = doomed.get(NO_ODOMETRY, 0) + 1
                if len(doomed_frames) < 100_000:
                    doomed_frames.append(sf.frame)
            record_rows(sf, "groundtruth" in sent, "odom" in sent)
            first_pub = now if first_pub is None else first_pub
            last_pub = now
            last_frame = sf.frame
            n_sent += 1
            if bar is not None:
                bar.update(task, advance=1)
        done = True
        publish_stats()
        # Keep the session (and any shared-memory buffers) alive until the supervisor has seen the
        # pipeline drain: zenoh loses samples in flight when their publisher closes.
        deadline = time.monotonic() + spec.linger_timeout
        while not stop.is_set() and time.monotonic() < deadline:
            stop.wait(0.5)
            publish_stats()
    finally:
        if bar is not None:
            bar.stop()
        for name, rows in (("groundtruth.tum", gt_rows), ("odometry.tum", odo_rows)):
            if rows:
                write_tum(Path(spec.run_dir) / name, rows)
        publish_stats(final=True)
        time.sleep(0.3)
        token.undeclare()
        bus.close()
        session.close()
        source.close()
