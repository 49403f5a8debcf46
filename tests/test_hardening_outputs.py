"""Hardened workers: bugs are not bad input, each bad input counted once, one message cannot make a
stage run away with its frame number, a full disk costs a checkpoint and not the stage, a saved
state that does not fit ends the worker with one line. (The recorder's outputs:
test_recorder_outputs.py.)

Most tests host nodes in an in-process :class:`Worker` (no zenoh): its ``handle`` is what the worker
process calls for every message taken from its queue.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest
from test_recorder_outputs import disk_full_after

from neoslam_stream.algorithms.errors import InvalidInput
from neoslam_stream.config import load_config
from neoslam_stream.runtime.bus import InputQueue
from neoslam_stream.runtime.messages import MAX_FRAME, Message, MessageError, encode, register_unvalidated
from neoslam_stream.runtime.node import Node, NodeSpec, StageInputError, is_input_error
from neoslam_stream.runtime.worker import Worker, WorkerSpec

#: the probe node's free-form test messages (declared, as every topic must be)
register_unvalidated("probe")


# ------------------------------------------------------------------------------ helpers
class ProbeNode(Node):
    """Does what each message asks: ``ok``, or raise an invalid input, a stage input error or a bug."""

    inputs = ("probe",)
    outputs = ()

    def __init__(self, batchable: bool = False) -> None:
        super().__init__()
        self.batchable = batchable
        self.seen: list[int] = []
        self.batches: list[list[int]] = []

    def warm_up(self, max_batch):
        self.warmed = max_batch

    def process(self, topic, msg):
        what = msg["what"]
        if what == "invalid":
            raise InvalidInput(f"frame {msg.frame}: the algorithm refuses this input")
        if what == "stage":
            raise StageInputError(f"frame {msg.frame}: the node refuses this input")
        if what == "bug":
            raise ValueError("an internal ValueError (a bug)")
        if what == "keyerror":
            return [("x", msg.data["missing"])]
        self.seen.append(msg.frame)
        return []

    def process_batch(self, topic, msgs):
        self.batches.append([m.frame for m in msgs])
        if any(m["what"] != "ok" for m in msgs):
            raise StageInputError("a frame of the batch is bad")
        self.seen += [m.frame for m in msgs]
        return []

    def state_dict(self):
        return {"seen": list(self.seen)}


def make_probe(batchable: bool = False) -> ProbeNode:
    return ProbeNode(batchable)


class FakeBus:
    def __init__(self) -> None:
        self.out: list[tuple[str, bytes]] = []

    def put(self, topic: str, payload: bytes, frame: int | None = None) -> None:
        self.out.append((topic, payload))


def _worker(tmp_path: Path, spec: NodeSpec, **kw) -> Worker:
    kw.setdefault("lossless", True)
    w = Worker(WorkerSpec(name=spec.name, stages=[spec], run="test-run", run_dir=str(tmp_path),
                          checkpoint_dir=str(tmp_path / "checkpoint"), **kw))
    w.build()
    w.setup()
    w.bus = FakeBus()  # type: ignore[assignment]
    return w


def _probe(frame: int, what: str = "ok") -> bytes:
    return encode(Message("probe", frame, float(frame), {"what": what}))


def _stats(w: Worker) -> dict:
    return w.stats_messages()[0].data


# ------------------------------------------------------------------------------ 1. bugs are not bad input
def test_algorithms_refuse_bad_input_with_their_own_error_type():
    from neoslam_stream.algorithms.features import InvalidImage
    from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
    from neoslam_stream.algorithms.ratslam.local_view import LocalViewCells
    from neoslam_stream.algorithms.ratslam.pose_cells import PoseCellNetwork
    from neoslam_stream.algorithms.ratslam.visual_odometry import VisualOdometry
    from neoslam_stream.algorithms.spatial_view import SpatialViewCells
    from neoslam_stream.algorithms.temporal_memory import TemporalMemory

    refusals = [
        lambda: SpatialViewCells(sdr_size=256).compute(np.array([1, 300])),
        lambda: TemporalMemory(columns=32, cells_per_column=2).compute(np.array([0.5, 1.5])),
        lambda: TemporalMemory(columns=32, cells_per_column=2).compute(np.array([40])),
        lambda: PoseCellNetwork(pc_dim_xy=11).on_odo(float("nan"), 0.0, 0.1),
        lambda: PoseCellNetwork(pc_dim_xy=11).on_view_template(-1),
        lambda: ExperienceMap().on_odo(0.1, float("inf"), 0.1),
        lambda: LocalViewCells(template_x_size=60, template_y_size=20, vt_shift_match=4).on_image(
            np.zeros(10, np.uint8)),
        lambda: VisualOdometry().on_image(np.zeros((60, 80), np.uint8), float("nan")),
    ]
    for refuse in refusals:
        with pytest.raises(InvalidInput) as info:
            refuse()
        assert is_input_error(info.value)
    assert issubclass(InvalidImage, InvalidInput) and issubclass(InvalidInput, ValueError)
    # what the runtime counts as bad input, and what it does not
    assert is_input_error(StageInputError("x")) and is_input_error(MessageError("x"))
    assert not is_input_error(ValueError("x")) and not is_input_error(KeyError("x"))


def test_a_bug_in_a_node_is_counted_apart_from_bad_input_and_the_worker_goes_on(tmp_path, caplog):
    w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe"))
    kinds = ["ok", "invalid", "ok", "stage", "bug", "ok", "keyerror", "bug", "ok"]
    with caplog.at_level(logging.WARNING, logger="neoslam.worker"):
        for f, what in enumerate(kinds):
            w.handle("probe", _probe(f, what), time.time())
    st = _stats(w)
    node = w.stages[0].node
    assert node.seen == [f for f, what in enumerate(kinds) if what == "ok"]  # it went on
    # bad input: the algorithm's InvalidInput and the node's StageInputError, each once
    assert st["errors"] == 2 and sum(st["error_causes"].values()) == 2
    assert all(c.startswith(("InvalidInput:", "StageInputError:")) for c in st["error_causes"])
    # bugs: a plain ValueError and a KeyError are no bad input; counted apart, traceback logged once
    assert st["internal_errors"] == 3
    assert st["internal_error_causes"] == {"ValueError: an internal ValueError (a bug)": 2,
                                           "KeyError: 'missing'": 1}
    tracebacks = [r for r in caplog.records if r.levelno == logging.ERROR and "internal error" in r.message]
    assert len(tracebacks) == 2 and "Traceback" in tracebacks[0].message
    assert st["processed"] == 4 and st["received"] == len(kinds)


def test_the_in_process_api_raises_bad_input_to_the_caller_and_goes_on():
    from neoslam_stream.api import NeoSLAM

    slam = NeoSLAM(_light_config(), backend=True)
    img = np.zeros((96, 160, 3), np.uint8)
    slam.step(img, odometry=(0.1, 0.0, 0.1))
    with pytest.raises(InvalidInput, match="5 channels"):
        slam.step(np.zeros((96, 160, 5), np.uint8), odometry=(0.1, 0.0, 0.1))
    with pytest.raises(ValueError, match="int64"):
        slam.step(img, odometry=(0.1, 0.0, 0.1), frame=MAX_FRAME + 1)
    r = slam.step(img, odometry=(0.1, 0.0, 0.1))
    assert r.frame == 2 and r.template is not None and r.pose is not None
    slam.finish()


def _light_config():
    from neoslam_stream.config import load_config

    return load_config("default", {"features": {"backbone": "random_alexnet"},
                                   "projector": {"projection": "sparse"}, "pose_cells": {"pc_dim_xy": 11}})


# ------------------------------------------------------------------------------ 2. counted once
def test_a_bad_frame_in_a_micro_batch_is_counted_once(tmp_path):
    w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe", {"batchable": True}), max_batch=8)
    w.queue = InputQueue({"probe": 16}, lossless=True)
    kinds = ["ok", "stage", "ok", "invalid", "ok", "ok"]
    for f, what in enumerate(kinds):
        w.queue.put("probe", _probe(f, what), time.time())
    w.handle(*w.queue.get(0.1))  # the first and, batched with it, every other waiting one
    assert w.queue.depth() == {"probe": 0}
    st = _stats(w)
    assert st["errors"] == 2
    assert sum(st["error_causes"].values()) == st["errors"]  # each bad frame once, not batch + frame
    assert st["received"] == len(kinds) and st["processed"] == 4
    assert w.stages[0].node.seen == [0, 2, 4, 5]


def test_realtime_workers_batch_the_frames_waiting_in_their_ring(tmp_path):
    # a stage that falls behind in a real-time run gets every frame its drop-oldest ring
    # still holds in one call (one pass over B's matrix for all of them), as in lossless runs
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import Supervisor

    w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe", {"batchable": True}), max_batch=8,
                lossless=False)
    w.queue = InputQueue({"probe": 3}, lossless=False)
    for f in range(5):  # the ring keeps the newest three
        w.queue.put("probe", _probe(f), time.time())
    w.handle(*w.queue.get(0.1))
    assert w.stages[0].node.batches == [[2, 3, 4]]
    assert _stats(w)["processed"] == 3
    cfg = load_config("default", {"run": {"mode": "realtime", "max_batch": 5, "live": False}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run")
    assert {sup.layout.worker_spec(w).max_batch for w in sup.layout.groups} == {5}


def test_a_real_time_worker_warms_its_batching_stages_up_before_the_first_frame(tmp_path):
    # Node.warm_up(max_batch) is called after setup in a real-time run, for a batchable node only
    # (a live stream must not wait for a first call's one-time costs); a lossless run needs none
    for lossless, batchable, expected in ((False, True, 6), (False, False, None), (True, True, None)):
        w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe", {"batchable": batchable}),
                    max_batch=6, lossless=lossless)
        assert getattr(w.stages[0].node, "warmed", None) == expected


def test_a_stage_with_a_batch_wait_pairs_a_lone_frame_only_while_frames_come_often(tmp_path):
    # run.batch_wait_ms: a frame found alone waits (from its arrival) for a second one when the
    # recent arrivals came at least that often; the frames' received times are the arrival times
    import threading

    def worker(waits: dict) -> tuple[Worker, list[int]]:
        w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe", {"batchable": True}), max_batch=8,
                    batch_wait_ms=waits)
        w.queue = InputQueue({"probe": 8}, lossless=True)
        waited: list[int] = []
        wait_for = w.queue.wait_for
        w.queue.wait_for = lambda topic, timeout: waited.append(1) or wait_for(topic, timeout)  # type: ignore
        return w, waited

    t0 = time.time()
    w, waited = worker({"probe": 2000.0})
    w.handle("probe", _probe(0), t0 - 0.02)  # no arrival seen yet: no wait
    w.handle("probe", _probe(1), t0 - 0.01)  # one arrival seen: no interval known yet
    assert not waited and w.stages[0].node.seen == [0, 1]  # one at a time (no batch call)
    # frames 0 and 1 came 10 ms apart (< 2 s): frame 2, alone, waits for frame 3 and takes it along
    later = threading.Timer(0.05, lambda: w.queue.put("probe", _probe(3), time.time()))
    later.start()
    w.handle("probe", _probe(2), time.time())
    later.join()
    assert waited == [1] and w.stages[0].node.batches == [[2, 3]]

    # frames that came 3 s apart (> 2 s): a lone frame does not wait
    w, waited = worker({"probe": 2000.0})
    for f in range(3):
        w.handle("probe", _probe(f), t0 - 6 + 3 * f)
    assert not waited and w.stages[0].node.seen == [0, 1, 2] and not w.stages[0].node.batches

    # a stage not named waits for nothing
    w, waited = worker({"other": 2000.0})
    for f in range(3):
        w.handle("probe", _probe(f), t0 + 0.001 * f)
    assert not waited and w.stages[0].node.seen == [0, 1, 2] and not w.stages[0].node.batches


def test_batch_waits_reach_the_workers_of_the_stages_they_name(tmp_path):
    from neoslam_stream.config import ConfigError
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import Supervisor

    cfg = load_config("default", {"run": {"batch_wait_ms": {"B": 12.5}, "live": False},
                                  "projector": {"device": "cpu"}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run")
    assert {w: sup.layout.worker_spec(w).batch_wait_ms for w in sup.layout.groups} == {
        w: ({"B": 12.5} if w == "B" else {}) for w in sup.layout.groups}
    with pytest.raises(ConfigError, match="batch_wait_ms"):
        load_config("default", {"run": {"batch_wait_ms": {"B": -1}}})


def test_error_causes_always_add_up_to_the_errors(tmp_path):
    w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe"))
    for f in range(80):  # more distinct causes than are kept
        w.handle("probe", _probe(f, "stage"), time.time())
    st = _stats(w)
    assert st["errors"] == 80 and sum(st["error_causes"].values()) == 80
    assert st["error_causes"]["(other causes)"] == 80 - 50


# ------------------------------------------------------------------------------ 3. frames far ahead
def _pose_cells_worker(tmp_path: Path, **kw) -> Worker:
    return _worker(tmp_path, NodeSpec("pose_cells", "neoslam_stream.nodes.ratslam:make_pose_cells_node",
                                      {"pc_dim_xy": 11}), checkpoint_every=20, **kw)


def _tpl(frame: int, vt: int = 0) -> bytes:
    return encode(Message("visual_template", frame, frame * 0.1,
                          {"id": vt, "is_loop_closure": False, "relative_rad": 0.0, "best_interval": -1,
                           "best_score": 0}), validate=False)


def _odo(frame: int) -> bytes:
    return encode(Message("odom", frame, frame * 0.1, {"vtrans": 0.1, "vrot": 0.0, "dt": 0.1}), validate=False)


def _drive(w: Worker, frames: int, inject_at: int, injected: list[tuple[str, bytes]]) -> None:
    for f in range(frames):
        w.handle("odom", _odo(f), time.time())
        if f == inject_at:
            for topic, payload in injected:
                w.handle(topic, payload, time.time())
        w.handle("visual_template", _tpl(f, f % 7), time.time())


def _cuts(tmp_path: Path) -> list[int]:
    root = tmp_path / "checkpoint"
    return sorted(int(p.name) for p in root.iterdir()) if root.exists() else []


def test_a_frame_number_far_ahead_is_refused_and_the_stage_goes_on(tmp_path):
    frames = 100
    w = _pose_cells_worker(tmp_path)
    # odometry of frame 2**64 - 1 (what crashed the pose cells), then messages far ahead
    _drive(w, frames, 50, [("odom", _odo(2**64 - 1)), ("odom", _odo(10**7)),
                           ("visual_template", _tpl(10**6, 3))])
    st = _stats(w)
    assert st["errors"] == 3 and sum(st["error_causes"].values()) == 3
    causes = " | ".join(st["error_causes"])
    assert "does not fit in int64" in causes and causes.count("max_frame_jump=100000") == 2
    # every real frame went through: one action per odometry, in order
    assert st["processed"] == 2 * frames
    assert [t for t, _ in w.bus.out] == ["pose_cells/action"] * frames
    # checkpoint cuts: one per multiple of 20 the frames passed, none beyond the frames seen
    assert _cuts(tmp_path) == [20, 40, 60, 80]


def test_checkpoint_cuts_stay_bounded_without_the_jump_limit(tmp_path):
    """With ``max_frame_jump`` off, frames far ahead on both inputs still give at most one cut per
    message and no recursion (they made the pose cells save ~495 cuts, then die of RecursionError)."""
    frames = 100
    w = _pose_cells_worker(tmp_path, max_frame_jump=0)
    _drive(w, frames, 50, [("odom", _odo(10**15)), ("visual_template", _tpl(10**6, 3))])
    st = _stats(w)
    assert st["received"] == 2 * frames + 2
    assert len(_cuts(tmp_path)) <= st["received"]
    assert len(_cuts(tmp_path)) <= 10


def test_an_output_beyond_int64_is_refused_by_the_codec():
    with pytest.raises(MessageError, match="int64"):
        encode(Message("odom", 2**63, 0.0, {"vtrans": 0.0, "vrot": 0.0}))


# ------------------------------------------------------------------------------ 5. disk full
def test_a_full_disk_costs_a_checkpoint_not_the_stage(tmp_path, monkeypatch, caplog):
    fail = {"on": True}
    disk_full_after(monkeypatch, fail)
    w = _worker(tmp_path, NodeSpec("probe", f"{__name__}:make_probe"), checkpoint_every=2)
    with caplog.at_level(logging.ERROR, logger="neoslam.worker"):
        for f in range(10):
            w.handle("probe", _probe(f), time.time())
    st = _stats(w)
    assert st["processed"] == 10 and st["errors"] == 0 and st["internal_errors"] == 0
    assert st["counters"]["write_errors"] == 4  # cuts 2, 4, 6, 8
    assert len([r for r in caplog.records if "disk full writing" in r.message]) == 1
    leftovers = [p for p in (tmp_path / "checkpoint").rglob("*") if p.is_file()]
    assert leftovers == []  # no torn or temporary state file
    fail["on"] = False
    w.handle("probe", _probe(10), time.time())
    saved = sorted(p.relative_to(tmp_path / "checkpoint") for p in (tmp_path / "checkpoint").rglob("*.state"))
    assert saved == [Path("000000010") / "probe.state"]


# ------------------------------------------------------------------------------ saved states that do not fit
class PickyNode(ProbeNode):
    """Refuses a state made with another threshold, as an algorithm's load_state_dict does."""

    def load_state_dict(self, state):
        if state["theta"] != 5:
            raise ValueError(f"probe.theta: the state was made with {state['theta']}, the config has 5")


