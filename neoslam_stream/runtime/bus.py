"""zenoh transport: sessions, publishers and bounded input queues.

Sessions are peers with multicast and gossip scouting off, listening on loopback only unless the
user configures other endpoints (zenoh's own default would listen on every interface). The
processes of one run form a full mesh, so frames go directly from producer to consumer.

Two delivery modes (DESIGN.md "Queues and loss"): **real-time**, a bounded ring per input that
drops the *oldest* waiting message and never blocks its upstream (congestion control DROP); and
**lossless**, a bounded FIFO whose producer blocks when full (congestion control BLOCK), so
back-pressure reaches the source. The queues are fed by zenoh callbacks, with the semantics of
``RingChannel``/``FifoChannel``, so that one worker thread waits on all its inputs without polling
and every eviction is counted with the frame it removed (docs/runtime.md, "The two modes").
A put may carry its frame in the sample's attachment (:class:`LinkTag`): a lossless run split over
hosts uses it to refuse a stream with a hole in it (a link that lost samples) or of an older epoch.
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import zenoh

KEY_ROOT = "neoslam"


def key_for(run: str, topic: str) -> str:
    """Key expression of a topic in a run: ``neoslam/<run>/<topic>``."""
    return f"{KEY_ROOT}/{run}/{topic}"


#: environment variable naming a zenoh config file applied under neoslam's own settings
ZENOH_CONFIG_ENV = "NEOSLAM_ZENOH_CONFIG"
#: bus.tx_queue, handed to every process of a run the same way
ZENOH_TX_QUEUE_ENV = "NEOSLAM_ZENOH_TX_QUEUE"


def make_config(listen: Sequence[str] | None = None, connect: Sequence[str] | None = None,
                shm: bool = False, mode: str = "peer") -> zenoh.Config:
    """A zenoh config with safe defaults: scouting off, loopback listening, optional SHM."""
    # bus.zenoh_config: a zenoh json5 file for what neoslam does not set itself (TLS certificates,
    # access control...); the supervisor hands it to every process of the run in this variable
    extra = os.environ.get(ZENOH_CONFIG_ENV)
    conf = zenoh.Config.from_file(extra) if extra else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    # zenoh's peer default listens on tcp/[::]:0 (every interface): never leave it implicit.
    conf.insert_json5("listen/endpoints", json.dumps(list(listen or [])))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect or [])))
    conf.insert_json5("transport/shared_memory/enabled", "true" if shm else "false")
    tx_queue = os.environ.get(ZENOH_TX_QUEUE_ENV)
    if tx_queue:
        conf.insert_json5("transport/link/tx/queue/size/data", str(int(tx_queue)))
    return conf


def open_session(listen: list[str] | None = None, connect: list[str] | None = None,
                 shm: bool = False, mode: str = "peer") -> zenoh.Session:
    """Open a zenoh session (peer mode, scouting off, loopback-only unless endpoints say otherwise).

    ``listen``/``connect`` are zenoh endpoints such as ``tcp/127.0.0.1:7447``. With both empty the
    session talks to nobody but itself, which is what a test of one process wants.
    """
    return zenoh.open(make_config(listen, connect, shm, mode))


def wait_for_peers(session: zenoh.Session, n: int, timeout: float) -> bool:
    """Wait until ``session`` has links to ``n`` other sessions, peers or routers (the supervisor is
    a router); zenoh retries connections in the background."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if len(list(session.info.peers_zid())) + len(list(session.info.routers_zid())) >= n:
            return True
        time.sleep(0.05)
    return False


def wait_for_subscribers(publishers: Sequence[zenoh.Publisher], timeout: float) -> bool:
    """Wait until every publisher has at least one matching subscriber (declarations travel after
    the links are up: a message put before they arrive is dropped)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(p.matching_status.matching for p in publishers):
            return True
        time.sleep(0.02)
    return False


# --------------------------------------------------------------------------- input queue

@dataclass
class QueueStats:
    """Per topic of an input queue: items received, and those evicted from a full ring."""

    received: int = 0
    evicted: int = 0


#: no frame before this one (a producer's first put, or an untagged one)
NO_FRAME = -(2**63)
_TAG = struct.Struct("<4sqqq")
_TAG_MAGIC = b"nslk"


@dataclass(frozen=True)
class LinkTag:
    """What a put says about its place in its producer's stream (the sample's attachment): its
    frame, the frame of the producer's previous put on the topic (``NO_FRAME`` for the first) and
    the run's epoch (a lossless run split over hosts starts a new epoch when it rolls back)."""

    frame: int
    prev: int
    epoch: int = 0

    def pack(self) -> bytes:
        return _TAG.pack(_TAG_MAGIC, self.frame, self.prev, self.epoch)

    @staticmethod
    def unpack(data: bytes | None) -> LinkTag | None:
        if data is None or len(data) != _TAG.size:
            return None
        magic, frame, prev, epoch = _TAG.unpack(data)
        return LinkTag(frame, prev, epoch) if magic == _TAG_MAGIC else None


