"""Nodes of the RatSLAM back end and baseline front end (see ``algorithms.ratslam``).

Determinism: lossless runs are repeatable whatever the arrival order of ``visual_template`` and
``odom``, because the pose-cell stage processes events in frame order. Both wait in buffers. A
template of frame f is applied once the odometry stream has reached frame f (odometry arrives in
frame order): first every buffered odometry of frames < f, then the template, then the odometry of
frame f. Odometry of frames without a template (``frame_stride``, or templates dropped in real-time
mode) is processed when a later template is applied; both buffers are bounded (``max_odom_lag``),
beyond which the oldest event is processed without waiting. Each processed odometry
yields one ``pose_cells/action`` carrying that odometry, so the experience-map stage needs only
that one topic and dead reckoning stays in the same order as the actions.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import numpy as np

from ..algorithms.backend import CameraOdometry, PoseCellStage, PoseCellStageConfig, integrate
from ..algorithms.calibration import PlatformConfig
from ..algorithms.frontend import LocalViewFrontEnd, LocalViewFrontEndConfig
from ..algorithms.ratslam.experience_map import ExperienceMap, ExperienceMapConfig
from ..algorithms.ratslam.visual_odometry import VisualOdometryConfig
from ..algorithms.records import Action
from ..runtime.messages import Message, decode, encode
from ..runtime.node import Node, Output, StageInputError
from .camera import camera_pixels
from .topics import (
    EXPERIENCE_MAP,
    EXPERIENCE_POSE,
    IMAGE,
    ODOM,
    POSE_CELL_ACTION,
    VISUAL_TEMPLATE,
    record_data,
    record_of,
)


class PoseCellsNode(Node):
    """The back end's pose-cell stage in a node: ``visual_template`` + ``odom`` -> one
    ``pose_cells/action`` per odometry, in frame order (see the module docstring).

    ``max_odom_lag``: how many odometry (or template) messages may wait for their partner before
    the oldest is processed without it; the other parameters are :class:`PoseCellStageConfig`'s.
    """

    inputs = (VISUAL_TEMPLATE, ODOM)
    outputs = (POSE_CELL_ACTION,)

    def __init__(self, max_odom_lag: int = 64, **params: Any) -> None:
        super().__init__()
        self.stage = PoseCellStage(PoseCellStageConfig(**params))
        self.max_odom_lag = max_odom_lag
        self.pending: OrderedDict[int, Message] = OrderedDict()  # odometry by frame
        self.templates_waiting: OrderedDict[int, Message] = OrderedDict()
        self.last_template_frame = -1
        self.max_odom_frame = -1
        self.last_odom_frame = -1

    def _odo(self, msg: Message, via: Message | None = None) -> Output:
        dt = msg.data.get("dt")
        self.last_odom_frame = max(self.last_odom_frame, msg.frame)
        a = self.stage.on_odometry(float(msg["vtrans"]), float(msg["vrot"]), None if dt is None else float(dt),
                                   msg.stamp)
        base = via if via is not None else msg
        out = base.derive(POSE_CELL_ACTION, record_data(a))
        out.frame, out.stamp = msg.frame, msg.stamp
        return [(POSE_CELL_ACTION, out)]

    def _apply_template(self, msg: Message) -> Output:
        out: Output = []
        while self.pending and next(iter(self.pending)) < msg.frame:
            out += self._odo(self.pending.pop(next(iter(self.pending))))
        self.stage.on_template(int(msg["id"]), float(msg.data.get("relative_rad", 0.0)))
        self.last_template_frame = max(self.last_template_frame, msg.frame)
        odo = self.pending.pop(msg.frame, None)
        if odo is not None:
            out += self._odo(odo, via=msg)
        return out

    def _drain(self, final: bool = False) -> Output:
        """Process what can be processed in frame order (everything when ``final``)."""
        out: Output = []
        while True:
            t = next(iter(self.templates_waiting), None)
            if t is not None and (final or self.max_odom_frame >= t
                                  or len(self.templates_waiting) > self.max_odom_lag):
                out += self._apply_template(self.templates_waiting.pop(t))
                continue
            if self.pending and (final or len(self.pending) > self.max_odom_lag):
                f = next(iter(self.pending))
                if t is None or f < t:
                    out += self._odo(self.pending.pop(f))
                    continue
            return out

    def process(self, topic: str, msg: Message) -> Output:
        if topic == "odom":
            for k in ("vtrans", "vrot"):
                v = msg.data.get(k)
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                    raise StageInputError(f"odometry field {k!r} of frame {msg.frame} is not a finite number")
            if msg.frame in self.pending or msg.frame <= self.last_odom_frame:
                # odometry is integrated in frame order exactly once: a repeated or older frame
                # would count the same motion twice or move back in time
                raise StageInputError(f"odometry of frame {msg.frame} is out of order (frame "
                                      f"{max(self.last_odom_frame, self.max_odom_frame)} already seen)")
            if msg.frame <= self.last_template_frame:  # late: its template has been applied already
                return self._odo(msg)
            self.pending[msg.frame] = msg
            if msg.frame < self.max_odom_frame:
                self.pending = OrderedDict(sorted(self.pending.items()))
            self.max_odom_frame = max(self.max_odom_frame, msg.frame)
        else:
            vt = int(msg["id"])
            if vt < 0:
                raise StageInputError(f"template id {vt} is negative")
            if msg.frame <= self.last_template_frame or msg.frame in self.templates_waiting:
                raise StageInputError(f"template of frame {msg.frame} is out of order (frame "
                                      f"{self.last_template_frame} already applied)")
            self.templates_waiting[msg.frame] = msg
            self.templates_waiting = OrderedDict(sorted(self.templates_waiting.items()))
        return self._drain()

    def flush(self) -> Output:
        return self._drain(final=True)

    def info(self) -> dict[str, Any]:
        return {**self.stage.info(), "pending_odom": len(self.pending)}

    def state_dict(self) -> dict[str, Any]:
        return {**self.stage.state_dict(), "last_template_frame": self.last_template_frame,
                "max_odom_frame": self.max_odom_frame, "last_odom_frame": self.last_odom_frame,
                "pending": [np.frombuffer(encode(m), dtype=np.uint8) for m in self.pending.values()],
                "templates_waiting": [np.frombuffer(encode(m), dtype=np.uint8)
                                      for m in self.templates_waiting.values()]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.stage.load_state_dict(st)
        self.last_template_frame = int(st["last_template_frame"])
        self.max_odom_frame = int(st["max_odom_frame"])
        self.last_odom_frame = int(st["last_odom_frame"])
        self.pending, self.templates_waiting = OrderedDict(), OrderedDict()
        for key, store in (("pending", self.pending), ("templates_waiting", self.templates_waiting)):
            for raw in st[key]:
                m = decode(np.asarray(raw, dtype=np.uint8).tobytes())
                store[m.frame] = m

    def new_session(self) -> None:
        self.pending, self.templates_waiting = OrderedDict(), OrderedDict()
        self.last_template_frame = self.max_odom_frame = self.last_odom_frame = -1
        self.stage.new_session()


class ExperienceMapNode(Node):
    """Experience map in a node: ``pose_cells/action`` (with its odometry) -> ``experience_map/pose``
    per message, and ``experience_map/map`` (the whole map) at the end of the run. The recorder
    node writes them to the run folder. Parameters: :class:`ExperienceMapConfig`'s, and
    ``map_period_s`` (> 0: also the map's nodes and links, without the export, at most this often
    in source time when it changed, for a viewer that redraws the relaxed map; 0: only at the end)."""

    inputs = (POSE_CELL_ACTION,)
    outputs = (EXPERIENCE_POSE, EXPERIENCE_MAP)

    def __init__(self, map_period_s: float = 0.0, **params: Any) -> None:
        super().__init__()
        self.em = ExperienceMap(ExperienceMapConfig(**params))
        #: the last frame integrated, and its stamp (-1: none yet)
        self.last_frame = -1
        self.last_stamp = 0.0
        self.map_period_s = float(map_period_s)
        self._map_sent: tuple[float, int, int] | None = None  # stamp, experiences, links then

    def setup(self) -> None:
        self.em.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        if msg.frame <= self.last_frame:
            # an action the map has integrated already: the pose cells re-send the frames after
            # their checkpoint when they restart after a crash; integrating them twice would move
            # the robot twice
            self.counters["replayed_skipped"] = self.counters.get("replayed_skipped", 0) + 1
            return []
        # the topic's schema guarantees finite vtrans, vrot and dt (messages from the bus are
        # validated on decoding; those from a node in the same process are ours)
        p = integrate(self.em, record_of(Action, msg.data), msg.stamp)
        self.last_frame, self.last_stamp = msg.frame, msg.stamp
        # the pose relative to its experience as well, so that the recorder can re-express the
        # whole trajectory on the final, relaxed map (trajectory_map.tum)
        out: Output = [(EXPERIENCE_POSE, msg.derive(EXPERIENCE_POSE, record_data(p)))]
        if self.map_period_s > 0:
            out.extend(self._map_now(msg.stamp))
        return out

    def _map_now(self, stamp: float) -> Output:
        """The map's nodes and links when ``map_period_s`` passed since the last ones and the map
        changed (an experience or a link more: the relaxation moved it too)."""
        sizes = (self.em.n_experiences, self.em.n_links)
        last = self._map_sent
        if last is not None and (stamp - last[0] < self.map_period_s or last[1:] == sizes):
            return []
        self._map_sent = (stamp, *sizes)
        return [(EXPERIENCE_MAP, Message(EXPERIENCE_MAP, max(self.last_frame, 0), stamp, self._arrays()))]

    def _arrays(self) -> dict[str, np.ndarray]:
        """The map as arrays: nodes (id, x, y, theta, stamp), links (from, to)."""
        em = self.em
        ids = np.asarray(em.ids, dtype=np.float64).reshape(-1, 1)
        nodes = np.hstack([ids, np.column_stack([em.x, em.y, em.th, em.stamp])]).reshape(-1, 5)
        links = np.array([lk[:2] for lk in em.links], dtype=np.int64).reshape(-1, 2)
        return {"nodes": nodes, "links": links}

    def flush(self) -> Output:
        ex = self.em.export()
        frame = max(self.last_frame, 0)
        return [(EXPERIENCE_MAP, Message(EXPERIENCE_MAP, frame, self.last_stamp, {**self._arrays(), "export": ex}))]

    def new_session(self) -> None:
        self.last_frame, self.last_stamp = -1, 0.0  # the map stays; frame numbers start again
        self.em.new_session()

    def info(self) -> dict[str, Any]:
        return {"experiences": self.em.n_experiences, "links": self.em.n_links,
                "repaired_actions": self.em.repaired_actions, "relax_ms_last": self.em.relax_time_s * 1e3,
                "solve_s_total": round(self.em.solve_s_total, 4),
                **({"experiences_merged": len(self.em.merged)} if self.em.config.prune_m > 0 else {})}

    def state_dict(self) -> dict[str, Any]:
        return {"em": self.em.state_dict(), "last_frame": self.last_frame, "last_stamp": self.last_stamp}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.em.load_state_dict(st["em"])
        self.last_frame, self.last_stamp = int(st["last_frame"]), float(st["last_stamp"])


class LocalViewNode(Node):
    """RatSLAM's local-view cells in a node: ``image`` -> ``visual_template`` (id, relative_rad,
    is_loop_closure, best_score = the match error). Parameters: :class:`LocalViewFrontEndConfig`'s."""

    inputs = (IMAGE,)
    outputs = (VISUAL_TEMPLATE,)

    def __init__(self, platform: dict[str, Any] | None = None, **params: Any) -> None:
        super().__init__()
        self.front = LocalViewFrontEnd(LocalViewFrontEndConfig(**params), PlatformConfig(**(platform or {})))

    def setup(self) -> None:
        self.front.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        return [(VISUAL_TEMPLATE, msg.derive(VISUAL_TEMPLATE, self.front.template(camera_pixels(msg.data), msg.stamp)))]

    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = {"templates": len(self.front.cells.templates)}
        if self.front.config.calibration.enabled:  # what the run settled on (report.json)
            out["calibration"] = self.front.calibration.report()
        return out

    def state_dict(self) -> dict[str, Any]:
        return self.front.state_dict()

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.front.load_state_dict(st)

    def new_session(self) -> None:
        self.front.new_session()


