"""One run over two hosts and a bad link: network namespaces 'robot' (the source, A, B) and
'base' (the router and the rest), joined by a veth pair, through a TCP relay that adds 50 +- 20 ms
(tests/netlab/). The link is taken down for 5 s, the router killed and started again, a host
killed. Needs root (CI runs as root); skipped with its reason where namespaces cannot be made.
The two runs go on at the same time (their waits overlap); bench/hosts.py has the longer set."""

from __future__ import annotations

import filecmp
import multiprocessing as mp
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml
from netlab.netns import netns_unavailable
from netlab.scenario import Faults, SplitResult, run_split, split_config

from neoslam_stream import NeoSLAM, load_config
from neoslam_stream.sources.synthetic import SyntheticWorldSource

pytestmark = [pytest.mark.slow, pytest.mark.zenoh,
              pytest.mark.skipif(netns_unavailable() is not None, reason=str(netns_unavailable()))]

OUTPUTS = ("templates.csv", "trajectory.tum")
LOSSLESS_FRAMES = 80


def _one_host(out: str) -> None:
    """The same frames through the in-process API (the pipeline's bytes: test_default_run.py)."""
    conf = load_config(str(Path(out) / "cfg.yaml"))
    slam = NeoSLAM(conf, run_dir=out)
    for sf in SyntheticWorldSource(**conf.source.params):
        slam.step(sf.image, odometry=sf.odom, stamp=sf.stamp, frame=sf.frame)
    slam.finish()


def _lossless(work: Path) -> tuple[SplitResult, int | None]:
    """Latency all along, and a 5 s outage of the link during which the router is killed and
    started again: the samples on their way are lost, the hosts must find each other again.
    Beside it, the same frames on one host (in a process of its own)."""
    cfg = split_config("lossless", LOSSLESS_FRAMES, 20.0, checkpoint_every=10)
    (work / "one").mkdir(parents=True)
    (work / "one" / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    one = mp.get_context("spawn").Process(target=_one_host, args=(str(work / "one"),))
    one.start()
    try:
        r = run_split(work / "split", cfg, Faults(delay_ms=50, jitter_ms=20, outage_at=5, outage_s=5.0,
                                                   router_restart_in_outage=True), tag=f"l{os.getpid() % 10000}")
        one.join(120)
    finally:
        if one.is_alive():
            one.kill()
    return r, one.exitcode


def _realtime(work: Path) -> SplitResult:
    """Latency, a 5 s outage, then (once frames flow again) the robot's supervisor killed."""
    cfg = split_config("realtime", 400, 20.0, host_timeout=8.0)  # beyond the 5 s outage
    return run_split(work / "split", cfg, Faults(delay_ms=50, jitter_ms=20, outage_at=10, outage_s=5.0,
                                                  robot_kill_at=60), tag=f"r{os.getpid() % 10000}")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    work = tmp_path_factory.mktemp("hosts")
    with ThreadPoolExecutor(2) as ex:
        yield {"lossless": (ex.submit(_lossless, work / "lossless"), work / "lossless"),
               "realtime": ex.submit(_realtime, work / "realtime")}


def _logs(r) -> str:
    return f"robot:\n{r.robot_log[-3000:]}\nbase:\n{r.base_log[-3000:]}"


def test_lossless_over_a_failing_link_equals_a_one_host_run(runs):
    fut, work = runs["lossless"]
    r, one_exit = fut.result(timeout=600)
    assert r.robot_rc == 0 and r.base_rc == 0, _logs(r)
    events = [e for _t, e in r.events]
    assert events.index("link down") < events.index("router killed") < events.index("link up")
    assert r.relay["delay_min_ms"] >= 30 and r.relay["delay_max_ms"] <= 70  # the latency was there
    rep = r.report()
    # every frame processed, none lost
    assert rep["frames_in"] == rep["frames_out"] == LOSSLESS_FRAMES and rep["loss"] == 0.0, rep["loss_breakdown"]
    assert sum(rep["loss_by_cause"].values()) == 0
    # the router's restart lost samples on the way: the run rolled back rather than skip them
    assert rep["rollbacks"] and all(rb["cut"] % 10 == 0 for rb in rep["rollbacks"]), rep["rollbacks"]
    # the report names the outage (both sides saw it) and its length
    assert any(o["length_s"] >= 4.0 and not o.get("host_restarted") for o in rep["outages"]), rep["outages"]
    # the outputs are those of one host, byte for byte
    assert one_exit == 0
    for name in OUTPUTS:
        assert filecmp.cmp(r.base_dir / name, work / "one" / name, shallow=False), name
    assert not r.leftover, r.leftover


def test_realtime_counts_each_lost_frame_once_and_a_dead_host_ends_the_other(runs):
    r = runs["realtime"].result(timeout=600)
    events = [e for _t, e in r.events]
    assert events.index("link up") < events.index("robot killed")
    # processing went on after the link came back
    assert r.resumed_after("link up") is not None
    # the base saw the robot go: it ended by itself, with one line saying what is missing
    assert r.base_rc == 1, _logs(r)
    assert "host 'A,B,source' silent" in r.base_log and "missing A, B, the source" in r.base_log, _logs(r)
    # nothing of the run is left on either host (the killed robot's children went with it)
    assert not r.leftover, r.leftover
    rep = r.report()
    # every lost frame counted once, by cause: the outage cost frames, counted as the link's
    causes = rep["loss_by_cause"]
    assert sum(causes.values()) == rep["frames_lost"] > 0, causes
    assert causes["link"] > 0, causes
    assert any(o["length_s"] >= 4.0 for o in rep["outages"]), rep["outages"]
