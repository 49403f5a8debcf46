"""Stage adapters of the RatSLAM back end and baseline front end.

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

import json
import math
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from neoslam_stream.messages import Message
from neoslam_stream.stage import Output, StageAdapter, StageInputError

from ..imaging import decode_grey, decode_rgb
from .experience_map import ExperienceMap, _relax
from .local_view import LocalViewCells, _best_match
from .pose_cells import PoseCellNetwork
from .visual_odometry import VisualOdometry


class PoseCellsStage(StageAdapter):
    """Pose cells in a stage: ``visual_template`` + ``odom`` -> one ``pose_cells/action`` per odometry.

    ``max_odom_lag``: how many odometry (or template) messages may wait for their partner before
    the oldest is processed without it; other parameters are :class:`PoseCellConfig`'s.
    """

    inputs = ("visual_template", "odom")
    outputs = ("pose_cells/action",)

    def __init__(self, max_odom_lag: int = 64, **params: Any) -> None:
        super().__init__()
        self.pc = PoseCellNetwork(**params)
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
        self.pc.on_odo(vtrans, vrot, dt)
        action, src, dst, rr = self.pc.get_action()
        self.actions[action] += 1
        data = {"action": action, "src_id": src, "dst_id": dst, "relative_rad": rr,
                "vtrans": vtrans, "vrot": vrot, "dt": dt}
        base = via if via is not None else msg
        out = base.derive("pose_cells/action", data)
        out.frame, out.stamp = msg.frame, msg.stamp
        return [("pose_cells/action", out)]

    def _apply_template(self, msg: Message) -> Output:
        out: Output = []
        while self.pending and next(iter(self.pending)) < msg.frame:
            out += self._odo(self.pending.pop(next(iter(self.pending))))
        self.pc.on_view_template(int(msg["id"]), float(msg.data.get("relative_rad", 0.0)))
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
                "best_pose_cells": [round(v, 3) for v in self.pc.best]}

    def state_dict(self) -> dict[str, Any]:
        from neoslam_stream.messages import encode

        return {"pc": self.pc.state_dict(), "last_template_frame": self.last_template_frame,
                "max_odom_frame": self.max_odom_frame, "last_odom_frame": self.last_odom_frame,
                "actions": {str(k): v for k, v in self.actions.items()},
                "prev_odom_stamp": -1.0 if self.prev_odom_stamp is None else self.prev_odom_stamp,
                "pending": [np.frombuffer(encode(m), dtype=np.uint8) for m in self.pending.values()],
                "templates_waiting": [np.frombuffer(encode(m), dtype=np.uint8)
                                      for m in self.templates_waiting.values()]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        from neoslam_stream.messages import decode

        self.pc.load_state_dict(st["pc"])
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


class ExperienceMapStage(StageAdapter):
    """Experience map in a stage: ``pose_cells/action`` (with its odometry) -> ``experience_map/pose``
    per message; ``experience_map/map`` and ``map.json`` + ``trajectory.tum`` (when ``run_dir`` is
    set) at flush. Parameters: :class:`ExperienceMapConfig`'s."""

    inputs = ("pose_cells/action",)
    outputs = ("experience_map/pose", "experience_map/map")

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.em = ExperienceMap(**params)
        self.trajectory: list[tuple[int, float, float, float, float, int]] = []

    def setup(self) -> None:
        warm_up_numba()

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if self.trajectory and msg.frame <= self.trajectory[-1][0]:
            # an action the map has integrated already: the pose cells re-send the frames after
            # their checkpoint when they restart after a crash; integrating them twice would move
            # the robot twice
            self.counters["replayed_skipped"] = self.counters.get("replayed_skipped", 0) + 1
            return []
        for k in ("vtrans", "vrot", "dt"):
            if not isinstance(d.get(k), (int, float)) or isinstance(d.get(k), bool) or not math.isfinite(d[k]):
                raise StageInputError(f"pose_cells/action field {k!r} missing or not a finite number")
        self.em.on_odo(float(d["vtrans"]), float(d["vrot"]), float(d["dt"]))
        action = int(d["action"])
        if action:
            try:
                self.em.on_action(action, int(d["src_id"]), int(d["dst_id"]), float(d.get("relative_rad", 0.0)),
                                  msg.stamp)
            except ValueError as exc:
                raise StageInputError(f"inconsistent action: {exc}") from None
        x, y, th = self.em.robot_pose()
        self.trajectory.append((msg.frame, msg.stamp, x, y, th, self.em.current))
        pose = np.array([x, y, th], dtype=np.float64)
        return [("experience_map/pose", msg.derive("experience_map/pose", {"pose": pose, "exp_id": self.em.current}))]

    def flush(self) -> Output:
        ex = self.em.export()
        run_dir = getattr(self, "run_dir", None)
        if run_dir:
            write_run_outputs(Path(run_dir), ex, self.trajectory)
        nodes = np.array([[n["id"], n["x"], n["y"], n["theta"], n["stamp"]] for n in ex["nodes"]],
                         dtype=np.float64).reshape(-1, 5)
        links = np.array([[lk["from"], lk["to"]] for lk in ex["links"]], dtype=np.int64).reshape(-1, 2)
        last = self.trajectory[-1] if self.trajectory else (0, 0.0)
        return [("experience_map/map", Message("experience_map/map", last[0], last[1],
                                               {"nodes": nodes, "links": links}))]

    def new_session(self) -> None:
        self.trajectory = []  # the map stays; the path is this session's

    def info(self) -> dict[str, Any]:
        return {"experiences": self.em.n_experiences, "links": self.em.n_links,
                "repaired_actions": self.em.repaired_actions, "relax_ms_last": self.em.relax_time_s * 1e3}

    def state_dict(self) -> dict[str, Any]:
        return {"em": self.em.state_dict(), "trajectory": [list(t) for t in self.trajectory]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.em.load_state_dict(st["em"])
        self.trajectory = [(int(t[0]), float(t[1]), float(t[2]), float(t[3]), float(t[4]), int(t[5]))
                           for t in st["trajectory"]]


def write_run_outputs(run_dir: Path, export: dict[str, Any], trajectory: list) -> None:
    """map.json and trajectory.tum (one experience-map pose per frame, TUM: t x y z qx qy qz qw)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    from neoslam_stream.evaluation import write_tum

    (run_dir / "map.json").write_text(json.dumps(export))
    write_tum(run_dir / "trajectory.tum", [(stamp, x, y, th) for _f, stamp, x, y, th, _e in trajectory])


def camera_pixels(msg: Message) -> np.ndarray:
    """The frame as OpenRatSLAM reads it: grey frames as HxW, colour frames as HxWx3 (the RatSLAM
    stages sum the channels as the C++ does, rather than using luma weights)."""
    raw = msg.data.get("image")
    if raw is not None and np.asarray(raw).ndim == 2:
        return decode_grey(msg)
    return decode_rgb(msg)


class LocalViewStage(StageAdapter):
    """RatSLAM's local-view cells in a stage: ``image`` -> ``visual_template`` (id, relative_rad,
    is_loop_closure, best_score = the match error); ``templates.csv`` at flush when ``run_dir`` is
    set. Parameters: :class:`LocalViewConfig`'s."""

    inputs = ("image",)
    outputs = ("visual_template",)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.lv = LocalViewCells(**params)
        self.rows: list[tuple] = []
        self.prev = -1

    def setup(self) -> None:
        warm_up_numba()

    def process(self, topic: str, msg: Message) -> Output:
        grey = camera_pixels(msg)
        n_before = len(self.lv.templates)
        try:
            vt, rad = self.lv.on_image(grey)
        except ValueError as exc:
            raise StageInputError(str(exc)) from None
        # a loop closure: an existing template other than the previous one was recognised
        loop = len(self.lv.templates) == n_before and vt != self.prev
        self.prev = vt
        self.rows.append((msg.frame, msg.stamp, vt, int(loop), -1, self.lv.last_error))
        data = {"id": vt, "relative_rad": rad, "is_loop_closure": bool(loop),
                "best_score": float(self.lv.last_error) if math.isfinite(self.lv.last_error) else -1.0}
        return [("visual_template", msg.derive("visual_template", data))]

    def flush(self) -> Output:
        run_dir = getattr(self, "run_dir", None)
        if run_dir:
            from ..spatial_view import write_templates_csv

            write_templates_csv(f"{run_dir}/templates.csv", self.rows)
        return []

    def info(self) -> dict[str, Any]:
        return {"templates": len(self.lv.templates)}

    def state_dict(self) -> dict[str, Any]:
        return {"lv": self.lv.state_dict(), "prev": self.prev}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.lv.load_state_dict(st["lv"])
        self.prev = int(st["prev"])


