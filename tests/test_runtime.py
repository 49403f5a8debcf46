"""The runtime end to end through real processes and real zenoh on loopback."""

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
from runhelpers import attach, finish, start_run, wait_stats

from neoslam_stream.config import ConfigError, load_config
from neoslam_stream.launch import run
from neoslam_stream.runtime.bus import key_for
from neoslam_stream.runtime.messages import Message, encode

pytestmark = pytest.mark.zenoh

TAUS = [50.0, 280.0, 20.0, 350.0]
RATE = 10.0


@pytest.mark.parametrize("topology", ["pipeline", "monolithic"])
def test_emulated_paper_example(tmp_path, topology):
    """The paper's worked example: eq. 2 predicts the output rate and the loss of each design."""
    duration = 12.0
    cfg = load_config(None, {
        "run": {"pipeline": "emulated", "topology": topology, "mode": "realtime", "live": False,
                "drain_s": 0.0},
        "source": {"kind": "emulated", "rate": RATE, "pacing": "fixed", "duration": duration},
        "emulated": {"tau_ms": TAUS}, "bus": {"capacity": {"image": 1}}})
    report = run(cfg, tmp_path).report
    # expectations from the paper's equations, not from the code
    if topology == "pipeline":
        f_expected = 1.0 / (max(TAUS) / 1e3)  # min_i 1/tau_i
        bottleneck = "stage4"
    else:
        f_expected = 1.0 / (sum(TAUS) / 1e3)  # one process serves the stages in sequence
        bottleneck = "monolithic"
    loss_expected = 1.0 - f_expected / RATE
    assert report["topology"] == topology
    assert report["f_in"] == pytest.approx(RATE, rel=0.05)
    assert report["f_out"] == pytest.approx(f_expected, rel=0.05)
    assert report["loss"] == pytest.approx(loss_expected, rel=0.05)
    assert report["f_pipeline_predicted"] == pytest.approx(f_expected, rel=0.05)
    assert report["predicted_loss"] == pytest.approx(loss_expected, rel=0.05)
    assert report["bottleneck"] == bottleneck
    for key in ("frames_in", "frames_out", "latency_p50_ms", "stages"):
        assert key in report
    # what the host did over the run: the CPU seconds the hypervisor took, from /proc/stat
    assert report["host"]["cpus"] == os.cpu_count() and report["host"]["steal_s"] >= 0
    assert (tmp_path / "timeline.csv").read_text().startswith("t_s,stage")


