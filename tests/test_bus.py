"""Queue semantics through real zenoh sessions linked over loopback (no mocked bus)."""

import threading
import time

import pytest

from neoslam_stream.runtime.bus import Bus, InputQueue, open_session, wait_for_peers
from neoslam_stream.runtime.ports import free_port

pytestmark = pytest.mark.zenoh


@pytest.fixture()
def linked_buses():
    made = []

    def make(lossless: bool):
        ep = f"tcp/127.0.0.1:{free_port()}"
        a = open_session(listen=[ep])
        b = open_session(listen=[], connect=[ep])
        assert wait_for_peers(b, 1, 10.0)
        made.extend([a, b])
        return Bus(a, "test", lossless), Bus(b, "test", lossless)

    yield make
    for s in made:
        s.close()


def _wait_delivery(queue: InputQueue, n: int, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while queue.stats["x"].received < n and time.monotonic() < deadline:
        time.sleep(0.02)


def test_ring_keeps_the_newest_k(linked_buses):
    pub_bus, sub_bus = linked_buses(lossless=False)
    q = InputQueue({"x": 3}, lossless=False)
    sub_bus.subscribe("x", q)
    time.sleep(0.5)  # let the subscription reach the publisher
    for i in range(20):
        pub_bus.put("x", i.to_bytes(4, "little"))
    _wait_delivery(q, 20)
    got = []
    while (item := q.get(timeout=0.2)) is not None:
        got.append(int.from_bytes(item[1], "little"))
    # nobody consumed while 20 arrived: exactly the newest 3 remain, oldest first
    assert got == [17, 18, 19]
    assert q.stats["x"].evicted == 17


def test_lossless_loses_nothing_with_a_slow_consumer(linked_buses):
    pub_bus, sub_bus = linked_buses(lossless=True)
    q = InputQueue({"x": 2}, lossless=True)
    sub_bus.subscribe("x", q)
    time.sleep(0.5)
    n = 60
    sender = threading.Thread(target=lambda: [pub_bus.put("x", i.to_bytes(4, "little") * 1000)
                                              for i in range(n)])
    sender.start()
    got = []
    deadline = time.monotonic() + 30
    while len(got) < n and time.monotonic() < deadline:
        item = q.get(timeout=0.5)
        if item is not None:
            got.append(int.from_bytes(item[1][:4], "little"))
            time.sleep(0.01)  # slower than the publisher
    sender.join(10)
    assert got == list(range(n))
    assert q.stats["x"].evicted == 0
    assert max(q.depth().values()) <= 2


def test_queue_interleaves_topics_in_arrival_order():
    q = InputQueue({"a": 2, "b": 2}, lossless=False)
    q.put("a", b"1", 0.0)
    q.put("b", b"2", 0.0)
    q.put("a", b"3", 0.0)
    q.put("a", b"4", 0.0)  # evicts a:1
    assert [q.get(0.1)[1] for _ in range(3)] == [b"2", b"3", b"4"]
    assert q.get(0.05) is None


def test_rejects_zero_capacity():
    with pytest.raises(ValueError):
        InputQueue({"a": 0}, lossless=False)


def test_strict_inputs_take_a_stream_only_as_its_producer_sent_it(linked_buses):
    """A lossless run over hosts: each put carries its frame and the producer's previous one
    (bus.LinkTag). A hole (puts lost on a link) closes the topic; an older epoch is refused."""
    from neoslam_stream.runtime.bus import NO_FRAME, LinkTag

    assert LinkTag.unpack(LinkTag(7, 5, 3).pack()) == LinkTag(7, 5, 3)
    assert LinkTag.unpack(b"not a tag") is None and LinkTag.unpack(None) is None
    pub_bus, sub_bus = linked_buses(lossless=True)
    q = InputQueue({"x": 50}, lossless=True, strict=True)
    sub_bus.subscribe("x", q)
    time.sleep(0.5)
    # frames 0, 1, 3 (2 refused upstream: the producer never put it, so 3 says "after 1")
    for f in (0, 1, 3):
        pub_bus.put("x", f.to_bytes(4, "little"), frame=f)
    _wait_delivery(q, 3)
    assert q.stats["x"].received == 3 and not q.holes
    # a put lost on the way: the next one shows the hole, and nothing after it is taken
    pub_bus._prev["x"] = 4  # as if frame 4 had been put and lost
    for f in (5, 6):
        pub_bus.put("x", f.to_bytes(4, "little"), frame=f)
    time.sleep(0.5)
    assert q.holes == {"x": [3, 4, 5]} and q.stats["x"].received == 3
    # a new queue (a restarted consumer) of epoch 1 takes a restarted producer's stream (its
    # first put follows nothing) and refuses what an old producer of epoch 0 still sends
    q1 = InputQueue({"x": 50}, lossless=True, strict=True, epoch=1)
    q1.put("x", b"old", 0.0, LinkTag(7, 6, 0))
    q1.put("x", b"new", 0.0, LinkTag(3, NO_FRAME, 1))
    q1.put("x", b"new", 0.0, LinkTag(4, 3, 1))
    assert q1.refused_stale == 1 and q1.stats["x"].received == 2 and not q1.holes
    # untagged puts (a tool, an older producer) and real-time queues are not checked
    q2 = InputQueue({"x": 5}, lossless=False)
    q2.put("x", b"a", 0.0, LinkTag(9, 1, 5))
    assert q2.stats["x"].received == 1


def test_wait_for_returns_when_an_item_of_its_topic_arrives_or_the_time_is_up():
    q = InputQueue({"x": 2, "y": 2}, lossless=False)
    assert not q.wait_for("x", 0.01)  # nothing came
    q.put("y", b"other topic", 0.0)
    assert not q.wait_for("x", 0.01)  # an item of another topic does not count
    later = threading.Timer(0.05, lambda: q.put("x", b"frame", 0.0))
    later.start()
    assert q.wait_for("x", 30.0)  # returns when it arrives, long before the 30 s
    later.join()
    assert q.depth() == {"x": 1, "y": 1}  # waiting takes nothing


def _bindable(port: int) -> bool:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_a_port_another_process_handed_out_lately_is_not_handed_out_again(tmp_path, monkeypatch):
    """Two runs starting together on one machine drew the same free port now and then: both saw it
    free, and the later worker to bind it failed its start-up ("Address already in use"). The
    draw is scripted here to repeat a port; the registry of ports handed out must skip it."""
    import tempfile
    import types

    from neoslam_stream.runtime import ports

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    low = ports._ephemeral_low()
    p, q = [port for port in range(max(1025, low - 12000), low, 97) if _bindable(port)][:2]
    draws = iter([p, p, q, p])

    class Scripted:
        def choice(self, _candidates):
            return next(draws)

    monkeypatch.setattr(ports, "random", types.SimpleNamespace(Random=Scripted))
    monkeypatch.setattr(ports, "_ISSUED_PORTS", set())
    assert ports.free_port() == p
    monkeypatch.setattr(ports, "_ISSUED_PORTS", set())  # another process: its own set is empty
    assert ports.free_port() == q  # p was drawn again and skipped
    assert {int(line.split()[0]) for line in (tmp_path / ports._port_registry().name).read_text().splitlines()} == {p, q}
    # once the reservation has run out (the worker has bound it, or never will), p may come again
    monkeypatch.setattr(ports, "PORT_RESERVE_S", 0.0)
    monkeypatch.setattr(ports, "_ISSUED_PORTS", set())
    assert ports.free_port() == p
