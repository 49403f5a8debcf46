"""The lossless source's credit window: frames seen on the run's final topic.

A lossless source publishes frame n only once frame n - ``window`` has reached the final topic, so
the queues and memory stay bounded whatever the pipeline's speed; the source process also waits on
it to drain the pipeline at the end (runtime/source_runner.py).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from .messages import MessageError, decode

log = logging.getLogger("neoslam.source")


class CreditWindow:
    """Frames seen on the final topic (credit window and end-of-run drain). ``start_frame``: the
    first frame this run publishes (a resumed run starts at its checkpoint's cut): the credit
    window counts from there, not from 0, or the first frame would wait ``stall_timeout`` for
    frames that will never come."""

    def __init__(self, start_frame: int = 0) -> None:
        self.last_frame = start_frame - 1
        self.count = 0
        self.last_change = time.monotonic()
        self.cond = threading.Condition()
        self.refusal_logged = False

    def on_sample(self, sample: Any) -> None:
        try:
            msg = decode(sample.payload.to_bytes())
        except MessageError as exc:  # an unregistered type says so here, once
            if not self.refusal_logged:
                self.refusal_logged = True
                log.warning("a message of the final topic was refused: %s", exc)
            return
        except Exception:
            return
        with self.cond:
            self.count += 1
            if msg.frame > self.last_frame:
                self.last_frame = msg.frame
            self.last_change = time.monotonic()
            self.cond.notify_all()

    def wait_until(self, frame: int, stall_timeout: float, stop: threading.Event) -> bool:
        with self.cond:
            while self.last_frame < frame and not stop.is_set():
                if time.monotonic() - self.last_change > stall_timeout:
                    return False
                self.cond.wait(0.1)
        return True
