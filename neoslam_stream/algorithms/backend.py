"""The RatSLAM back end as one core: what corrects the odometry, the pose cells, the experience map.

Per camera frame it takes the front end's visual template (when the frame has one) and the
odometry since the previous frame, in OpenRatSLAM's order: the template first, then the odometry,
whose pose-cell update yields one action for the experience map. Before the pose cells the yaw-rate
bias estimator corrects the odometry and the odometry gate may refuse a recognised place that
dead reckoning cannot explain. :class:`PoseCellStage` is the part the pose-cell process hosts,
:class:`ExperienceMap` with :func:`integrate` the part the map's process hosts; :class:`BackEnd`
composes both for the in-process API and the benches.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .errors import InvalidInput
from .ratslam.experience_map import ExperienceMap, ExperienceMapConfig
from .ratslam.odometry_bias import OdometryBiasConfig, YawBiasEstimator
from .ratslam.odometry_gate import OdometryGate, OdometryGateConfig
from .ratslam.pose_cells import PoseCellConfig, PoseCellNetwork
from .ratslam.visual_odometry import VisualOdometry, VisualOdometryConfig
from .records import Action, MapPose


class PoseCellStageConfig(PoseCellConfig):
    """The ``pose_cells`` section: the network's parameters plus what corrects its input."""

    #: refuse recognitions that dead reckoning cannot explain (radius_m 0: off)
    odometry_gate: OdometryGateConfig = Field(default_factory=OdometryGateConfig)
    #: subtract the odometry's yaw-rate bias, estimated from loop closures (enabled false: off)
    odometry_bias: OdometryBiasConfig = Field(default_factory=OdometryBiasConfig)