class VisualOdometryNode(Node):
    """RatSLAM's visual odometry in a node: ``image`` -> ``odom`` (vtrans, vrot, dt from the image
    stamps; zero motion on the first frame). Parameters: :class:`VisualOdometryConfig`'s, and
    ``speed_mps``, the platform's typical speed (``scale: platform``)."""

    inputs = (IMAGE,)
    outputs = (ODOM,)

    def __init__(self, speed_mps: float | None = None, **params: Any) -> None:
        super().__init__()
        self.vo = CameraOdometry(VisualOdometryConfig(**params), speed_mps)

    def process(self, topic: str, msg: Message) -> Output:
        vtrans, vrot, dt = self.vo.on_frame(camera_pixels(msg.data), msg.stamp)
        return [(ODOM, msg.derive(ODOM, {"vtrans": vtrans, "vrot": vrot, "dt": dt}))]

    def state_dict(self) -> dict[str, Any]:
        return self.vo.state_dict()

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.vo.load_state_dict(st)

    def new_session(self) -> None:
        self.vo.new_session()


def make_pose_cells_node(**params: Any) -> PoseCellsNode:
    return PoseCellsNode(**params)


def make_experience_map_node(**params: Any) -> ExperienceMapNode:
    return ExperienceMapNode(**params)


def make_local_view_node(**params: Any) -> LocalViewNode:
    return LocalViewNode(**params)


def make_visual_odometry_node(**params: Any) -> VisualOdometryNode:
    return VisualOdometryNode(**params)
