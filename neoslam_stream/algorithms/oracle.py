"""The oracle front end: template ids from ground truth instead of images (a diagnosis tool).

It replaces A, B, C and D (``neoslam run --oracle-templates``), so the back end gets the best
template stream a place-recognition front end could give: a map that is bad with the oracle is
the back end's fault, and the distance between the oracle's map and a run's is what the front
end costs. Per frame, with the true pose (x, y, theta), a template is a candidate when its place
(the true pose of the frame that created it) is within ``radius_m`` and its heading within
``heading_tolerance_deg`` (a camera facing the other way sees another view; 180 closes every
revisit); the nearest candidate is the frame's template, else a new one (ids consecutive from 0).
A loop closure is a match to a template the robot had left before; the score is the distance to
the match and the runner-up's score the distance to the second-nearest candidate. ``radius_m``
defaults to the experience map's spacing, ``exp_delta_pc_threshold * pc_cell_x_size`` of the
run's pose cells: one template per experience.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .errors import InvalidInput
from .ratslam.angles import wrap_pi


class OracleConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    #: a template's reach (m); None: exp_delta_pc_threshold * pc_cell_x_size of the pose cells
    radius_m: float | None = Field(None, gt=0)
    #: how far (deg) the heading may differ from the template's; 180 ignores the heading
    heading_tolerance_deg: float = Field(45.0, gt=0, le=180)


class OracleTemplates:
    """True pose -> (template id, loop-closure flag, distance to the match, runner-up's distance)."""

    def __init__(self, config: OracleConfig | None = None, **overrides: Any) -> None:
        cfg = self.config = make_config(OracleConfig, config, overrides)
        if cfg.radius_m is None:
            raise ValueError("OracleTemplates needs radius_m (the oracle pipeline derives it from the pose cells)")
        self.radius = float(cfg.radius_m)
        self.tolerance = math.radians(cfg.heading_tolerance_deg)
        self._places = np.zeros((256, 3))
        self.n_templates = 0
        self.current = -1
        #: templates the robot has left at least once (a match to one of them is a return)
        self._left = np.zeros(256, dtype=bool)

    @property
    def places(self) -> np.ndarray:
        """(n, 3): each template's true (x, y, theta) where it was created."""
        return self._places[: self.n_templates]

    def compute(self, pose: Any) -> dict[str, Any]:
        p = np.asarray(pose, dtype=np.float64).ravel()
        if p.shape != (3,) or not np.isfinite(p).all():
            raise InvalidInput(f"a true pose must be 3 finite numbers (x, y, theta), got {pose!r}")
        pl = self.places
        dist = np.hypot(pl[:, 0] - p[0], pl[:, 1] - p[1])
        dth = np.abs(wrap_pi(pl[:, 2] - p[2]))
        cand = np.flatnonzero((dist <= self.radius) & (dth <= self.tolerance + 1e-12))
        second: float | None = None
        if cand.size:
            order = cand[np.argsort(dist[cand], kind="stable")]
            tid, score = int(order[0]), float(dist[order[0]])
            if order.size > 1:
                second = float(dist[order[1]])
        else:
            if self.n_templates == self._places.shape[0]:
                self._places = np.concatenate([self._places, np.zeros_like(self._places)])
                self._left = np.concatenate([self._left, np.zeros_like(self._left)])
            tid, score = self.n_templates, 0.0
            self._places[tid] = p
            self.n_templates += 1
        if self.current >= 0 and tid != self.current:
            self._left[self.current] = True
        loop = bool(self._left[tid])
        self.current = tid
        return {"id": tid, "is_loop_closure": bool(loop), "best_score": score, "second_score": second}

    def state_dict(self) -> dict[str, Any]:
        return {"places": self.places.copy(), "left": self._left[: self.n_templates].copy(),
                "current": self.current}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        places = np.asarray(state["places"], dtype=np.float64).reshape(-1, 3)
        self._places = np.concatenate([places, np.zeros((256, 3))])
        self._left = np.concatenate([np.asarray(state["left"], dtype=bool).ravel(), np.zeros(256, dtype=bool)])
        self.n_templates = len(places)
        self.current = int(state["current"])
