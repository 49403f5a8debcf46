"""One run split over the two test hosts of netns.py, with faults on the link between them.

'robot' runs the source and stages A, B (``neoslam run --stages A,B,source``) and reaches the
router through relay.py (added latency); 'base' runs ``neoslam router`` and the other stages
(``--stages rest``). :func:`run_split` starts them, applies the faults of a :class:`Faults` when
the base's trajectory has reached the given frame counts, waits for both supervisors to end and
returns what happened: exit codes, the last lines of each log, the times of the faults, and when
the base's trajectory grew again after each. Used by tests/test_hosts.py and bench/hosts.py.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .netns import TwoHosts

ROUTER_PORT = 7447
RELAY_PORT = 7500
TOKEN = "netns-test-shared-secret"
LIGHT = {"features": {"backbone": "random_alexnet"}, "projector": {"projection": "sparse"},
         "pose_cells": {"pc_dim_xy": 11}}


def split_config(mode: str, frames: int, rate: float, **run: Any) -> dict[str, Any]:
    """The LIGHT NeoSLAM on small synthetic frames, paced at ``rate`` frames per second (on the
    models' defaults: ``base: none``)."""
    return {"base": "none", "run": {"pipeline": "neoslam", "topology": "pipeline", "mode": mode, "live": False,
                    "startup_timeout": 240, **run},
            "source": {"kind": "synthetic", "params": {"seed": 0, "frames": frames, "width": 160, "height": 96},
                       "rate": rate, "pacing": "fixed"}, **LIGHT}


@dataclass
class Faults:
    """What to do to the run, each once the base's trajectory holds ``at`` rows."""

    outage_at: int | None = None
    outage_s: float = 5.0
    #: kill the router 1 s into the outage and start it again 1 s later (both faults in one window)
    router_restart_in_outage: bool = False
    router_restart_at: int | None = None
    #: the relay holds every byte for ``outage_s`` (the link stalls, its connections stay up)
    stall_at: int | None = None
    base_restart_at: int | None = None
    robot_kill_at: int | None = None
    base_kill_at: int | None = None
    delay_ms: float = 0.0
    jitter_ms: float = 0.0


@dataclass
class SplitResult:
    robot_rc: int | None
    base_rc: int | None
    robot_log: str
    base_log: str
    robot_dir: Path
    base_dir: Path
    events: list[tuple[float, str]] = field(default_factory=list)
    #: (time, rows of the base's trajectory.tum), sampled while the run went on
    rows: list[tuple[float, int]] = field(default_factory=list)
    relay: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    #: per host, the processes still in its namespace once both supervisors had ended (the router
    #: and the relay, which the harness runs, left out)
    leftover: dict[str, list[str]] = field(default_factory=dict)

    def report(self) -> dict[str, Any]:
        return json.loads((self.base_dir / "report.json").read_text())

    def resumed_after(self, what: str) -> float | None:
        """Seconds from the (last) event ``what`` to the next growth of the base's trajectory."""
        times = [t for t, e in self.events if e == what]
        if not times:
            return None
        t0 = times[-1]
        before = max([n for t, n in self.rows if t <= t0] or [0])
        for t, n in self.rows:
            if t > t0 and n > before:
                return t - t0
        return None


def _rows(path: Path) -> int:
    try:
        with open(path, "rb") as fh:
            return sum(1 for line in fh if line.strip())
    except OSError:
        return 0


def _tail(path: Path, n: int = 4000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


def _kill_router(hosts: TwoHosts, rtr: Any) -> Any:
    hosts.signal(rtr, signal.SIGKILL)
    rtr.wait(10)
    hosts.events.append((time.time(), "router killed"))
    return rtr


def _leftover(hosts: TwoHosts, ours: set[int], wait_s: float = 5.0) -> dict[str, list[str]]:
    """Command lines of the processes left in each namespace (other than ``ours``), after giving
    the children of an ended supervisor ``wait_s`` to go."""
    import subprocess

    deadline = time.monotonic() + wait_s
    while True:
        left: dict[str, list[str]] = {}
        for host, ns in hosts.ns.items():
            pids = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split()
            for pid in pids:
                if int(pid) in ours:
                    continue
                try:
                    if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                        continue  # exited, not yet reaped by whoever inherited it
                    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200]
                except (OSError, IndexError):
                    continue
                left.setdefault(host, []).append(cmd)
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.2)