class InputQueue:
    """One waiting place for all the inputs of a worker.

    Each topic has its own bound: in ``ring`` mode a full topic drops its oldest item (counted),
    in ``fifo`` mode the producing zenoh thread blocks until there is room (back-pressure).
    ``get`` returns items of any topic in arrival order.
    """

    def __init__(self, capacities: dict[str, int], lossless: bool, strict: bool = False, epoch: int = 0) -> None:
        if any(c < 1 for c in capacities.values()):
            raise ValueError(f"queue capacities must be >= 1, got {capacities}")
        self.lossless = lossless
        #: ``strict``: each topic must come as its producer sent it (LinkTag.prev is the last frame
        #: taken) and of ``epoch``; a hole closes the topic (nothing after it is taken: a lossless
        #: stage must not process frames out of order) and is reported in ``holes``
        self.strict = strict
        self.epoch = epoch
        self.last_tag: dict[str, int] = {}
        self.holes: dict[str, list[int]] = {}
        self.refused_stale = 0
        self.capacities = dict(capacities)
        self._items: dict[str, deque] = {t: deque() for t in capacities}
        self._order: deque[tuple[str, int]] = deque()  # (topic, seq) arrival order
        self._seq = 0
        self._cond = threading.Condition()
        self._closed = False
        self.stats: dict[str, QueueStats] = {t: QueueStats() for t in capacities}

    def put(self, topic: str, payload: bytes, received: float, tag: LinkTag | None = None) -> None:
        with self._cond:
            if self.strict and tag is not None and not self._in_order(topic, tag):
                return
            q = self._items[topic]
            cap = self.capacities[topic]
            if self.lossless:
                while len(q) >= cap and not self._closed:
                    self._cond.wait(0.1)
                if self._closed:
                    return
            elif len(q) >= cap:
                q.popleft()
                self.stats[topic].evicted += 1
            self._seq += 1
            q.append((self._seq, payload, received))
            self._order.append((topic, self._seq))
            self.stats[topic].received += 1
            self._cond.notify_all()

    def _in_order(self, topic: str, tag: LinkTag) -> bool:
        """Strict mode: whether the tagged put continues ``topic``'s stream (module docstring)."""
        if tag.epoch != self.epoch:
            self.refused_stale += 1
            return False
        if topic in self.holes:
            return False
        last = self.last_tag.get(topic)
        if last is not None and tag.prev != NO_FRAME and tag.prev != last:
            self.holes[topic] = [last, tag.prev, tag.frame]  # lost: the puts after ``last`` up to ``prev``
            return False
        self.last_tag[topic] = tag.frame
        return True

    def _pop_next(self) -> tuple[str, bytes, float] | None:
        while self._order:
            topic, seq = self._order.popleft()
            q = self._items[topic]
            if q and q[0][0] == seq:
                _, payload, received = q.popleft()
                return topic, payload, received
            # that item was evicted; its order entry is stale
        return None

    def get(self, timeout: float) -> tuple[str, bytes, float] | None:
        """The oldest waiting item of any topic, or None after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                item = self._pop_next()
                if item is not None:
                    self._cond.notify_all()
                    return item
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closed:
                    return None
                self._cond.wait(remaining)

    def get_more(self, topic: str, limit: int) -> list[tuple[bytes, float]]:
        """Up to ``limit`` further waiting items of ``topic`` (for micro-batching), oldest first."""
        out: list[tuple[bytes, float]] = []
        with self._cond:
            q = self._items[topic]
            while q and len(out) < limit:
                _, payload, received = q.popleft()
                out.append((payload, received))
            if out:
                # their entries in _order are now stale and skipped by _pop_next
                self._cond.notify_all()
        return out

    def wait_for(self, topic: str, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds until an item of ``topic`` is waiting; whether one is."""
        deadline = time.monotonic() + max(0.0, timeout)
        with self._cond:
            while not self._items[topic] and not self._closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            return bool(self._items[topic])

    def depth(self) -> dict[str, int]:
        with self._cond:
            return {t: len(q) for t, q in self._items.items()}

    def counts(self) -> dict[str, tuple[int, int, int]]:
        """Per topic (received, evicted, depth), read together: every item received and not
        evicted is either waiting (depth) or was taken. Read apart, an item arriving in between
        would look taken (a drain check could end a lossless run before it is processed)."""
        with self._cond:
            return {t: (s.received, s.evicted, len(self._items[t])) for t, s in self.stats.items()}

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class Bus:
    """A session bound to one run: publishers and queue-fed subscribers by topic name."""

    def __init__(self, session: zenoh.Session, run: str, lossless: bool, epoch: int = 0) -> None:
        self.session = session
        self.run = run
        self.lossless = lossless
        self.epoch = epoch
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list[zenoh.Subscriber] = []
        self._prev: dict[str, int] = {}

    def publisher(self, topic: str, express: bool = False) -> zenoh.Publisher:
        pub = self._publishers.get(topic)
        if pub is None:
            cc = zenoh.CongestionControl.BLOCK if self.lossless else zenoh.CongestionControl.DROP
            pub = self.session.declare_publisher(key_for(self.run, topic), congestion_control=cc,
                                                 express=express)
            self._publishers[topic] = pub
        return pub

    def put(self, topic: str, payload: bytes, frame: int | None = None) -> None:
        """Publish ``payload``; with its ``frame``, tagged (:class:`LinkTag`) for strict consumers."""
        if frame is None:
            self.publisher(topic).put(payload)
            return
        tag = LinkTag(int(frame), self._prev.get(topic, NO_FRAME), self.epoch)
        self.publisher(topic).put(payload, attachment=tag.pack())
        self._prev[topic] = tag.frame

    def subscribe(self, topic: str, queue: InputQueue) -> None:
        """Feed ``topic`` into ``queue`` (ring or FIFO semantics are the queue's)."""

        def on_sample(sample: zenoh.Sample, _topic: str = topic) -> None:
            att = sample.attachment
            tag = LinkTag.unpack(att.to_bytes()) if att is not None and queue.strict else None
            queue.put(_topic, sample.payload.to_bytes(), time.time(), tag)

        self._subscribers.append(self.session.declare_subscriber(key_for(self.run, topic), on_sample))

    def subscribe_callback(self, key_expr: str, fn: Callable[[zenoh.Sample], None]) -> zenoh.Subscriber:
        sub = self.session.declare_subscriber(key_expr, fn)
        self._subscribers.append(sub)
        return sub

    def close(self) -> None:
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:  # already closed with the session
                pass
        for pub in self._publishers.values():
            try:
                pub.undeclare()
            except Exception:
                pass
        self._subscribers.clear()
        self._publishers.clear()


