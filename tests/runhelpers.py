"""Helpers for tests that drive ``neoslam run`` as a real child process and attach to its zenoh."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from neoslam_stream.runtime.bus import key_for, open_session
from neoslam_stream.runtime.messages import decode

#: the cheapest real NeoSLAM: random AlexNet (no weights to load), sparse projection (no 265 MB
#: matrix), small pose-cell network
LIGHT = {"features": {"backbone": "random_alexnet"}, "projector": {"projection": "sparse"},
         "pose_cells": {"pc_dim_xy": 11}}


def light_config(mode: str, source: dict, **run: Any) -> dict:
    """A run config of the LIGHT NeoSLAM pipeline in ``mode`` on ``source`` (``run`` overrides), on
    the models' defaults (``base: none``), not on the shipped default."""
    return {"base": "none", "run": {"pipeline": "neoslam", "topology": "pipeline", "mode": mode, "live": False,
                    "startup_timeout": 240, **run},
            "source": source, **LIGHT}


def read_report(run_dir: Path) -> dict:
    return json.loads((run_dir / "report.json").read_text())


def start_run(tmp_path: Path, cfg: dict[str, Any], *args: str, run_dir: Path | None = None) -> subprocess.Popen:
    """``neoslam run -c <cfg> --out <run_dir> [args]`` in a child process (output captured)."""
    path = tmp_path / f"cfg-{time.monotonic_ns()}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    run_dir = run_dir or tmp_path / "run"
    return subprocess.Popen([sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(path), "--out",
                             str(run_dir), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def attach(run_dir: Path, timeout: float = 240.0):
    """A client zenoh session on the run's router, and the run id (waits for endpoints.json)."""
    ep_file = Path(run_dir) / "endpoints.json"
    deadline = time.monotonic() + timeout
    while not ep_file.exists():
        assert time.monotonic() < deadline, "run did not start"
        time.sleep(0.1)
    ep = json.loads(ep_file.read_text())
    session = open_session(listen=[], connect=ep["connect"], mode="client")
    time.sleep(0.5)
    return session, ep["run"]


def wait_stats(session, run_id: str, stage: str, timeout: float = 240.0, until=None) -> dict:
    """The first stats of ``stage`` (for which ``until(stats)`` holds, when given)."""
    got: dict[str, Any] = {}

    def on(sample):
        data = decode(sample.payload.to_bytes()).data
        if until is None or until(data):
            got.update(data)

    sub = session.declare_subscriber(key_for(run_id, f"stats/{stage}"), on)
    deadline = time.monotonic() + timeout
    while not got and time.monotonic() < deadline:
        time.sleep(0.05)
    sub.undeclare()
    assert got, f"no stats from {stage}"
    return got


def finish(proc: subprocess.Popen, timeout: float = 400.0) -> str:
    out, _ = proc.communicate(timeout=timeout)
    return out


#: the synthetic world looped at 10 FPS in real time: a run that goes on until it is stopped
LOOPING_10FPS = {"kind": "synthetic", "params": {"seed": 0, "loop": True}, "rate": 10.0, "pacing": "fixed"}


def start_looping_run(tmp_path: Path, processed: int) -> tuple[subprocess.Popen, list]:
    """A real-time LIGHT run on :data:`LOOPING_10FPS` in ``tmp_path/run``, returned once its
    experience map has processed ``processed`` actions, with the run's child processes then."""
    import psutil

    proc = start_run(tmp_path, light_config("realtime", LOOPING_10FPS))
    session, run_id = attach(tmp_path / "run")
    try:
        wait_stats(session, run_id, "experience_map", until=lambda s: s.get("processed", 0) >= processed)
    finally:
        session.close()
    return proc, psutil.Process(proc.pid).children(recursive=True)


def still_running(processes: list) -> list:
    """The psutil processes of ``processes`` that run (neither exited nor zombies)."""
    import psutil

    alive = []
    for p in processes:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                alive.append(p)
        except psutil.NoSuchProcess:
            pass
    return alive