def run_split(tmp: Path, cfg: dict[str, Any], faults: Faults, timeout: float = 400.0,
              robot_stages: str = "A,B,source", tag: str | None = None) -> SplitResult:
    """Run ``cfg`` over robot and base (module docstring) with ``faults``; everything started is
    ended and the namespaces deleted before this returns, whatever happened. ``tag`` names the
    namespaces (runs at the same time need different tags)."""
    tmp = Path(tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    robot_dir, base_dir = tmp / "robot", tmp / "base"
    env = {**os.environ, "NEOSLAM_CONTROL_TOKEN": TOKEN}
    cli = [sys.executable, "-m", "neoslam_stream.cli"]
    t_start = time.time()
    with TwoHosts(tag) as hosts:
        router_ep = f"tcp/{hosts.ip['base']}:{ROUTER_PORT}"

        def router() -> Any:
            p = hosts.popen("base", [*cli, "router", "--listen", router_ep], tmp / "router.log", env=env)
            hosts.events.append((time.time(), "router started"))
            return p

        def share(host: str, stages: str, run_dir: Path, *extra: str) -> Any:
            connect = f"tcp/127.0.0.1:{RELAY_PORT}" if host == "robot" else router_ep
            return hosts.popen(host, [*cli, "run", "-c", str(tmp / "cfg.yaml"), "--out", str(run_dir),
                                      "--stages", stages, "--run-id", "hosts", "--connect", connect, *extra],
                               tmp / f"{host}.log", env=env)

        rtr = router()
        relay = hosts.relay("robot", f"127.0.0.1:{RELAY_PORT}", f"{hosts.ip['base']}:{ROUTER_PORT}",
                            faults.delay_ms, faults.jitter_ms, tmp / "relay.json", tmp / "relay.log")
        robot = share("robot", robot_stages, robot_dir)
        base = share("base", "rest", base_dir)
        result = SplitResult(None, None, "", "", robot_dir, base_dir, hosts.events)
        todo = {k: getattr(faults, f"{k}_at") for k in ("outage", "stall", "router_restart", "base_restart",
                                                         "robot_kill", "base_kill")}
        deadline = time.monotonic() + timeout
        try:
            while time.monotonic() < deadline:
                n = _rows(base_dir / "trajectory.tum")
                result.rows.append((time.time(), n))
                for what, at in list(todo.items()):
                    if at is None or n < at:
                        continue
                    del todo[what]
                    if what == "outage":
                        hosts.link(False)
                        t_down = time.monotonic()
                        router_down = False
                        while time.monotonic() < t_down + faults.outage_s:
                            result.rows.append((time.time(), _rows(base_dir / "trajectory.tum")))
                            if faults.router_restart_in_outage and not router_down and \
                                    time.monotonic() > t_down + 1.0:
                                rtr = _kill_router(hosts, rtr)
                                router_down = True
                            if router_down and rtr.poll() is not None and time.monotonic() > t_down + 2.0:
                                rtr = router()
                            time.sleep(0.05)
                        hosts.link(True)
                    elif what == "stall":
                        hosts.signal(relay, signal.SIGUSR1)
                        hosts.events.append((time.time(), "relay stalled"))
                        t_end = time.monotonic() + faults.outage_s
                        while time.monotonic() < t_end:
                            result.rows.append((time.time(), _rows(base_dir / "trajectory.tum")))
                            time.sleep(0.05)
                        hosts.signal(relay, signal.SIGUSR2)
                        hosts.events.append((time.time(), "relay released"))
                    elif what == "router_restart":
                        rtr = _kill_router(hosts, rtr)
                        time.sleep(1.0)
                        rtr = router()
                    elif what == "base_restart":
                        hosts.signal(base, signal.SIGKILL)
                        base.wait(30)
                        hosts.events.append((time.time(), "base killed"))
                        base = share("base", "rest", base_dir, "--resume", str(base_dir))
                        hosts.events.append((time.time(), "base restarted"))
                    elif what in ("robot_kill", "base_kill"):
                        victim = robot if what == "robot_kill" else base
                        hosts.signal(victim, signal.SIGKILL)
                        victim.wait(30)
                        hosts.events.append((time.time(), what.replace("_", " ") + "ed"))
                if robot.poll() is not None and base.poll() is not None:
                    break
                time.sleep(0.05)
            result.robot_rc, result.base_rc = robot.poll(), base.poll()
            result.leftover = _leftover(hosts, {rtr.pid, *(p.pid for p in hosts.procs if "relay.py" in str(p.args))})
        finally:
            for p in (robot, base):
                if p.poll() is None:
                    hosts.stop(p, 60)
            for p in list(hosts.procs):
                if p.poll() is None:
                    hosts.stop(p, 10)
    result.robot_log = _tail(tmp / "robot.log")
    result.base_log = _tail(tmp / "base.log")
    result.wall_s = time.time() - t_start
    try:
        result.relay = json.loads((tmp / "relay.json").read_text())
    except (OSError, ValueError):
        pass
    return result
