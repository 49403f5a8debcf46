"""Yaw-rate bias b of the wheel odometry, estimated from loop closures and subtracted.

A loop closure measures the heading error accumulated since the place was first seen: the robot
faces as it faced then (plus the view's relative rotation), so with H(t) the raw yaw rate's
integral and gap_i = t - t_e

    drift_i = wrap(H(t) - H(t_e) - relative_rad - b_LS gap_i) + b_LS gap_i

(wrapped around the returns' current estimate b_LS, below; modulo pi when ``bidirectional``, for a
front end that also recognises a place seen the other way round). t_e is the place's latest visit at least ``min_gap_s``
before (``reference: latest``), or its first (``first``). A sample averages the bias over its gap,
and its heading is known only modulo a turn: against the first visit, after hours of driving it
averages a bias that has wandered since and can move b by at most pi / gap, so a wandering bias
slips past the estimate, which then follows an alias (docs/long_runs.md: a day's run). The latest
visit keeps the gap at one loop. b = b_LS = sum w_i drift_i gap_i / sum w_i gap_i^2, with
w_i = exp(-age_i / forget_s); closures sooner than ``min_gap_s`` are not used, and a rate further
than ``max_residual_rad_s`` from b_LS is an outlier. Samples come from the pose cells' returns to an
experience (``samples_from: actions``) or from every recognised template (``templates``: a
look-alike faces the same way, so it measures the heading too). ``enabled: false`` (the default,
OpenRatSLAM) passes the odometry through. Study and figures: docs/mapping.md.

``anchor_s`` > 0 adds what the pose cells' anchoring measures, every frame and without a wrap: a
recognised view pulls the cells' heading to the heading it was learned with, so the turn of the
cells' heading that the corrected odometry does not explain, e = wrap(theta_pc(t) - theta_pc(t-dt)
- (vrot - b) dt), is -(b_true - b) dt wherever views anchor it (0 where none does). An offset c
follows it, c <- c - e / anchor_s (a first-order filter of time constant anchor_s on the residual
rate -e / dt, at least ``ANCHOR_MIN_STEPS`` odometry steps; steps of a pose cell's angle or more are
the packet moving elsewhere, not a pull, and are left out), and the estimate is b = b_LS + c: the
returns set the level, the anchoring follows what the level misses between them, including a return
that unwrapped onto an alias. The returns are unwrapped around b_LS, not b: the offset moves with
every pull of the pose cells, and around it a long return's wrap would move from one alias to the
next and the level would swing (a there-and-back corridor's returns 1 000 s apart are told apart at
pi / 1 000 s, 0.003 rad/s).

How far b wanders is the robot's own (a gyro's random walk, a gearbox warming up), and the map's
``bias_walk`` relaxation needs it: :attr:`YawBiasEstimator.wander` is the mean of
(b_i - b_j)^2 / (t_i - t_j) over the samples i, j the latest earlier sample at least ``min_gap_s``
before (a random walk's variance per second, rad^2/s^3), 0 until the first such pair.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from .._config import make_config
from ..errors import InvalidInput
from .actions import CREATE_EDGE, NO_ACTION, SET_NODE
from .angles import clip_pi

#: the anchoring's time constant is never shorter than this many odometry steps: its offset
#: integrates a reading taken once a step, with a gain dt / tau a step through the pose cells, and
#: at a few steps or less that loop overshoots and oscillates (a numerical guard, not chosen on data;
#: the derived back end's loop times lie far above it)
ANCHOR_MIN_STEPS = 10


class OdometryBiasConfig(BaseModel):
    """Parameters of :class:`YawBiasEstimator`."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = False
    min_gap_s: float = Field(30.0, ge=0, description="closures sooner after the experience's creation are not used")
    max_residual_rad_s: float = Field(0.05, gt=0, description="samples whose rate differs more from the estimate are outliers")
    forget_s: float = Field(120.0, ge=0, description="a sample's weight is exp(-age / forget_s) (0: never forgotten)")
    samples_from: Literal["actions", "templates"] = Field(
        "actions", description="returns of the pose cells to an experience, or recognised visual templates")
    bidirectional: bool = Field(False, description="places are also recognised seen the other way round: "
                                                   "headings are compared modulo pi")
    reference: Literal["latest", "first"] = Field(
        "latest", description="the heading a return is compared with: the place's latest visit at least "
                              "min_gap_s before, or its first (module docstring)")
    anchor_s: float = Field(0.0, ge=0, description="time constant of the offset that follows the pose cells' "
                                                   "anchoring (module docstring); 0: off")