class VisualOdometryStage(StageAdapter):
    """RatSLAM's visual odometry in a stage: ``image`` -> ``odom`` (vtrans, vrot, dt from the image
    stamps; zero motion on the first frame). Parameters: :class:`VisualOdometryConfig`'s."""

    inputs = ("image",)
    outputs = ("odom",)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.vo = VisualOdometry(**params)
        self.prev_stamp: float | None = None

    def process(self, topic: str, msg: Message) -> Output:
        img = camera_pixels(msg)
        dt = 1.0 / self.vo.cfg.camera_hz if self.prev_stamp is None else msg.stamp - self.prev_stamp
        if dt < 0:
            raise StageInputError(f"image stamp {msg.stamp} is earlier than the previous one ({self.prev_stamp})")
        try:
            res = self.vo.on_image(img, dt)
        except ValueError as exc:
            raise StageInputError(str(exc)) from None
        self.prev_stamp = msg.stamp
        vtrans, vrot = res if res is not None else (0.0, 0.0)
        return [("odom", msg.derive("odom", {"vtrans": vtrans, "vrot": vrot, "dt": dt}))]


def warm_up_numba() -> None:
    """Compile (or load from the cache) the numba kernels before the first frame is timed."""
    z = np.zeros(2)
    _relax(z.copy(), z.copy(), z.copy(), np.zeros(1, np.int64), np.ones(1, np.int64), z[:1].copy(),
           z[:1].copy(), z[:1].copy(), 1, 0.5)
    _best_match(np.zeros((1, 1, 4)), np.zeros(1, np.int64), np.zeros((1, 4)), 1, 1, False)


def make_pose_cells_stage(**params: Any) -> PoseCellsStage:
    return PoseCellsStage(**params)


def make_experience_map_stage(**params: Any) -> ExperienceMapStage:
    return ExperienceMapStage(**params)


def make_local_view_stage(**params: Any) -> LocalViewStage:
    return LocalViewStage(**params)


def make_visual_odometry_stage(**params: Any) -> VisualOdometryStage:
    return VisualOdometryStage(**params)
