"""One run over several hosts (``neoslam run --stages ...``): here two supervisors on one machine
that reach each other only through a zenoh router on loopback."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from neoslam_stream.config import load_config
from neoslam_stream.nodes.pipelines import build_plan
from neoslam_stream.runtime.bus import free_port
from neoslam_stream.runtime.parts import PartSupervisor, check_selection, parse_stages
from neoslam_stream.runtime.topology import RunError, group_workers

FRAMES = 30
TINY = {"run": {"pipeline": "neoslam", "topology": "pipeline", "mode": "lossless", "live": False,
                "startup_timeout": 240},
        "source": {"kind": "synthetic", "params": {"seed": 0, "frames": FRAMES}},
        "features": {"backbone": "random_alexnet"}, "projector": {"projection": "sparse"},
        "pose_cells": {"pc_dim_xy": 11}}


def test_stage_lists_are_parsed_and_checked():
    assert parse_stages("A, B") == ["A", "B"]
    assert parse_stages("rest") == ["rest"]
    for bad in ("", "rest,A"):
        with pytest.raises(ValueError):
            parse_stages(bad)
    groups = group_workers(build_plan(load_config("default")), "pipeline")
    assert check_selection(groups, ["B", "A"]) == ["A", "B"]  # the plan's order
    with pytest.raises(RunError, match="unknown stage"):
        check_selection(groups, ["A", "Z"])
    with pytest.raises(RunError, match="experience_map"):  # the recorder is no process of its own
        check_selection(groups, ["recorder"])


def test_a_part_needs_a_run_id_and_the_pipeline_topology(tmp_path):
    cfg = load_config("default", {"run": {"stages": ["A"]}})
    with pytest.raises(RunError, match="--run-id"):
        PartSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    cfg = load_config("default", {"run": {"stages": ["A"], "run_id": "x1", "topology": "monolithic"}})
    with pytest.raises(RunError, match="pipeline topology"):
        PartSupervisor(cfg, build_plan(cfg), tmp_path / "b")


def test_only_the_supervisors_router_links_to_other_hosts(tmp_path):
    # bus.connect names the router between hosts: the supervisor's session connects to it, no
    # other process does (zenoh routes between peers of linked routers, not between peers that
    # merely share a router), and no process links to another host's processes
    cfg = load_config("default", {"run": {"stages": ["A", "B"], "run_id": "x2"},
                                  "bus": {"connect": ["tcp/127.0.0.1:7"]}})
    sup = PartSupervisor(cfg, build_plan(cfg), tmp_path / "a")
    sup.order = ["supervisor", *sup.hosted]  # as _select_hosted sets it for a part without the source
    for w in sup.hosted:
        spec = sup.worker_spec(w)
        assert "tcp/127.0.0.1:7" not in spec.connect
        assert set(spec.connect) <= {sup.endpoints[n] for n in sup.order}
        assert spec.expected_peers == sup.order.index(w)


def _start(tmp_path: Path, name: str, *args: str) -> subprocess.Popen:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(TINY))
    return subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(cfg),
                             "--out", str(tmp_path / name), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.mark.zenoh
@pytest.mark.slow
def test_two_hosts_through_a_router_make_one_lossless_run(tmp_path):
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "router", "--listen",
                               f"tcp/127.0.0.1:{port}", "--duration", "500"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    link = ["--run-id", "twohosts", "--connect", f"tcp/127.0.0.1:{port}"]
    try:
        time.sleep(1.0)
        front = _start(tmp_path, "front", "--stages", "A,B", *link)
        back = _start(tmp_path, "back", "--stages", "rest", *link)
        out_back, _ = back.communicate(timeout=500)
        out_front, _ = front.communicate(timeout=120)
    finally:
        router.terminate()
        router.wait(10)
        for p in (locals().get("front"), locals().get("back")):
            if p is not None and p.poll() is None:
                p.kill()
    assert back.returncode == 0, out_back[-3000:]
    assert front.returncode == 0, out_front[-3000:]
    # the front host ran A and B only; the back end host ran the rest, the source and the monitor
    part = json.loads((tmp_path / "front" / "part.json").read_text())
    assert part["part"] == ["A", "B"] and part["restarts"] == {}
    assert not (tmp_path / "front" / "report.json").exists()
    report = json.loads((tmp_path / "back" / "report.json").read_text())
    assert report["hosted_here"] == ["C", "D", "pose_cells", "experience_map"]
    # the monitor saw every stage, wherever it ran, and nothing was lost
    for stage in ("A", "B", "C", "D", "pose_cells", "experience_map", "recorder"):
        assert not report["stages"][stage].get("missing"), stage
    for stage in ("A", "B", "C", "D", "experience_map"):
        assert report["stages"][stage]["processed"] == FRAMES, stage
    assert report["frames_in"] == report["frames_out"] == FRAMES and report["loss"] == 0.0
    # every frame has its template and its pose
    with (tmp_path / "back" / "templates.csv").open() as f:
        assert [int(r["frame"]) for r in csv.DictReader(f)] == list(range(FRAMES))
    rows = [r for r in (tmp_path / "back" / "trajectory.tum").read_text().splitlines() if r.strip()]
    assert len(rows) == FRAMES
