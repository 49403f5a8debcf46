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

from ..algorithms.errors import InvalidInput
from ..algorithms.ratslam.experience_map import ExperienceMap, ExperienceMapConfig
from ..algorithms.ratslam.local_view import LocalViewCells, LocalViewConfig
from ..algorithms.ratslam.odometry_bias import YawBiasEstimator
from ..algorithms.ratslam.odometry_gate import OdometryGate
from ..algorithms.ratslam.pose_cells import PoseCellConfig, PoseCellNetwork
from ..algorithms.ratslam.visual_odometry import VisualOdometry, VisualOdometryConfig
from ..runtime.messages import Message, decode, encode
from ..runtime.node import Node, Output, StageInputError
from .camera import decode_grey, decode_rgb
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, IMAGE, ODOM, POSE_CELL_ACTION, VISUAL_TEMPLATE


class PoseCellsNode(Node):
    """Pose cells in a node: ``visual_template`` + ``odom`` -> one ``pose_cells/action`` per odometry.

    ``max_odom_lag``: how many odometry (or template) messages may wait for their partner before
    the oldest is processed without it; other parameters are :class:`PoseCellConfig`'s.
    """

    inputs = (VISUAL_TEMPLATE, ODOM)
    outputs = (POSE_CELL_ACTION,)

    def __init__(self, max_odom_lag: int = 64, **params: Any) -> None:
        super().__init__()
        self.pc = PoseCellNetwork(PoseCellConfig(**params))
        self.gate = OdometryGate(self.pc.cfg.odometry_gate)
        self.bias = YawBiasEstimator(self.pc.cfg.odometry_bias)
        self.max_odom_lag = max_odom_lag
        self.pending: OrderedDict[int, Message] = OrderedDict()  # odometry by frame
        self.templates_waiting: OrderedDict[int, Message] = OrderedDict()
        self.last_template_frame = -1
        self.max_odom_frame = -1
        self.last_odom_frame = -1
        self.actions = {0: 0, 1: 0, 2: 0, 3: 0}
        self.prev_odom_stamp: float | None = None

    def _odo(self, msg: Message, via: Message | None = None) -> Output:
        vtrans, vrot = float(msg["vtrans"]), float(msg["vrot"])
        if msg.data.get("dt") is not None:
            dt = float(msg["dt"])
        else:  # OpenRatSLAM's rule: the time since the previous odometry (the first one moves nothing)
            dt = 0.0 if self.prev_odom_stamp is None else msg.stamp - self.prev_odom_stamp
        self.prev_odom_stamp = msg.stamp
        self.last_odom_frame = max(self.last_odom_frame, msg.frame)
        if not (math.isfinite(dt) and dt >= 0):
            raise StageInputError(f"odometry dt {dt} is not a finite non-negative number")
        # with odometry_bias on, everything downstream (pose cells, gate, the experience map via the
        # action message) integrates the yaw rate less the bias estimated so far
        vrot = self.bias.correct(vrot, dt)
        self.pc.on_odo(vtrans, vrot, dt)
        if self.gate.enabled:
            self.gate.on_odo(vtrans, vrot, dt)
        action, src, dst, rr = self.pc.get_action()
        self.bias.on_action(action, dst, rr)
        self.actions[action] += 1
        data = {"action": action, "src_id": src, "dst_id": dst, "relative_rad": rr,
                "vtrans": vtrans, "vrot": vrot, "dt": dt}
        base = via if via is not None else msg
        out = base.derive(POSE_CELL_ACTION, data)
        out.frame, out.stamp = msg.frame, msg.stamp
        return [(POSE_CELL_ACTION, out)]

    def _apply_template(self, msg: Message) -> Output:
        out: Output = []
        while self.pending and next(iter(self.pending)) < msg.frame:
            out += self._odo(self.pending.pop(next(iter(self.pending))))
        vt, rel = int(msg["id"]), float(msg.data.get("relative_rad", 0.0))
        # the bias sees every recognition (samples_from: templates), the gate's refusals too: a
        # look-alike still faces the way the place was seen, and the gate needs the estimate
        self.bias.on_template(vt, rel)
        if not self.gate.enabled or self.gate.check(vt):
            self.pc.on_view_template(vt, rel)
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
        return {"templates": len(self.pc.templates), "experiences": len(self.pc.experiences),
                "actions": {str(k): v for k, v in self.actions.items()}, "pending_odom": len(self.pending),
                "gate_refused": self.gate.refused,
                **({"yaw_bias_rad_s": round(self.bias.bias, 6), "yaw_bias_samples": self.bias.samples,
                    "yaw_bias_outliers": self.bias.outliers} if self.bias.enabled else {}),
                "best_pose_cells": [round(v, 3) for v in self.pc.best]}

    def state_dict(self) -> dict[str, Any]:
        return {"pc": self.pc.state_dict(), "gate": self.gate.state_dict(), "bias": self.bias.state_dict(),
                "last_template_frame": self.last_template_frame,
                "max_odom_frame": self.max_odom_frame, "last_odom_frame": self.last_odom_frame,
                "actions": {str(k): v for k, v in self.actions.items()},
                "prev_odom_stamp": -1.0 if self.prev_odom_stamp is None else self.prev_odom_stamp,
                "pending": [np.frombuffer(encode(m), dtype=np.uint8) for m in self.pending.values()],
                "templates_waiting": [np.frombuffer(encode(m), dtype=np.uint8)
                                      for m in self.templates_waiting.values()]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.pc.load_state_dict(st["pc"])
        if "gate" in st:
            self.gate.load_state_dict(st["gate"])
        if "bias" in st:
            self.bias.load_state_dict(st["bias"])
        self.last_template_frame = int(st["last_template_frame"])
        self.max_odom_frame = int(st["max_odom_frame"])
        self.last_odom_frame = int(st.get("last_odom_frame", -1))
        self.actions = {int(k): int(v) for k, v in st.get("actions", {}).items()} or self.actions
        stamp = float(st.get("prev_odom_stamp", -1.0))
        self.prev_odom_stamp = None if stamp < 0 else stamp
        self.pending, self.templates_waiting = OrderedDict(), OrderedDict()
        for key, store in (("pending", self.pending), ("templates_waiting", self.templates_waiting)):
            for raw in st[key]:
                m = decode(np.asarray(raw, dtype=np.uint8).tobytes())
                store[m.frame] = m


    def new_session(self) -> None:
        self.pending, self.templates_waiting = OrderedDict(), OrderedDict()
        self.last_template_frame = self.max_odom_frame = self.last_odom_frame = -1
        self.prev_odom_stamp = None
        self.bias.new_session()


class ExperienceMapNode(Node):
    """Experience map in a node: ``pose_cells/action`` (with its odometry) -> ``experience_map/pose``
    per message, and ``experience_map/map`` (the whole map) at the end of the run. The recorder
    node writes them to the run folder. Parameters: :class:`ExperienceMapConfig`'s."""

    inputs = (POSE_CELL_ACTION,)
    outputs = (EXPERIENCE_POSE, EXPERIENCE_MAP)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.em = ExperienceMap(ExperienceMapConfig(**params))
        #: the last frame integrated, and its stamp (-1: none yet)
        self.last_frame = -1
        self.last_stamp = 0.0

    def setup(self) -> None:
        self.em.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if msg.frame <= self.last_frame:
            # an action the map has integrated already: the pose cells re-send the frames after
            # their checkpoint when they restart after a crash; integrating them twice would move
            # the robot twice
            self.counters["replayed_skipped"] = self.counters.get("replayed_skipped", 0) + 1
            return []
        # the topic's schema guarantees finite vtrans, vrot and dt (messages from the bus are
        # validated on decoding; those from a node in the same process are ours)
        self.em.on_odo(float(d["vtrans"]), float(d["vrot"]), float(d["dt"]))
        action = int(d["action"])
        if action:
            try:
                self.em.on_action(action, int(d["src_id"]), int(d["dst_id"]), float(d.get("relative_rad", 0.0)),
                                  msg.stamp)
            except InvalidInput as exc:
                raise StageInputError(f"inconsistent action: {exc}") from None
        x, y, th = self.em.robot_pose()
        self.last_frame, self.last_stamp = msg.frame, msg.stamp
        pose = np.array([x, y, th], dtype=np.float64)
        exp_id, *local = self.em.local_pose()
        # the pose relative to its experience as well, so that the recorder can re-express the
        # whole trajectory on the final, relaxed map (trajectory_map.tum)
        return [(EXPERIENCE_POSE, msg.derive(EXPERIENCE_POSE, {"pose": pose, "exp_id": exp_id,
                                                               "local": np.array(local, dtype=np.float64)}))]

    def flush(self) -> Output:
        ex = self.em.export()
        nodes = np.array([[n["id"], n["x"], n["y"], n["theta"], n["stamp"]] for n in ex["nodes"]],
                         dtype=np.float64).reshape(-1, 5)
        links = np.array([[lk["from"], lk["to"]] for lk in ex["links"]], dtype=np.int64).reshape(-1, 2)
        frame = max(self.last_frame, 0)
        return [(EXPERIENCE_MAP, Message(EXPERIENCE_MAP, frame, self.last_stamp,
                                         {"nodes": nodes, "links": links, "export": ex}))]

    def new_session(self) -> None:
        self.last_frame, self.last_stamp = -1, 0.0  # the map stays; frame numbers start again

    def info(self) -> dict[str, Any]:
        return {"experiences": self.em.n_experiences, "links": self.em.n_links,
                "repaired_actions": self.em.repaired_actions, "relax_ms_last": self.em.relax_time_s * 1e3}

    def state_dict(self) -> dict[str, Any]:
        return {"em": self.em.state_dict(), "last_frame": self.last_frame, "last_stamp": self.last_stamp}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.em.load_state_dict(st["em"])
        if "last_frame" in st:
            self.last_frame, self.last_stamp = int(st["last_frame"]), float(st["last_stamp"])
        elif st.get("trajectory"):  # a state saved before the recorder took the trajectory over
            self.last_frame, self.last_stamp = int(st["trajectory"][-1][0]), float(st["trajectory"][-1][1])


def camera_pixels(msg: Message) -> np.ndarray:
    """The frame as OpenRatSLAM reads it: grey frames as HxW, colour frames as HxWx3 (the RatSLAM
    stages sum the channels as the C++ does, rather than using luma weights)."""
    raw = msg.data.get("image")
    if raw is not None and np.asarray(raw).ndim == 2:
        return decode_grey(msg)
    return decode_rgb(msg)


class LocalViewNode(Node):
    """RatSLAM's local-view cells in a node: ``image`` -> ``visual_template`` (id, relative_rad,
    is_loop_closure, best_score = the match error). Parameters: :class:`LocalViewConfig`'s."""

    inputs = (IMAGE,)
    outputs = (VISUAL_TEMPLATE,)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.lv = LocalViewCells(LocalViewConfig(**params))
        self.prev = -1

    def setup(self) -> None:
        self.lv.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        grey = camera_pixels(msg)
        n_before = len(self.lv.templates)
        try:
            vt, rad = self.lv.on_image(grey)
        except InvalidInput as exc:
            raise StageInputError(str(exc)) from None
        # a loop closure: an existing template other than the previous one was recognised
        loop = len(self.lv.templates) == n_before and vt != self.prev
        self.prev = vt
        data = {"id": vt, "relative_rad": rad, "is_loop_closure": bool(loop), "best_interval": -1,
                "best_score": float(self.lv.last_error)}
        return [(VISUAL_TEMPLATE, msg.derive(VISUAL_TEMPLATE, data))]

    def info(self) -> dict[str, Any]:
        return {"templates": len(self.lv.templates)}

    def state_dict(self) -> dict[str, Any]:
        return {"lv": self.lv.state_dict(), "prev": self.prev}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.lv.load_state_dict(st["lv"])
        self.prev = int(st["prev"])


class VisualOdometryNode(Node):
    """RatSLAM's visual odometry in a node: ``image`` -> ``odom`` (vtrans, vrot, dt from the image
    stamps; zero motion on the first frame). Parameters: :class:`VisualOdometryConfig`'s."""

    inputs = (IMAGE,)
    outputs = (ODOM,)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.vo = VisualOdometry(VisualOdometryConfig(**params))
        self.prev_stamp: float | None = None

    def process(self, topic: str, msg: Message) -> Output:
        img = camera_pixels(msg)
        dt = 1.0 / self.vo.cfg.camera_hz if self.prev_stamp is None else msg.stamp - self.prev_stamp
        if dt < 0:
            raise StageInputError(f"image stamp {msg.stamp} is earlier than the previous one ({self.prev_stamp})")
        try:
            res = self.vo.on_image(img, dt)
        except InvalidInput as exc:
            raise StageInputError(str(exc)) from None
        self.prev_stamp = msg.stamp
        vtrans, vrot = res if res is not None else (0.0, 0.0)
        return [(ODOM, msg.derive(ODOM, {"vtrans": vtrans, "vrot": vrot, "dt": dt}))]


def make_pose_cells_node(**params: Any) -> PoseCellsNode:
    return PoseCellsNode(**params)


def make_experience_map_node(**params: Any) -> ExperienceMapNode:
    return ExperienceMapNode(**params)


def make_local_view_node(**params: Any) -> LocalViewNode:
    return LocalViewNode(**params)


def make_visual_odometry_node(**params: Any) -> VisualOdometryNode:
    return VisualOdometryNode(**params)