def make_picky() -> PickyNode:
    return PickyNode()


def test_a_stage_that_refuses_its_saved_state_ends_the_worker_with_one_line(tmp_path):
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file
    from neoslam_stream.runtime.worker import StateRefused

    path = tmp_path / "picky.state"
    save_state_file(path, {"theta": 7})
    assert load_state_file(path) == {"theta": 7}
    w = Worker(WorkerSpec(name="picky", stages=[NodeSpec("picky", f"{__name__}:make_picky")], run="test-run",
                          run_dir=str(tmp_path), lossless=True, resume_states={"picky": str(path)}))
    w.build()
    with pytest.raises(StateRefused, match=r"stage picky refuses the state in .*picky.state: probe.theta: "
                                           r"the state was made with 7, the config has 5"):
        w.setup()


# ------------------------------------------------------------------------------ the format version of state files
def _unversioned(path: Path, state: dict) -> Path:
    """A state file as written before state files had a format version: the state map itself."""
    import msgpack

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(msgpack.packb(state))
    return path


def test_a_state_file_carries_its_format_version_and_round_trips(tmp_path):
    import msgpack

    from neoslam_stream.runtime import checkpoint as ck

    path = tmp_path / "C.state"
    ck.save_state_file(path, {"theta": 7, "cells": np.arange(5, dtype=np.int32), "nested": {"ids": [1, 2]}})
    # the version is a field of what is written, ahead of the state
    written = msgpack.unpackb(path.read_bytes(), raw=False, ext_hook=lambda code, data: None)
    assert list(written)[:2] == ["format", "version"] and written["version"] == ck.STATE_VERSION
    assert ck.state_file_version(path) == ck.STATE_VERSION
    back = ck.load_state_file(path)
    assert back["theta"] == 7 and back["nested"] == {"ids": [1, 2]}
    assert back["cells"].dtype == np.int32 and back["cells"].tolist() == [0, 1, 2, 3, 4]
    assert back["cells"].flags.writeable  # nodes mutate what they load


