"""Loss by cause, counted once per frame, and what the supervisors of a split run learn from
each other's heartbeats: plain data, no process, no network."""

from __future__ import annotations

import time

from neoslam_stream.runtime.collector import FinalTracker, StatsCollector, union_ranges
from neoslam_stream.runtime.hostlink import OUTAGE_S, HostLink
from neoslam_stream.runtime.loss import loss_by_cause, publish_time, to_ranges, useful_stages
from neoslam_stream.runtime.messages import Message, encode
from neoslam_stream.runtime.report import loss_accounting

T0 = 1000.0


def _src(n: int, **extra) -> dict:
    # 10 frames a second from T0, sampled every second
    return {"published_ranges": [[0, n - 1]], "frames_in": n,
            "frame_times": [[f, T0 + f / 10] for f in range(0, n, 10)], **extra}


def test_each_lost_frame_has_one_cause():
    src = _src(100, lost_at_source={"source ring full": 2}, doomed_frames=[3])
    lost = {3, 20, 21, 22, 50, 51, 52, 53, 90, 98, 99}
    final = set(range(100)) - lost
    stats = {"A": {"outputs": ["f"], "consumes": ["image"], "inputs": {"image": {"evicted": 1}}},
             "B": {"outputs": ["pose"], "consumes": ["f"], "first_frame": 23, "last_frame": 99,
                   "inputs": {"f": {"evicted": 0}}, "errors": 1},
             "recorder": {"outputs": [], "consumes": ["pose"], "inputs": {"pose": {"evicted": 40}}}}
    # B's first life processed up to frame 19, its next life from 23 on: 20-22 lost to the restart
    spans = {"B": [[0, 19]]}
    # the link was out from 5.0 s to 5.3 s: frames 50-53 (with the margin in front: 40-53)
    outages = [{"start_wall": T0 + 5.0, "end_wall": T0 + 5.3}]
    useful = useful_stages(stats, "pose")
    assert useful == ["A", "B"]  # the recorder's drops lose no frame
    got = loss_by_cause(src, final, stats, spans, outages, stages=useful)
    assert got["by_cause"] == {"source": 2 + 1, "restart": 3, "link": 4, "ring": 1, "refused": 1,
                               "in flight or unexplained": 1}
    assert got["frames"] == {"restart": [[20, 22]], "link": [[50, 53]]}
    # every lost frame once, the source's unpublished ones too
    assert got["frames_lost"] == len(lost) + 2
    # frames removed on purpose (frame_stride) are not lost
    assert loss_by_cause(src, final, stats, spans, outages, strided=2, stages=useful)["frames_lost"] == len(lost)


def test_a_stage_whose_new_life_processed_nothing_lost_every_frame_after_its_last():
    src = _src(30)
    stats = {"C": {"first_frame": -1, "last_frame": -1}}
    got = loss_by_cause(src, set(range(12)), stats, {"C": [[0, 11]]}, [])
    assert got["by_cause"]["restart"] == 18 and got["frames"]["restart"] == [[12, 29]]


def test_publication_times_are_interpolated():
    times = [[0, 10.0], [10, 11.0], [20, 13.0]]
    assert publish_time(times, 5) == 10.5 and publish_time(times, 15) == 12.0
    assert publish_time(times, 30) == 15.0  # beyond the last sample: the rate before it
    assert publish_time([], 3) is None
    assert to_ranges([5, 1, 2, 3, 7]) == [[1, 3], [5, 5], [7, 7]]
    assert union_ranges([[0, 4], [10, 12]], [[3, 8], [13, 13]]) == [[0, 8], [10, 13]]


def test_a_restarted_source_counts_each_frame_once_and_stage_lives_leave_their_spans():
    c = StatsCollector()
    c.add({"stage": "source", "pid": 1, "frames_in": 40, "published_ranges": [[0, 39]], "first_publish": 5.0,
           "lost_at_source": {"gap": 1}, "frame_times": [[0, 5.0]]})
    # a rollback: the source replays from frame 30
    c.add({"stage": "source", "pid": 2, "frames_in": 20, "published_ranges": [[30, 49]], "first_publish": 9.0,
           "lost_at_source": {"gap": 2}, "frame_times": [[30, 9.0]]})
    src = c.snapshot()["source"]
    assert src["published_ranges"] == [[0, 49]] and src["frames_in"] == 50
    assert src["first_publish"] == 5.0 and src["lost_at_source"] == {"gap": 3}
    assert src["frame_times"] == [[0, 5.0], [30, 9.0]]
    c.add({"stage": "C", "pid": 3, "first_frame": 0, "last_frame": 17, "processed": 18})
    c.add({"stage": "C", "pid": 4, "first_frame": 25, "last_frame": 30, "processed": 6})
    assert c.spans == {"source": [[-1, -1]], "C": [[0, 17]]}
    assert c.snapshot()["C"]["processed"] == 24


