"""Odometry gate: loop closures that dead reckoning cannot explain do not reach the pose cells.

The gate integrates the odometry, re-anchored at every accepted recognition, and keeps the place
where each visual template was first seen. A recognised template passes only when its place lies
within r(t) = radius_m + drift * L(t) of the estimate, L(t) the path length driven since the last
accepted recognition (odometry's error grows with the distance driven). An accepted recognition
moves the estimate to the template's place and resets L; a refused one changes nothing, so a
look-alike far away cannot pull the map. The heading stays odometry's (a place may be revisited
the other way round). ``radius_m = 0`` (the default) switches the gate off: every template passes,
as in OpenRatSLAM.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from .._config import make_config
from ..errors import InvalidInput


class OdometryGateConfig(BaseModel):
    """Parameters of :class:`OdometryGate`."""

    model_config = ConfigDict(extra="forbid")

    radius_m: float = Field(0.0, ge=0, description="radius at L = 0 (0: gate off)")
    drift: float = Field(0.1, ge=0, description="radius growth per metre driven since the last accepted recognition")


class OdometryGate:
    """Dead reckoning re-anchored at accepted recognitions; see the module docstring."""

    def __init__(self, config: OdometryGateConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(OdometryGateConfig, config, overrides)
        self.x = self.y = self.th = 0.0
        self.path_m = 0.0
        self.places: dict[int, tuple[float, float]] = {}
        self.current = -1
        self.refused = 0

    @property
    def enabled(self) -> bool:
        return self.config.radius_m > 0

    def on_odo(self, vtrans: float, vrot: float, dt: float) -> None:
        """Integrate one odometry sample (rotate, then advance; as the experience map does)."""
        if not (math.isfinite(vtrans) and math.isfinite(vrot) and math.isfinite(dt)):
            raise InvalidInput(f"odometry must be finite, got vtrans={vtrans} vrot={vrot} dt={dt}")
        self.th += vrot * dt
        self.x += vtrans * dt * math.cos(self.th)
        self.y += vtrans * dt * math.sin(self.th)
        self.path_m += abs(vtrans * dt)

    def allowed_m(self) -> float:
        """r(t): how far from the estimate a recognised place may lie now."""
        return self.config.radius_m + self.config.drift * self.path_m

    def check(self, template: int) -> bool:
        """Whether template ``template`` may reach the pose cells now. A new template is always
        accepted (its place is recorded); the current one too (the robot is still there)."""
        template = int(template)
        place = self.places.get(template)
        if place is None:
            self.places[template] = (self.x, self.y)
            self.current = template
            return True
        if not self.enabled or template == self.current:
            return True
        if math.hypot(self.x - place[0], self.y - place[1]) > self.allowed_m():
            self.refused += 1
            return False
        self.x, self.y = place
        self.path_m = 0.0
        self.current = template
        return True

    def new_session(self) -> None:
        """A new session on a stored map: the dead reckoning of the old one says nothing about where
        the robot is now, so the next recognition of a known place passes (the path driven since
        the last accepted one counts as endless) and re-anchors the estimate."""
        self.path_m = math.inf
        self.current = -1

    def state_dict(self) -> dict[str, Any]:
        return {"pose": [self.x, self.y, self.th, self.path_m], "current": self.current, "refused": self.refused,
                "places": [[k, v[0], v[1]] for k, v in self.places.items()]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.x, self.y, self.th, self.path_m = (float(v) for v in st["pose"])
        self.current = int(st["current"])
        self.refused = int(st["refused"])
        self.places = {int(k): (float(x), float(y)) for k, x, y in st["places"]}