def test_a_state_file_of_another_version_is_refused_with_one_line(tmp_path):
    import msgpack

    from neoslam_stream.runtime import checkpoint as ck

    version = ck.STATE_VERSION
    old = _unversioned(tmp_path / "old.state", {"theta": 7})
    other = tmp_path / "other.state"
    other.write_bytes(msgpack.packb({"format": "neoslam-state", "version": version + 1, "state": {"theta": 7}}))
    for path, found, has in ((old, None, "no format version"), (other, version + 1, f"format version {version + 1}")):
        assert ck.state_file_version(path) == found
        with pytest.raises(ck.StateFormatError) as err:
            ck.load_state_file(path)
        assert str(err.value) == (f"{path} has {has}; this build reads version {version} "
                                  f"(it was written by another version of neoslam)")


def test_a_worker_refuses_a_state_file_of_another_version(tmp_path):
    from neoslam_stream.runtime.worker import StateRefused

    old = _unversioned(tmp_path / "picky.state", {"theta": 5})  # a state the node would take
    w = Worker(WorkerSpec(name="picky", stages=[NodeSpec("picky", f"{__name__}:make_picky")], run="test-run",
                          run_dir=str(tmp_path), lossless=True, resume_states={"picky": str(old)}))
    w.build()
    with pytest.raises(StateRefused, match=r"^stage picky: .*picky.state has no format version; this build "
                                           r"reads version 1"):
        w.setup()