def test_frames_published_without_odometry_are_lost_by_that_cause():
    """A frame whose odometry row the source refused is published, but no pose can come of it:
    the report names that cause instead of 'in flight or lost while restarting'."""
    final = FinalTracker()
    for f in (0, 1, 3):
        final.add(f, [], time.time())
    cause = "published without odometry (its row refused or missing at the source): no pose"
    src = {"frames_in": 4, "published_ranges": [[0, 3]], "published_doomed": {cause: 1}}
    acct = loss_accounting(src, final, {}, 0)
    assert acct["frames_lost"] == 1
    assert acct["breakdown"]["source"] == {cause: 1} and acct["breakdown"]["unattributed"] == 0


class _Session:
    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []

    def declare_subscriber(self, key, fn):
        return self

    def undeclare(self):
        pass

    def put(self, key, payload):
        self.puts.append((key, payload))


class _Sample:
    def __init__(self, data: dict) -> None:
        payload = encode(Message("stats", 0, 0.0, data), validate=False)
        self.payload = type("P", (), {"to_bytes": lambda _self: payload})()


def test_heartbeats_name_outages_and_restarted_hosts():
    link = HostLink(_Session(), "r1", "C,D", "secret", time.time())
    beat = {"stage": "host:A,B", "label": "A,B", "life": "one", "stages": ["A", "B"]}
    link._on_heartbeat(_Sample(beat))
    link._on_heartbeat(_Sample(beat))
    assert link.outages == [] and set(link.silent()) == {"A,B"}
    link.peers["A,B"]["_arrived"] -= OUTAGE_S + 2.0  # silent for longer than an outage
    link.peers["A,B"]["_wall"] -= OUTAGE_S + 2.0
    link._on_heartbeat(_Sample(beat))
    assert len(link.outages) == 1 and link.outages[0]["host"] == "A,B"
    assert link.outages[0]["length_s"] >= OUTAGE_S + 2.0 and "host_restarted" not in link.outages[0]
    # the same host back as a new life after a silence: its supervisor was started again
    link.peers["A,B"]["_arrived"] -= OUTAGE_S + 1.0
    link._on_heartbeat(_Sample({**beat, "life": "two"}))
    assert link.restarted[-1]["host"] == "A,B" and link.outages[-1]["host_restarted"] is True
    # our own heartbeats are not a peer's; a peer's reported outages are listed with who saw them
    link._on_heartbeat(_Sample({**beat, "label": "C,D"}))
    assert set(link.silent()) == {"A,B"}
    assert {o["seen_by"] for o in link.all_outages()} == {"C,D"}


def test_a_lossless_run_is_drained_once_every_stage_shows_all_it_was_sent_taken(tmp_path):
    # the supervisor's drain check, no quiet period: each stage's newest stats (taken between two
    # messages) must show everything its upstream published received and nothing waiting, and the
    # final topic's messages must all have reached the supervisor
    from neoslam_stream.config import load_config
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import Supervisor

    c = StatsCollector()
    c.add({"stage": "source", "frames_in": 3, "odom": 0})
    c.add({"stage": "A", "inputs": {"image": {"received": 3, "depth": 0}}, "published": {"feat": 3}})
    c.add({"stage": "B", "inputs": {"feat": {"received": 2, "depth": 0}}, "published": {"bits": 2}})
    assert not c.quiet(["A", "B"], for_s=0.0, fresh_s=60)  # B has not received A's third
    c.add({"stage": "B", "inputs": {"feat": {"received": 3, "depth": 1}}, "published": {"bits": 2}})
    assert not c.quiet(["A", "B"], for_s=0.0, fresh_s=60)  # ... it waits in B's queue
    c.add({"stage": "B", "inputs": {"feat": {"received": 3, "depth": 0}}, "published": {"bits": 3}})
    assert c.quiet(["A", "B"], for_s=0.0, fresh_s=60)
    assert not c.quiet(["A", "B"], for_s=60.0, fresh_s=60)  # a quiet period, where one is asked for

    cfg = load_config("default", {"run": {"live": False}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run")
    sup.collector = StatsCollector()
    sup.collector.add({"stage": "experience_map", "published": {sup.plan.final_topic: 2}})
    assert not sup._final_arrived()
    sup.final.add(0, [], T0)
    assert not sup._final_arrived()
    sup.final.add(1, [], T0)
    assert sup._final_arrived()


def test_a_queue_reports_received_and_waiting_items_together():
    from neoslam_stream.runtime.bus import InputQueue

    q = InputQueue({"x": 2}, lossless=False)
    for f in range(3):  # the third evicts the first
        q.put("x", b"%d" % f, T0)
    assert q.counts() == {"x": (3, 1, 2)}
    q.get(0.1)
    assert q.counts() == {"x": (3, 1, 1)}  # received - evicted - waiting: one taken
