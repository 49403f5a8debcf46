"""Yaw-rate bias of the wheel odometry, estimated from loop closures (issue #14).

Wheel odometry turns the robot's heading by a small, slowly varying error per second (unequal
wheel radii, a gyro's bias): over one lap of the synthetic world it amounts to tens of degrees,
and dead reckoning between recognised places, and across a stretch where no place is recognised
at all (a lap driven the other way), bends the map with it. A loop closure measures it: when the
pose cells return to an experience e (CREATE_EDGE or SET_NODE to it) and the view was recognised,
the robot faces as it faced when e was created (plus the view's relative rotation), so the heading
the raw odometry integrated in between, minus that, is the accumulated error

    drift_i = wrap(H(t) - H(t_e) - relative_rad - b gap_i) + b gap_i,   gap_i = t - t_e,

(H the integral of the raw yaw rate; the wrap is taken around the current estimate b, so a drift
beyond half a turn over a long gap is still counted whole). The bias is the least-squares rate of
these samples, b = sum w_i drift_i gap_i / sum w_i gap_i^2, with w_i = exp(-age_i / forget_s)
(older closures count less, so a drifting bias is followed); a closure seen less than
``min_gap_s`` after its experience was created says too little and is not used, and one whose
rate drift_i / gap_i differs from b by more than ``max_residual_rad_s`` is counted as an outlier
and left out. The pose cells and the experience map then integrate vrot - b.

It assumes that a recognised place is seen facing the same way as when it was first seen, as a
forward camera's place recognition does; a front end that matches a place seen the other way round
(a symmetric corridor) gives samples off by half a turn, which the residual test rejects once an
estimate exists. ``enabled: false`` (the model's default; the paper profile) integrates the
odometry as it comes.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .._config import make_config
from ..errors import InvalidInput
from .actions import CREATE_EDGE, NO_ACTION, SET_NODE
from .angles import clip_pi


class OdometryBiasConfig(BaseModel):
    """Parameters of :class:`YawBiasEstimator`."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False
    min_gap_s: float = Field(30.0, ge=0, description="closures sooner after the experience's creation are not used")
    max_residual_rad_s: float = Field(0.05, gt=0, description="samples whose rate differs more from the estimate are outliers")
    forget_s: float = Field(120.0, ge=0, description="a sample's weight is exp(-age / forget_s) (0: never forgotten)")


class YawBiasEstimator:
    """See the module docstring. Per odometry sample :meth:`correct` (returns the corrected yaw
    rate), per pose-cell action :meth:`on_action`."""

    def __init__(self, config: OdometryBiasConfig | None = None, **overrides: Any) -> None:
        self.config = cfg = make_config(OdometryBiasConfig, config, overrides)
        self.enabled = cfg.enabled
        #: the estimate b (rad/s), subtracted from every yaw rate once known
        self.bias = 0.0
        #: H(t): the raw yaw rate's integral, and t: the odometry's time
        self.heading = 0.0
        self.t = 0.0
        #: experience id -> (H, t) when the pose cells created it
        self.born: dict[int, tuple[float, float]] = {}
        self._sum_dg = self._sum_gg = 0.0
        self._last_sample_t = 0.0
        self.samples = 0
        self.outliers = 0

    def correct(self, vrot: float, dt: float) -> float:
        """Integrate one raw odometry sample; the yaw rate to use (vrot - b when enabled)."""
        if not (math.isfinite(vrot) and math.isfinite(dt)):
            raise InvalidInput(f"odometry must be finite, got vrot={vrot} dt={dt}")
        self.heading += vrot * dt
        self.t += dt
        return vrot - self.bias if self.enabled else vrot

    def on_action(self, action: int, dst: int, relative_rad: float = 0.0) -> None:
        """A pose-cell action (see pose_cells.get_action): note new experiences, and take a sample
        when the cells return to an old one."""
        if not self.enabled or action == NO_ACTION:
            return
        dst = int(dst)
        if dst not in self.born:
            self.born[dst] = (self.heading, self.t)
            return
        if action not in (CREATE_EDGE, SET_NODE):
            return
        h0, t0 = self.born[dst]
        gap = self.t - t0
        if gap < self.config.min_gap_s or gap <= 0:
            return
        drift = clip_pi(self.heading - h0 - relative_rad - self.bias * gap) + self.bias * gap
        if self.samples and abs(drift / gap - self.bias) > self.config.max_residual_rad_s:
            self.outliers += 1
            return
        if self.config.forget_s > 0 and self.samples:
            keep = math.exp(-(self.t - self._last_sample_t) / self.config.forget_s)
            self._sum_dg *= keep
            self._sum_gg *= keep
        self._last_sample_t = self.t
        self._sum_dg += drift * gap
        self._sum_gg += gap * gap
        self.samples += 1
        self.bias = self._sum_dg / self._sum_gg

    def new_session(self) -> None:
        """A new session of a loaded map: the robot's heading is unrelated to the raw heading of the
        old session, so its experiences can no longer serve as references; the bias (the same
        robot's odometry) is kept."""
        self.born = {}

    def state_dict(self) -> dict[str, Any]:
        return {"scalars": [self.bias, self.heading, self.t, self._sum_dg, self._sum_gg, self._last_sample_t,
                            self.samples, self.outliers],
                "born": np.array([(k, h, t) for k, (h, t) in self.born.items()], dtype=np.float64).reshape(-1, 3)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        (self.bias, self.heading, self.t, self._sum_dg, self._sum_gg, self._last_sample_t,
         samples, outliers) = (float(v) for v in st["scalars"])
        self.samples, self.outliers = int(samples), int(outliers)
        self.born = {int(k): (float(h), float(t)) for k, h, t in np.asarray(st["born"], dtype=np.float64).reshape(-1, 3)}
