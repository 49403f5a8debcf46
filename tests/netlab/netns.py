"""Two test hosts on one machine: network namespaces 'robot' and 'base' joined by a veth pair.

:class:`TwoHosts` makes them (root only), starts processes inside either (``ip netns exec``, each
in its own process group), takes the link down and up, and removes everything again: every
process it started is ended by its own pid (group), then the namespaces are deleted, even when
the caller failed. :func:`netns_unavailable` says why namespaces cannot be made here (or None).
:data:`NETEM` tells whether the kernel has the netem qdisc (delay by ``tc``); most faults come from
the link itself and from relay.py, which work without it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

RELAY = Path(__file__).with_name("relay.py")


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


def netns_unavailable() -> str | None:
    """Why two network namespaces cannot be made here, or None when they can."""
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    name = f"nsl-probe-{os.getpid()}"
    try:
        res = _ip("netns", "add", name, check=False)
        if res.returncode != 0:
            return f"`ip netns add` failed: {res.stderr.strip() or res.returncode}"
    finally:
        _ip("netns", "del", name, check=False)
    return None


def netem_available() -> bool:
    """Whether ``tc qdisc add ... netem`` works on this kernel (tried on a throw-away dummy link)."""
    if os.geteuid() != 0 or shutil.which("tc") is None:
        return False
    dev = f"nslq{os.getpid() % 100000}"
    if _ip("link", "add", dev, "type", "dummy", check=False).returncode != 0:
        return False
    try:
        res = subprocess.run(["tc", "qdisc", "add", "dev", dev, "root", "netem", "delay", "1ms"],
                             capture_output=True, timeout=20)
        return res.returncode == 0
    finally:
        _ip("link", "del", dev, check=False)


class TwoHosts:
    """Namespaces ``robot`` (``ROBOT_IP``) and ``base`` (``BASE_IP``) on one veth link."""

    def __init__(self, tag: str | None = None) -> None:
        tag = tag or str(os.getpid() % 100000)
        self.ns = {"robot": f"nsl-robot-{tag}", "base": f"nsl-base-{tag}"}
        self.dev = {"robot": f"nslr{tag}", "base": f"nslb{tag}"}
        self.ip = {"robot": "10.213.0.1", "base": "10.213.0.2"}
        self.procs: list[subprocess.Popen] = []
        self.events: list[tuple[float, str]] = []

    def __enter__(self) -> TwoHosts:
        try:
            for ns in self.ns.values():
                _ip("netns", "add", ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            _ip("link", "add", self.dev["robot"], "netns", self.ns["robot"], "type", "veth", "peer", "name",
                self.dev["base"], "netns", self.ns["base"])
            for host, ns in self.ns.items():
                _ip("-n", ns, "addr", "add", f"{self.ip[host]}/24", "dev", self.dev[host])
                _ip("-n", ns, "link", "set", self.dev[host], "up")
        except Exception:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def popen(self, host: str, argv: list[str], log: Path | None = None, **kw) -> subprocess.Popen:
        """``argv`` inside ``host``'s namespace, in its own process group; output to ``log``."""
        out = open(log, "ab") if log is not None else subprocess.DEVNULL
        p = subprocess.Popen(["ip", "netns", "exec", self.ns[host], *argv], stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True, **kw)
        self.procs.append(p)
        return p

    def relay(self, host: str, listen: str, to: str, delay_ms: float, jitter_ms: float, stats: Path,
              log: Path | None = None) -> subprocess.Popen:
        """relay.py inside ``host``: ``listen`` -> ``to`` with the given delay (module docstring)."""
        return self.popen(host, [sys.executable, str(RELAY), "--listen", listen, "--to", to, "--delay-ms",
                                 str(delay_ms), "--jitter-ms", str(jitter_ms), "--stats", str(stats)], log)

    def link(self, up: bool) -> None:
        """Take the veth link down (both ends) or bring it up again."""
        state = "up" if up else "down"
        for host, ns in self.ns.items():
            _ip("-n", ns, "link", "set", self.dev[host], state)
        self.events.append((time.time(), f"link {state}"))

    @staticmethod
    def signal(p: subprocess.Popen, sig: int) -> None:
        """Send ``sig`` to ``p``'s process group (the program and its children)."""
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass

    def stop(self, p: subprocess.Popen, timeout: float = 30.0) -> int | None:
        """SIGTERM to ``p``'s group, SIGKILL after ``timeout``; its exit code."""
        self.signal(p, signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            self.signal(p, signal.SIGKILL)
            return p.wait(10)

    def close(self) -> None:
        """End every process started here (its group), then delete the namespaces and the link."""
        for p in self.procs:
            if p.poll() is None:
                self.signal(p, signal.SIGTERM)
        deadline = time.monotonic() + 15
        for p in self.procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for p in self.procs:
            self.signal(p, signal.SIGKILL)  # the group: children that outlived their parent too
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                pass
        for ns in self.ns.values():
            # processes still inside (none should be) would keep the namespace alive: kill them by pid
            res = _ip("netns", "pids", ns, check=False)
            for pid in res.stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", ns, check=False)
