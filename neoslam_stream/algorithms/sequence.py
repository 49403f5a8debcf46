"""Sequence consistency of loop closures: a SeqSLAM-style window over D's matches.

One frame's best match is often wrong where places look alike, and with the paper's parameters
C adds no sequence context; this filter asks for it explicitly. A closure of frame t onto the
reference frame m_t (the first frame of interval k*) is accepted only when each of the
``length`` previous frames t-i also had a candidate whose reference frame m_{t-i} lies within
``i * max_step + slack`` frames of m_t: a robot that comes back to a place sees the places before
it again too, in either direction, while an isolated look-alike is refused. ``slack`` absorbs the
interval granularity (an interval spans up to theta_rho + 1 frames). ``min_gap_frames``:
intervals opened fewer frames before t are no candidates at all (a slow or turning robot sees the
same view for longer than the omega newest intervals, and a "closure" onto the place it just left
makes the back end jump back). ``length = 0`` and ``min_gap_frames = 0`` switch the filter off
(the paper's rule).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config


class SequenceConfig(BaseModel):
    """Parameters of :class:`SequenceFilter` (frames are D's frames, counted from 0)."""

    model_config = ConfigDict(extra="forbid")

    length: int = Field(0, ge=0, description="previous frames that must agree (0: filter off)")
    max_step: float = Field(2.0, gt=0, description="reference frames per query frame, at most")
    slack: int = Field(4, ge=0, description="frames of tolerance (interval granularity)")
    min_gap_frames: int = Field(0, ge=0, description="intervals opened fewer frames ago are no candidates")


def refs_consistent(refs: Mapping[int, int], t: int, ref: int, length: int, max_step: float, slack: int) -> bool:
    """Whether frames t-1 .. t-length all had a reference frame (``refs``: frame -> reference,
    -1 for none) within i * max_step + slack of frame t's ``ref``."""
    for i in range(1, length + 1):
        m = refs.get(t - i, -1)
        if m < 0 or abs(ref - m) > i * max_step + slack:
            return False
    return True


class SequenceFilter:
    """Accepts a loop closure only after a run of consistent candidates (module docstring)."""

    def __init__(self, config: SequenceConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(SequenceConfig, config, overrides)
        #: (frame, reference frame or -1 when the frame had no candidate), the newest last
        self.history: deque[tuple[int, int]] = deque(maxlen=max(self.config.length, 1))
        self.refused = 0

    @property
    def enabled(self) -> bool:
        return self.config.length > 0

    def consistent(self, t: int, ref: int) -> bool:
        """Whether frames t-1 .. t-length all had candidates within i*max_step + slack of ``ref``."""
        cfg = self.config
        return refs_consistent(dict(self.history), t, ref, cfg.length, cfg.max_step, cfg.slack)

    def check(self, t: int, ref: int) -> bool:
        """Record frame t's candidate (``ref`` = its reference frame, -1 for none) and return
        whether a closure at t is accepted. Call once per frame, in frame order."""
        ok = ref >= 0 and (not self.enabled or self.consistent(t, ref))
        if self.enabled:
            self.refused += int(ref >= 0 and not ok)
            self.history.append((int(t), int(ref)))
        return ok

    def state_dict(self) -> dict[str, Any]:
        return {"history": [list(h) for h in self.history], "refused": self.refused}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.history.clear()
        for t, m in state["history"]:
            self.history.append((int(t), int(m)))
        self.refused = int(state["refused"])