class ControlGate:
    """The check every process of a run makes before obeying a ``control`` message.

    The control topic is a key on a bus that any local process can reach (the run's router
    listens on loopback, tools attach to it); one ``stop`` put there used to end every worker of a
    run. The supervisor therefore draws a random token per run and hands it to its children in
    their spawn arguments (never over the bus); a control message is obeyed only when it carries
    that token. Anything else is refused: counted per cause, logged once per cause, ignored.
    """

    MAX_CAUSES = 20

    def __init__(self, token: str, who: str) -> None:
        self.token = token
        self.who = who
        self.refused = 0
        self.causes: dict[str, int] = {}

    def check(self, payload: bytes) -> dict | None:
        """The message's ``data`` when it is a control message with the run's token; else None
        (the refusal is counted)."""
        import hmac

        from .messages import MessageError, decode

        try:
            data = decode(payload, expected_type="control").data
        except MessageError as exc:
            return self._refuse(f"not a control message: {str(exc)[:120]}")
        token = data.get("token")
        if not isinstance(token, str) or not token:
            return self._refuse(f"command {str(data.get('command'))[:40]!r} without the run's token")
        if not self.token or not hmac.compare_digest(token.encode(), self.token.encode()):
            return self._refuse(f"command {str(data.get('command'))[:40]!r} with a wrong token")
        return data

    def _refuse(self, cause: str) -> None:
        import logging

        self.refused += 1
        key = cause if cause in self.causes or len(self.causes) < self.MAX_CAUSES else "(other causes)"
        if key not in self.causes:
            logging.getLogger("neoslam.control").warning("%s: refused a control message: %s", self.who, cause)
        self.causes[key] = self.causes.get(key, 0) + 1
        return None
