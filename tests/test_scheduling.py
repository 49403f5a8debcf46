"""run.nice and run.cpus: each process's niceness and CPUs, and its name in top/ps."""

import json
import os
import subprocess
import sys

import pytest

from neoslam_stream import load_config
from neoslam_stream.config import ConfigError


def _in_child(name, nice, cpus):
    code = ("import json, os; from neoslam_stream.runtime.procs import apply_scheduling; "
            f"before = os.nice(0); problems = apply_scheduling({name!r}, {nice}, {cpus!r}); "
            "print(json.dumps({'comm': open('/proc/self/comm').read().strip(), 'raised': os.nice(0) - before, "
            "'cpus': sorted(os.sched_getaffinity(0)), 'problems': problems}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    return json.loads(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and sched_setaffinity are Linux's")
def test_a_process_gets_its_name_niceness_and_cpus():
    cpu = min(os.sched_getaffinity(0))
    got = _in_child("A", 5, [cpu])
    assert got == {"comm": "neoslam-A", "raised": 5, "cpus": [cpu], "problems": []}
    # a CPU this machine lacks: the process runs where it may, and says why
    everywhere = sorted(os.sched_getaffinity(0))
    got = _in_child("experience_map", 0, [4095])
    assert got["comm"] == "neoslam-experie" and got["raised"] == 0 and got["cpus"] == everywhere
    assert len(got["problems"]) == 1 and "CPUs [4095] refused" in got["problems"][0]


@pytest.mark.parametrize("run,message", [
    ({"nice": {"A": -1}}, "niceness must lie in 0..19"),
    ({"nice": {"C": 20}}, "niceness must lie in 0..19"),
    ({"cpus": {"A": []}}, "non-empty lists of CPU numbers"),
    ({"cpus": {"A": [-1]}}, "non-empty lists of CPU numbers"),
])
def test_bad_scheduling_settings_are_refused_by_the_config(run, message):
    with pytest.raises(ConfigError, match=message):
        load_config("default", {"run": run})


def test_the_supervisor_hands_each_process_its_settings(tmp_path):
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.topology import Supervisor

    run = {"nice": {"C": 10, "D": 4, "monitor": 15}, "cpus": {"A": [0], "C": [1], "D": [0]}}
    cfg = load_config("default", {"run": run})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "pipeline")
    assert sup.layout.scheduling("A") == {"nice": 0, "cpus": [0]}
    assert sup.layout.scheduling("C") == {"nice": 10, "cpus": [1]}
    assert sup.layout.scheduling("B") == {"nice": 0, "cpus": []}
    assert sup.layout.scheduling("monitor") == {"nice": 15, "cpus": []}
    assert sup.layout.scheduling("source") == {"nice": 0, "cpus": []}
    # one process for every stage: the lowest niceness of its stages (0 for those not named), the
    # union of their CPUs (any CPU when one of them is not restricted)
    cfg = load_config("default", {"run": {**run, "topology": "monolithic"}})
    sup = Supervisor(cfg, build_plan(cfg), tmp_path / "monolithic")
    assert sup.layout.scheduling("monolithic") == {"nice": 0, "cpus": []}
    cfg = load_config("default", {"run": {"topology": "monolithic", "cpus": {"monolithic": [1]}}})
    assert Supervisor(cfg, build_plan(cfg), tmp_path / "m1").layout.scheduling("monolithic") == {"nice": 0, "cpus": [1]}
    cfg = load_config("default", {"run": {**run, "topology": "monolithic", "nice": {"monolithic": 3}}})
    assert Supervisor(cfg, build_plan(cfg), tmp_path / "m2").layout.scheduling("monolithic")["nice"] == 3


def test_bus_tx_queue_reaches_every_process_config(tmp_path, monkeypatch):
    from neoslam_stream.nodes.pipelines import build_plan
    from neoslam_stream.runtime.bus import ZENOH_TX_QUEUE_ENV, make_config
    from neoslam_stream.runtime.topology import Supervisor

    monkeypatch.delenv(ZENOH_TX_QUEUE_ENV, raising=False)
    assert json.loads(make_config().get_json("transport/link/tx/queue/size"))["data"] == 2  # zenoh's own
    cfg = load_config("default", {"bus": {"tx_queue": 5}})
    Supervisor(cfg, build_plan(cfg), tmp_path / "a").export_bus_settings()
    assert json.loads(make_config().get_json("transport/link/tx/queue/size"))["data"] == 5
    cfg = load_config("default")  # the shipped default: 16 batches
    Supervisor(cfg, build_plan(cfg), tmp_path / "b").export_bus_settings()
    assert json.loads(make_config().get_json("transport/link/tx/queue/size"))["data"] == 16
    cfg = load_config("default", {"bus": {"tx_queue": None}})  # a later run without it: zenoh's own again
    Supervisor(cfg, build_plan(cfg), tmp_path / "c").export_bus_settings()
    assert json.loads(make_config().get_json("transport/link/tx/queue/size"))["data"] == 2
    for bad in (0, 65):
        with pytest.raises(ConfigError, match="tx_queue"):
            load_config("default", {"bus": {"tx_queue": bad}})


def test_thread_budget_after_numba_was_loaded_still_compiles(tmp_path):
    """A spawn child may have loaded numba (its parent's script imported the package) before the
    budget is set; a first, uncached compilation under the new budget must still work."""
    code = ("import numba; from neoslam_stream.runtime.procs import set_thread_budget; "
            "set_thread_budget(1); numba.set_num_threads(1); "
            "f = numba.njit(lambda x: x + 1); print(f(1), numba.config.NUMBA_NUM_THREADS)")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_NUM_THREADS"}
    env["NUMBA_CACHE_DIR"] = str(tmp_path)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["2", "1"]