class YawBiasEstimator:
    """See the module docstring. Per odometry sample :meth:`correct` (returns the corrected yaw
    rate), per pose-cell action :meth:`on_action`, per visual template received
    :meth:`on_template` (each ignores what ``samples_from`` does not name)."""

    def __init__(self, config: OdometryBiasConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(OdometryBiasConfig, config, overrides)
        #: the returns' least-squares level b_LS and the anchoring's offset c (rad/s): the estimate
        #: :attr:`bias` is their sum
        self.level = 0.0
        self.offset = 0.0
        #: the pose cells' heading after the previous odometry step (rad; None: none yet)
        self._theta_prev: float | None = None
        #: H(t): the raw yaw rate's integral, and t: the odometry's time
        self.heading = 0.0
        self.t = 0.0
        #: experience (or template, with samples_from templates) id -> (H, t) at its creation, or
        #: at its latest visit that was a sample (``reference: latest``)
        self.born: dict[int, tuple[float, float]] = {}
        self.last_template = -1
        self._sum_dg = self._sum_gg = 0.0
        self._last_sample_t = 0.0
        self.samples = 0
        self.outliers = 0
        #: (t, b) after each sample since the latest one at least min_gap_s old, and the wander's sums
        self._history: deque[tuple[float, float]] = deque()
        self._sum_q = 0.0
        self._pairs = 0

    @property
    def bias(self) -> float:
        """The estimate b (rad/s), subtracted from every yaw rate once known: b_LS + c."""
        return self.level + self.offset

    @bias.setter
    def bias(self, value: float) -> None:
        self.level = value - self.offset

    @property
    def wander(self) -> float:
        """How fast b wanders, rad^2/s^3 (module docstring); 0 while not measured."""
        return self._sum_q / self._pairs if self._pairs else 0.0

    @property
    def enabled(self) -> bool:
        return self.config.enabled

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
        if not self.enabled or action == NO_ACTION or self.config.samples_from != "actions":
            return
        dst = int(dst)
        if dst not in self.born:
            self.born[dst] = (self.heading, self.t)
            return
        if action in (CREATE_EDGE, SET_NODE):
            self._sample(dst, relative_rad)

    def on_template(self, template: int, relative_rad: float = 0.0) -> None:
        """A visual template reached the pose-cell node (``samples_from: templates``): note a new
        one, and take a sample when the robot returns to an old one."""
        if not self.enabled or self.config.samples_from != "templates":
            return
        template = int(template)
        previous, self.last_template = self.last_template, template
        if template not in self.born:
            self.born[template] = (self.heading, self.t)
        elif template != previous:
            self._sample(template, relative_rad)

    def _sample(self, ref: int, relative_rad: float) -> None:
        """One drift sample against reference ``ref`` (an experience or a template) and the new b."""
        h0, t0 = self.born[ref]
        gap = self.t - t0
        if gap < self.config.min_gap_s or gap <= 0:
            return
        if self.config.reference == "latest":  # the next return is compared with this visit, outlier or not
            self.born[ref] = (self.heading, self.t)
        drift = self._wrap(self.heading - h0 - relative_rad - self.level * gap) + self.level * gap
        if self.samples and abs(drift / gap - self.level) > self.config.max_residual_rad_s:
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
        self.level = self._sum_dg / self._sum_gg
        self._note_wander()

    def on_heading(self, theta_rad: float, vrot_used: float, dt: float, jump_rad: float) -> None:
        """The pose cells' heading after an odometry step that turned them by ``vrot_used`` * ``dt``
        (the corrected yaw rate): with ``anchor_s``, the offset follows the turn the odometry did not
        explain (module docstring); a step of ``jump_rad`` or more is the packet moving elsewhere."""
        if not (self.enabled and self.config.anchor_s > 0):
            return
        prev, self._theta_prev = self._theta_prev, theta_rad
        if prev is None or dt <= 0:
            return
        e = clip_pi(theta_rad - prev - vrot_used * dt)
        if abs(e) < jump_rad:
            self.offset -= e / max(self.config.anchor_s, ANCHOR_MIN_STEPS * dt)

    def _note_wander(self) -> None:
        """Pair the new estimate with the latest one at least min_gap_s older (module docstring)."""
        then, hist = self.t - self.config.min_gap_s, self._history
        while len(hist) > 1 and hist[1][0] <= then:
            hist.popleft()
        if hist and hist[0][0] <= then and self.t > hist[0][0]:
            self._sum_q += (self.bias - hist[0][1]) ** 2 / (self.t - hist[0][0])
            self._pairs += 1
        hist.append((self.t, self.bias))

    def _wrap(self, a: float) -> float:
        """a wrapped into (-pi, pi] (clip_pi), or into (-pi/2, pi/2] when bidirectional (modulo pi)."""
        return clip_pi(2 * a) / 2 if self.config.bidirectional else clip_pi(a)

    def new_session(self) -> None:
        """A new session of a loaded map: the robot's heading is unrelated to the raw heading of the
        old session, so its experiences can no longer serve as references, and the bias is measured
        afresh as in a first session (estimate 0, the first return sets it; the wander measured, the
        robot's own, stays). A session is a new power-on after a gap of unknown length: a gyro's
        bias changes at every power-on and over the gap by the wander, so the old session's last
        estimate may be far off, and held, it makes the pose cells' dead reckoning turn the wrong
        way and every return an outlier, and the session's new experiences bend the stored map
        (docs/long_runs.md, a day's map). A bias that did not change is found again by the first
        returns and the anchoring, as in the first session."""
        self.born = {}
        self.last_template = -1
        self._theta_prev = None
        self.level = self.offset = 0.0
        self._sum_dg = self._sum_gg = 0.0
        self.samples = 0
        self._history.clear()

    def state_dict(self) -> dict[str, Any]:
        return {"scalars": [self.bias, self.heading, self.t, self._sum_dg, self._sum_gg, self._last_sample_t,
                            self.samples, self.outliers, self._sum_q, self._pairs],
                "last_template": self.last_template,
                "anchor": [self.level, self.offset, math.nan if self._theta_prev is None else self._theta_prev],
                "history": np.array(self._history, dtype=np.float64).reshape(-1, 2),
                "born": np.array([(k, h, t) for k, (h, t) in self.born.items()], dtype=np.float64).reshape(-1, 3)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        (bias, self.heading, self.t, self._sum_dg, self._sum_gg, self._last_sample_t,
         samples, outliers, self._sum_q, pairs) = (float(v) for v in st["scalars"])
        self.samples, self.outliers, self._pairs = int(samples), int(outliers), int(pairs)
        self._history = deque((float(t), float(b)) for t, b in np.asarray(st["history"], dtype=np.float64).reshape(-1, 2))
        self.last_template = int(st["last_template"])
        # a state saved before the anchoring: the estimate was the level alone
        level, offset, theta = st.get("anchor", [bias, 0.0, math.nan])
        self.level, self.offset = float(level), float(offset)
        self._theta_prev = None if math.isnan(float(theta)) else float(theta)
        self.born = {int(k): (float(h), float(t)) for k, h, t in np.asarray(st["born"], dtype=np.float64).reshape(-1, 3)}