def test_bad_config_names_the_field(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("run:\n  topology: ring\n")
    with pytest.raises(ConfigError, match=r"run\.topology"):
        load_config(bad)
    bad.write_text("bus:\n  capacity: {image: 0}\n")
    with pytest.raises(ConfigError, match=r"bus\.capacity"):
        load_config(bad)
    bad.write_text("nonsense: 1\n")
    with pytest.raises(ConfigError, match="nonsense"):
        load_config(bad)


def test_the_plan_gives_every_process_its_topics_capacities_and_source(tmp_path):
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.config import DEFAULT_CAPACITY
    from neoslam_stream.runtime.topology import RunError, Supervisor

    assert set(DEFAULT_CAPACITY) == {"odom", "groundtruth"}  # the runtime's own topics only
    cfg = load_config("default", {"run": {"live": False}})
    plan = build_plan(cfg)
    assert plan.final_topic == "experience_map/pose" and "pose_cells/action" in plan.topics
    sup = Supervisor(cfg, plan, tmp_path / "a", source_factory="pkg.cam:Camera")
    for spec in [sup.layout.worker_spec(w) for w in sup.layout.groups] + [sup.layout.monitor_spec(), sup.layout.source_spec()]:
        assert [str(t) for t in spec.topics] == [str(t) for t in plan.topics]
    assert sup.layout.source_spec().source.factory == "pkg.cam:Camera"
    assert sup.layout.source_spec().final_topic == "experience_map/pose"
    # the back end's actions queue deep unless bus.capacity names them
    assert sup.layout.worker_spec("experience_map").capacities["pose_cells/action"] == 256
    # before and after a batching stage (A, B) a ring holds a whole batch of run.max_batch frames,
    # and after C, which turns B's batch into a burst of as many SDRs
    # the image ring before A: a batch in a real-time run, the default queue in a lossless one
    assert sup.layout.worker_spec("A").capacities.get("image", cfg.bus.default_capacity) == cfg.bus.default_capacity
    live = load_config("default", {"run": {"live": False, "mode": "realtime"}})
    assert Supervisor(live, build_plan(live), tmp_path / "r").layout.worker_spec("A").capacities["image"] == \
        live.run.max_batch
    assert sup.layout.worker_spec("B").capacities["visual_features"] == cfg.run.max_batch
    assert sup.layout.worker_spec("C").capacities["bin_features"] == cfg.run.max_batch
    assert sup.layout.worker_spec("D").capacities["sdr"] == cfg.run.max_batch
    one = load_config("default", {"run": {"live": False, "max_batch": 1}, "bus": {"capacity": {"bin_features": 3}}})
    sup1 = Supervisor(one, build_plan(one), tmp_path / "one")
    assert sup1.layout.worker_spec("B").capacities["visual_features"] == one.bus.default_capacity  # no batch: 2
    assert sup1.layout.worker_spec("D").capacities["sdr"] == one.bus.default_capacity
    assert sup1.layout.worker_spec("C").capacities["bin_features"] == 3  # bus.capacity names it: it wins
    # the monolithic process keeps the newest frames (the original design), not a batch, unless
    # bus.capacity names the image ring
    mono = load_config("default", {"run": {"live": False, "topology": "monolithic", "mode": "realtime"}})
    assert Supervisor(mono, build_plan(mono), tmp_path / "m").layout.worker_spec("monolithic").capacities.get(
        "image", mono.bus.default_capacity) == mono.bus.default_capacity
    named = load_config("default", {"run": {"live": False, "mode": "realtime"}, "bus": {"capacity": {"image": 3}}})
    assert Supervisor(named, build_plan(named), tmp_path / "n").layout.worker_spec("A").capacities["image"] == 3
    # the throughput bench reports the ring each run had
    from neoslam_stream.throughput import image_capacity

    assert image_capacity(live, "pipeline") == live.run.max_batch and image_capacity(named, "pipeline") == 3
    assert image_capacity(mono, "monolithic") == mono.bus.default_capacity
    cfg = load_config("default", {"run": {"live": False}, "bus": {"capacity": {"pose_cells/action": 7}}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "b")
    assert sup.layout.worker_spec("experience_map").capacities["pose_cells/action"] == 7
    with pytest.raises(RunError, match="no factory given for the source kind 'synthetic'"):
        sup.layout.source_spec()


# ---------------------------------------------------------------------------------------------
def _start_run(tmp_path: Path, frames: int, rate: float, taus: list[float], mode: str = "lossless",
               extra: dict | None = None) -> subprocess.Popen:
    cfg = {"run": {"pipeline": "emulated", "topology": "pipeline", "mode": mode, "live": False,
                   "startup_timeout": 120},
           "source": {"kind": "emulated", "params": {"frames": frames}, "rate": rate, "pacing": "fixed"},
           "emulated": {"tau_ms": taus}}
    if extra:
        for k, v in extra.items():
            cfg.setdefault(k, {}).update(v)
    return start_run(tmp_path, cfg)


def _attach(tmp_path: Path, timeout: float = 240.0):
    return attach(tmp_path / "run", timeout)


_wait_stats = wait_stats
_finish = finish


def test_malformed_payload_is_counted_and_skipped(tmp_path):
    frames = 60
    proc = _start_run(tmp_path, frames=frames, rate=20.0, taus=[5.0, 5.0])
    session, run_id = _attach(tmp_path)
    try:
        _wait_stats(session, run_id, "stage1")
        key = key_for(run_id, "image")
        session.put(key, b"\x00garbage")  # not msgpack
        session.put(key, encode(Message("control", 0, 0.0, {"command": "noop"})))  # wrong type for a stage
        session.put(key, encode(Message("image", 10**6, 0.0, {"image": np.zeros((2, 2, 2, 2), np.uint8)}),
                                validate=False))  # wrong shape
        # a type no process of the run registered: refused, never passed on unchecked. Put once
        # stage2 is up (its first stats follow its subscriptions): the workers start in parallel,
        # and a sample put before stage2 subscribed reaches nobody
        _wait_stats(session, run_id, "stage2")
        unregistered = encode(Message("nobody_registered", 7, 0.0, {"x": 1}), validate=False)
        for _ in range(5):  # until stage2 says it refused it (a sample can be lost on the way)
            session.put(key_for(run_id, "emulated/1"), unregistered)
            try:
                _wait_stats(session, run_id, "stage2", timeout=2.0,
                            until=lambda d: any("nobody_registered" in c for c in d.get("error_causes", {})))
                break
            except AssertionError:
                continue
    finally:
        session.close()
    out = _finish(proc)
    assert proc.returncode == 0, out
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    s1 = report["stages"]["stage1"]
    assert s1["errors"] >= 2, s1  # the garbage and the 4-D image (the control msg has no schema issue)
    assert any("MessageError" in c for c in s1["error_causes"])
    s2 = report["stages"]["stage2"]
    assert any("'nobody_registered' has no registered schema" in c for c in s2["error_causes"]), s2
    # every real frame still went through
    assert report["frames_in"] == frames
    assert report["frames_out"] == frames
    assert report["loss"] == 0.0


def test_sigkilled_worker_is_restarted_and_run_completes(tmp_path):
    frames = 120
    proc = _start_run(tmp_path, frames=frames, rate=20.0, taus=[5.0, 5.0, 5.0], mode="realtime")
    session, run_id = _attach(tmp_path)
    try:
        _wait_stats(session, run_id, "source", until=lambda st: st.get("frames_in", 0) > 0)  # under way
        st = _wait_stats(session, run_id, "stage2")
        time.sleep(1.0)
        os.kill(st["pid"], signal.SIGKILL)
    finally:
        session.close()
    out = _finish(proc)
    assert proc.returncode == 0, out
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["restarts"] == {"stage2": 1}
    assert report["frames_in"] == frames
    # the run went on after the restart: the last stage saw frames after the kill
    assert report["stages"]["stage3"]["processed"] > 0
    assert report["frames_out"] > 0


def test_sigint_stops_everything_and_writes_the_report(tmp_path):
    proc = _start_run(tmp_path, frames=100000, rate=20.0, taus=[5.0, 5.0], mode="realtime")
    session, run_id = _attach(tmp_path)
    try:
        _wait_stats(session, run_id, "stage2", until=lambda st: st.get("processed", 0) > 0)
    finally:
        session.close()
    children = psutil.Process(proc.pid).children(recursive=True)
    assert len(children) >= 4  # monitor, 2 workers, source
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _finish(proc, timeout=300)
    assert proc.returncode == 130
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["interrupted"] is True
    assert report["frames_in"] > 0 and report["stages"]["stage2"]["processed"] > 0
    time.sleep(0.5)
    alive = [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
    assert alive == [], f"orphans left: {alive}"