def test_resuming_from_a_checkpoint_of_another_version_is_refused_with_one_line(tmp_path, capsys):
    from neoslam_stream.cli import main
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.checkpoint import cut_dir, save_state_file
    from neoslam_stream.runtime.topology import Supervisor

    cfg = load_config("default", {"run": {"live": False}})
    names = [s.name for s in build_plan(cfg).stages]
    # a checkpoint of the current version: the supervisor resumes from it
    current = tmp_path / "current"
    for name in names:
        save_state_file(cut_dir(current / "checkpoint", 20) / f"{name}.state", {"theta": 5})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "resumed", resume=current)
    assert sup.layout.worker_spec("C").resume_states == {"C": str(cut_dir(current / "checkpoint", 20) / "C.state")}
    # the same cut written before state files had a version: refused before any process starts
    old = tmp_path / "old"
    for name in names:
        _unversioned(cut_dir(old / "checkpoint", 20) / f"{name}.state", {"theta": 5})
    assert main(["run", "--resume", str(old), "--out", str(tmp_path / "again"), "--no-live"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    first = cut_dir(old / "checkpoint", 20) / f"{names[0]}.state"
    assert err == [f"error: cannot resume: {first} has no format version; this build reads version 1 "
                   f"(it was written by another version of neoslam)"]
    # exporting its state as a map says so too
    assert main(["map", "export", str(old), "--out", str(tmp_path / "site.neoslam")]) == 1
    assert "has no format version; this build reads version 1" in capsys.readouterr().err


def test_the_supervisor_does_not_restart_a_worker_that_refused_its_state(tmp_path, monkeypatch):
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import RunError, Supervisor
    from neoslam_stream.runtime.worker import EXIT_STATE_REFUSED

    cfg = load_config("default")
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "run")

    class Exited:
        exitcode = EXIT_STATE_REFUSED

        def is_alive(self):
            return False

    sup.children.procs["D"] = Exited()
    restarted = []
    monkeypatch.setattr(sup.children, "alive_tokens", lambda: set())
    monkeypatch.setattr(sup.children, "restart", lambda *a: restarted.append(a))
    with pytest.raises(RunError, match="refused the saved state"):
        sup.children.wait_ready(["D"], timeout=5)
    assert restarted == []


# ------------------------------------------------------------------------------ the end of a run
class WatcherNode(Node):
    """A watcher whose flush (the recorder's: writing its files) notes which final states were
    already on disk when it began."""

    inputs = ("probe",)
    outputs = ()
    observer = True

    def __init__(self, state_dir: str) -> None:
        super().__init__()
        self.state_dir = Path(state_dir)
        self.seen_at_flush: list[str] = []

    def process(self, topic, msg):
        return []

    def flush(self):
        self.seen_at_flush = sorted(p.name for p in self.state_dir.iterdir()) if self.state_dir.exists() else []
        return []


def make_watcher(state_dir: str) -> WatcherNode:
    return WatcherNode(state_dir)


def test_a_worker_saves_what_its_stages_learned_before_its_watcher_writes_files(tmp_path):
    # a watcher's flush may outlast the supervisor's patience on a long run: by then the learned
    # state and the worker's marker must be on disk
    state_dir = tmp_path / "state"
    w = Worker(WorkerSpec(name="probe", stages=[NodeSpec("watcher", f"{__name__}:make_watcher",
                                                         params={"state_dir": str(state_dir)}, observer=True),
                                                NodeSpec("probe", f"{__name__}:make_probe")],
                          run="test-run", run_dir=str(tmp_path), lossless=True))
    w.build()
    w.setup()
    w.bus = FakeBus()  # type: ignore[assignment]
    w.handle("probe", _probe(0), time.time())
    w.publish_stats = lambda final=False: None  # no bus session here
    w.shutdown()
    watcher = next(st.node for st in w.stages if st.name == "watcher")
    assert watcher.seen_at_flush == ["probe.saved", "probe.state"]
    assert (state_dir / "probe.saved").read_text().strip() == '["probe"]'


def _run_folder_with_states(tmp_path: Path, forced: list[str], marked: list[str]) -> Path:
    import json

    from neoslam_stream.runtime.checkpoint import save_state_file

    run = tmp_path / "run"
    for stage in ("B", "pose_cells"):  # the map's worker never got to write experience_map.state
        save_state_file(run / "state" / f"{stage}.state", {"n": 1})
    for worker in marked:
        (run / "state" / f"{worker}.saved").write_text("[]\n")
    (run / "report.json").write_text(json.dumps({
        "workers": {"B": ["B"], "pose_cells": ["pose_cells"], "experience_map": ["experience_map", "recorder"]},
        "stopped_by_force": forced}))
    return run


def test_a_map_is_not_exported_without_the_state_of_a_worker_stopped_before_it_saved(tmp_path):
    from neoslam_stream.runtime.checkpoint import export_map

    run = _run_folder_with_states(tmp_path, forced=["experience_map"], marked=["B", "pose_cells"])
    with pytest.raises(ValueError, match=r"stopped worker experience_map \(stages experience_map, recorder\) "
                                         r"by force .* the map would be incomplete"):
        export_map(run, tmp_path / "m.neoslam")
    assert not (tmp_path / "m.neoslam").exists()
    # a worker stopped by force after it had saved (its marker is there), or none stopped: exported
    for forced, marked in ((["experience_map"], ["experience_map"]), ([], [])):
        run = _run_folder_with_states(tmp_path / f"{forced}{marked}", forced=forced, marked=marked)
        assert export_map(run, tmp_path / "ok.neoslam")["stages"] == ["B", "pose_cells"]