class PoseCellStage:
    """Yaw-bias correction, odometry gate and pose cells: template and odometry -> action."""

    def __init__(self, config: PoseCellStageConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(PoseCellStageConfig, config, overrides)
        self.network = PoseCellNetwork(self.config)
        self.gate = OdometryGate(self.config.odometry_gate)
        self.bias = YawBiasEstimator(self.config.odometry_bias)
        self.actions = {0: 0, 1: 0, 2: 0, 3: 0}
        #: stamp of the previous odometry sample, for samples that carry no dt
        self.prev_stamp: float | None = None

    def on_template(self, template: int, relative_rad: float = 0.0) -> bool:
        """A recognised (or new) visual template. The bias sees every recognition, the gate's
        refusals too (a look-alike still faces the way the place was seen); the pose cells see
        what the gate lets through. Returns whether they saw it."""
        self.bias.on_template(template, relative_rad)
        if self.gate.enabled and not self.gate.check(template):
            return False
        self.network.on_view_template(template, relative_rad)
        return True

    def on_odometry(self, vtrans: float, vrot: float, dt: float | None = None, stamp: float = 0.0) -> Action:
        """One odometry sample -> the action for the experience map. ``dt`` None: OpenRatSLAM's rule,
        the time since the previous sample (the first one moves nothing)."""
        if dt is None:
            dt = 0.0 if self.prev_stamp is None else stamp - self.prev_stamp
        self.prev_stamp = stamp
        if not (math.isfinite(dt) and dt >= 0):
            raise InvalidInput(f"odometry dt {dt} is not a finite non-negative number")
        vrot = self.bias.correct(vrot, dt)
        self.network.on_odo(vtrans, vrot, dt)
        if self.gate.enabled:
            self.gate.on_odo(vtrans, vrot, dt)
        cell = 2 * math.pi / self.network.config.pc_dim_th
        self.bias.on_heading(self.network.best[2] * cell, vrot, dt, cell)
        action, src, dst, rel = self.network.get_action()
        self.bias.on_action(action, dst, rel)
        self.actions[action] += 1
        return Action(action, src, dst, vtrans, vrot, dt, relative_rad=rel, bias_wander=self.bias.wander)

    def new_session(self) -> None:
        """A new session on an old map: times start again, and where the robot is waits for its
        first recognised place (the pose cells and the gate: their ``new_session``)."""
        self.prev_stamp = None
        self.bias.new_session()
        self.gate.new_session()
        self.network.new_session()

    def info(self) -> dict[str, Any]:
        pc, bias = self.network, self.bias
        return {"templates": len(pc.templates), "experiences": len(pc.experiences),
                "actions": {str(k): v for k, v in self.actions.items()}, "gate_refused": self.gate.refused,
                **({"yaw_bias_rad_s": round(bias.bias, 6), "yaw_bias_samples": bias.samples,
                    "yaw_bias_outliers": bias.outliers, "yaw_bias_wander_rad2_s3": float(f"{bias.wander:.4g}")}
                   if bias.enabled else {}),
                "best_pose_cells": [round(v, 3) for v in pc.best]}

    def state_dict(self) -> dict[str, Any]:
        return {"pc": self.network.state_dict(), "gate": self.gate.state_dict(), "bias": self.bias.state_dict(),
                "actions": {str(k): v for k, v in self.actions.items()},
                "prev_odom_stamp": -1.0 if self.prev_stamp is None else self.prev_stamp}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.network.load_state_dict(st["pc"])
        self.gate.load_state_dict(st["gate"])
        self.bias.load_state_dict(st["bias"])
        self.actions = {int(k): int(v) for k, v in st["actions"].items()}
        stamp = float(st["prev_odom_stamp"])
        self.prev_stamp = None if stamp < 0 else stamp


def integrate(em: ExperienceMap, action: Action, stamp: float) -> MapPose:
    """Move the experience map by one action and its odometry; the robot's pose after it."""
    em.on_odo(action.vtrans, action.vrot, action.dt)
    em.bias_wander = action.bias_wander
    if action.action:
        em.on_action(action.action, action.src_id, action.dst_id, action.relative_rad, stamp)
    exp_id, *local = em.local_pose()
    return MapPose(np.array(em.robot_pose(), dtype=np.float64), exp_id, np.array(local, dtype=np.float64))


class CameraOdometry:
    """RatSLAM's visual odometry on a stream of stamped frames: each frame -> (vtrans, vrot, dt),
    dt from the stamps (1 / camera_hz before the first), zero motion until two frames were seen.
    ``speed_mps``: the platform's typical speed (``scale: platform`` calibrates by it)."""

    def __init__(self, config: VisualOdometryConfig | None = None, speed_mps: float | None = None,
                 **overrides: Any) -> None:
        self.odometry = VisualOdometry(make_config(VisualOdometryConfig, config, overrides), speed_mps)
        self.prev_stamp: float | None = None

    def on_frame(self, pixels: np.ndarray, stamp: float) -> tuple[float, float, float]:
        dt = 1.0 / self.odometry.config.camera_hz if self.prev_stamp is None else stamp - self.prev_stamp
        if dt < 0:
            raise InvalidInput(f"image stamp {stamp} is earlier than the previous one ({self.prev_stamp})")
        res = self.odometry.on_image(pixels, dt)
        self.prev_stamp = stamp
        vtrans, vrot = res if res is not None else (0.0, 0.0)
        return vtrans, vrot, dt

    def state_dict(self) -> dict[str, Any]:
        return {**self.odometry.state_dict(), "prev_stamp": -math.inf if self.prev_stamp is None else self.prev_stamp}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.odometry.load_state_dict(st)
        stamp = float(st["prev_stamp"])
        self.prev_stamp = None if stamp == -math.inf else stamp

    def new_session(self) -> None:
        """A new session: its first frame has no previous one to compare with; the raw speeds
        seen (the same robot and camera) are kept."""
        self.odometry.prev_trans = self.odometry.prev_rot = None
        self.prev_stamp = None


#: constants of :func:`derived_back_end` (why each value: its docstring)
CELL_S = 1.0          # a pose cell is the distance driven in this many seconds
GATE_S = 100.0        # the odometry gate's radius is the distance driven in this many seconds
GATE_DRIFT = 0.1      # ... plus this many metres per metre driven since the last accepted recognition
RING_FACTOR = 2.2     # a shortest loop longer than this times the area's extent encloses part of it
BIAS_FORGET_S = 5.0   # the yaw-rate bias follows the recognitions of the last few seconds
PC_DIM_XY = 21
EXP_DELTA_PC_THRESHOLD = 2.0


def derived_back_end(speed_mps: float = 0.5, shortest_loop_m: float = 10.0, area_m: float = 50.0) -> dict[str, Any]:
    """The back end's sections (``pose_cells``, ``experience_map``) from what a user knows about the
    robot, its typical speed, shortest loop and the area's extent (``platform``); the camera rate
    does not enter, since pose cells and map move with the odometry. Why each rule
    (docs/mapping.md, "The back end from the platform"):

    * a pose cell is the distance driven in ``CELL_S``, so the packet moves a small fraction of a
      cell per odometry step at any speed and the experience spacing scales with the robot;
    * the yaw-rate bias comes from every recognised template (a refused look-alike still measures
      the heading), with headings compared modulo half a turn unless the shortest loop is a ring:
      a closed route spanning an extent E is at least 2E long, exactly 2E only when it goes there
      and back, whose first revisits face the other way; a loop longer than ``RING_FACTOR`` E
      encloses part of the area, so its revisits face the same way. Its samples are forgotten
      over ``BIAS_FORGET_S``: each already averages the bias over the 30 s or more since its
      place was seen, and a bias that wanders (a random walk, a warming gearbox) is followed by
      the latest of them. Between them the estimate follows the turn the corrected odometry does
      not explain where recognised views hold the pose cells' heading, over one shortest loop at
      the typical speed (``anchor_s``), the time a return takes to measure the bias again: a
      return's heading is known only modulo a turn, and a bias that wanders faster than a return
      can tell apart is lost by the returns alone;
    * the odometry gate's radius is the distance driven in ``GATE_S`` plus ``GATE_DRIFT`` per metre
      since the last accepted recognition (what the bias-corrected odometry may be off); a gate
      as wide as the area refuses nothing a right recognition could need: off;
    * the map relaxed after each loop link as a pose graph whose yaw-rate bias wanders as far as
      the bias estimator measured (``relaxation: bias_walk``; least squares until it has): one
      closure after a long stretch of dead reckoning bends that stretch as the bias bent it, and
      a robot whose bias barely wanders gets nearly one rate for the whole run.

    Constants chosen on synthetic worlds 1-4 and the first half of the TUC run (``BIAS_FORGET_S``
    and the relaxation with its ``walk_*`` constants on worlds 1, 3, 4 and that half; the
    anchoring's loop time over fixed times on a day's templates with two other odometry draws,
    within 5 % of no anchoring's final map on worlds 1, 3, 4 and that half; by the rules in
    docs/mapping.md).
    """
    for name, value in (("speed_mps", speed_mps), ("shortest_loop_m", shortest_loop_m), ("area_m", area_m)):
        if not (math.isfinite(value) and value > 0):
            raise InvalidInput(f"{name} must be a positive number, got {value}")
    radius = speed_mps * GATE_S
    return {
        "pose_cells": {
            "pc_dim_xy": PC_DIM_XY,
            "pc_cell_x_size": speed_mps * CELL_S,
            "exp_delta_pc_threshold": EXP_DELTA_PC_THRESHOLD,
            "odometry_bias": {"enabled": True, "samples_from": "templates", "forget_s": BIAS_FORGET_S,
                              "bidirectional": bool(shortest_loop_m <= RING_FACTOR * area_m),
                              "anchor_s": shortest_loop_m / speed_mps},
            "odometry_gate": {"radius_m": radius if radius < area_m else 0.0, "drift": GATE_DRIFT},
        },
        "experience_map": {"relaxation": "bias_walk", "exp_initial_em_deg": 0.0,
                           "prune_m": EXP_DELTA_PC_THRESHOLD * speed_mps * CELL_S,
                           "prune_gap_s": shortest_loop_m / (2.0 * speed_mps),
                           "prune_age_s": shortest_loop_m / speed_mps},
    }


class BackEndConfig(BaseModel):
    """The back end's sections, as in a run's config."""

    model_config = ConfigDict(extra="forbid")

    pose_cells: PoseCellStageConfig = Field(default_factory=PoseCellStageConfig)
    experience_map: ExperienceMapConfig = Field(default_factory=ExperienceMapConfig)


class BackEnd:
    """Template and odometry per frame -> the robot's pose on the experience map."""

    def __init__(self, config: BackEndConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(BackEndConfig, config, overrides)
        self.pose_cells = PoseCellStage(self.config.pose_cells)
        self.experience_map = ExperienceMap(self.config.experience_map)

    def step(self, template: int | None, relative_rad: float, vtrans: float, vrot: float,
             dt: float | None = None, stamp: float = 0.0) -> MapPose:
        """One frame: its template (None: the front end gave none) and its odometry."""
        if template is not None:
            self.pose_cells.on_template(template, relative_rad)
        return integrate(self.experience_map, self.pose_cells.on_odometry(vtrans, vrot, dt, stamp), stamp)

    def warm_up(self) -> None:
        self.experience_map.warm_up()
