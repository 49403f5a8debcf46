"""Free TCP ports for a run's processes, never handed to two of them.

Each worker of a run listens on its own loopback port, chosen by the supervisor before the worker
starts and bound by the worker during its start-up. Between the two, the port must not go to
anything else: not to an outgoing connection (the ports are drawn below the OS's ephemeral range),
not to another worker of this process (``_ISSUED_PORTS``), and not to a worker of another run
starting at the same time on this machine (a registry file in the temporary folder, under an
exclusive lock, that every process of the user consults and extends).
"""

from __future__ import annotations

import os
import random
import socket
import time
from pathlib import Path

from .files import write_all

_ISSUED_PORTS: set[int] = set()
#: a port handed out by any process of this user on this machine stays reserved this long: the
#: worker it was meant for binds it within its start-up (a run that cannot start in that time
#: has failed anyway), after which the bind check below sees it taken
PORT_RESERVE_S = 300.0


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _port_registry() -> Path:
    """The file in which the processes of this user on this machine note the ports they hand out."""
    import tempfile

    uid = os.getuid() if hasattr(os, "getuid") else 0
    return Path(tempfile.gettempdir()) / f"neoslam_stream-ports-{uid}"


class _Registry:
    """The ports other processes handed out lately (``PORT_RESERVE_S``), under an exclusive lock
    on the registry file for as long as the ``with`` lasts; ``add`` notes one for the others.
    Where the file cannot be used (no fcntl, a read-only temporary folder) it holds nothing and
    notes nothing: this process's own set still applies."""

    def __enter__(self) -> _Registry:
        self.fd: int | None = None
        self.recent: dict[int, float] = {}
        try:
            import fcntl

            self.fd = os.open(_port_registry(), os.O_RDWR | os.O_CREAT, 0o600)
            fcntl.flock(self.fd, fcntl.LOCK_EX)
            now = time.time()
            for line in os.read(self.fd, 1 << 20).decode(errors="replace").splitlines():
                fields = line.split()
                if len(fields) == 2 and fields[0].isdigit():
                    try:
                        t = float(fields[1])
                    except ValueError:
                        continue
                    if now - PORT_RESERVE_S < t <= now + 1.0:
                        self.recent[int(fields[0])] = t
        except (ImportError, OSError):
            self._close()
        return self

    def add(self, port: int) -> None:
        self.recent[port] = time.time()
        if self.fd is None:
            return
        try:
            data = "".join(f"{p} {t:.3f}\n" for p, t in self.recent.items()).encode()
            os.lseek(self.fd, 0, os.SEEK_SET)
            os.ftruncate(self.fd, 0)
            write_all(self.fd, data)
        except OSError:
            pass

    def _close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # releases the lock
            self.fd = None

    def __exit__(self, *exc: object) -> None:
        self._close()


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now and not handed out lately, by this process
    or by another process of this user on this machine (``PORT_RESERVE_S``).

    Picked below the OS's ephemeral range: a port the OS chose for us (bind to 0) is an ephemeral
    one, and any outgoing connection (a zenoh link, a browser) may take it as its local port in the
    moment between our check and the worker's bind ("Address already in use" at start-up). Two
    runs starting at the same time on one machine would otherwise draw the same port now and then,
    both see it free, and the later worker to bind it would fail its start-up.
    """
    low = _ephemeral_low()
    rng = random.Random()
    candidates = range(max(1025, low - 12000), low) if low > 13025 else None
    with _Registry() as others:
        for _ in range(200):
            port = rng.choice(candidates) if candidates else 0
            if port in _ISSUED_PORTS or port in others.recent:
                continue
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
                port = s.getsockname()[1]
            if port not in _ISSUED_PORTS and port not in others.recent:
                _ISSUED_PORTS.add(port)
                others.add(port)
                return port
    raise OSError(f"no free TCP port found on {host}")
