"""The run's log lines on the bus: every process of a run publishes what it logs on ``log``.

Each process logs to its own stderr (the terminal of ``neoslam run``); :func:`attach` adds a
handler that also publishes each record as a ``log`` message (level, process, logger name, text)
on the run's key, so that tools attached to the run see them live (``neoslam view --foxglove``)
and the monitor keeps them in ``log.jsonl`` (:class:`LogFile`). Publishing never waits (zenoh
drops the sample instead of blocking) and is bounded to :data:`MAX_PER_S` records a second per
process, the rest counted; a record logged while one is being published (zenoh's own) is not
published again.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

from .messages import LOG, Message, MessageError, decode, encode

#: records a process publishes at most per second (a flood of warnings is cut, counted)
MAX_PER_S = 20
#: lines log.jsonl holds at most (the rest counted in its last line)
MAX_LINES = 20_000
#: the run folder's file of log lines
LOG_FILE = "log.jsonl"


class BusLogHandler(logging.Handler):
    """Publishes each record on ``neoslam/<run>/log`` through ``session``, dropping, never waiting."""

    def __init__(self, session: Any, run: str, process: str, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        import zenoh

        from .bus import key_for

        self.process = process
        self.publisher = session.declare_publisher(key_for(run, str(LOG)),
                                                   congestion_control=zenoh.CongestionControl.DROP)
        self.suppressed = 0
        self._window = (0.0, 0)  # second, records published in it
        self._busy = threading.local()
        self.setFormatter(logging.Formatter("%(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(self._busy, "on", False):
            return
        now = time.time()
        second, n = self._window
        if int(now) != second:
            second, n = int(now), 0
        if n >= MAX_PER_S:
            self.suppressed += 1
            return
        self._window = (second, n + 1)
        self._busy.on = True
        try:
            data = {"level": record.levelname, "process": self.process, "name": record.name,
                    "message": self.format(record)[:4000]}
            self.publisher.put(encode(Message(str(LOG), 0, record.created, data)))
        except Exception:  # a log line must never break the process that logs it
            self.suppressed += 1
        finally:
            self._busy.on = False

    def close(self) -> None:
        try:
            self.publisher.undeclare()
        except Exception:  # the session is closed already
            pass
        super().close()


def attach(session: Any, run: str, process: str) -> BusLogHandler:
    """Publish this process's log records (those its root logger passes) on the run's ``log``;
    :func:`detach` before the session closes."""
    handler = BusLogHandler(session, run, process)
    logging.getLogger().addHandler(handler)
    return handler


def detach(handler: BusLogHandler | None) -> None:
    if handler is not None:
        logging.getLogger().removeHandler(handler)
        handler.close()


def log_record(payload: bytes) -> dict[str, Any] | None:
    """A ``log`` message as a dict (t, level, process, name, message); None when it is none."""
    try:
        msg = decode(payload, expected_type=str(LOG))
    except MessageError:
        return None
    return {"t": msg.stamp, **{k: msg.data[k] for k in ("level", "process", "name", "message")}}


class LogFile:
    """log.jsonl: one JSON object per log line of the run (:func:`log_record` and ``t_s``, seconds
    since ``t0``), at most :data:`MAX_LINES`; called from zenoh's callbacks. The file is opened
    once, for appending (a restarted monitor keeps what its first life wrote), and flushed after
    every line so that a viewer reading the run sees it at once."""

    def __init__(self, run_dir: str | Path, t0: float) -> None:
        self.path = Path(run_dir) / LOG_FILE
        self.t0 = t0
        self.lines = 0
        self.skipped = 0
        self.lock = threading.Lock()
        self._fh: Any = None
        self._closed = False

    def _write(self, rec: dict) -> bool:
        """Append one line; False where the disk refused it (the run goes on, the line is lost)."""
        try:
            if self._fh is None:
                self._fh = open(self.path, "a")
            self._fh.write(json.dumps(rec) + "\n")
            self._fh.flush()
            return True
        except OSError:
            return False

    def on_sample(self, sample: Any) -> None:
        rec = log_record(sample.payload.to_bytes())
        if rec is None:
            return
        with self.lock:
            if self._closed:
                return
            if self.lines >= MAX_LINES or not self._write({"t_s": round(rec["t"] - self.t0, 3), **rec}):
                self.skipped += 1
                return
            self.lines += 1

    def close(self) -> None:
        with self.lock:
            if self._closed:
                return
            self._closed = True
            if self.skipped:
                self._write({"t_s": None, "skipped": self.skipped})
            if self._fh is not None:
                try:
                    self._fh.close()
                except OSError:
                    pass
                self._fh = None
