"""The in-process API: NeoSLAM or RatSLAM in your own Python process, one camera frame at a time.

    from neoslam_stream import NeoSLAM, load_config

    slam = NeoSLAM(load_config("default"))          # or NeoSLAM() for the same default
    for image, (v, w, dt) in my_stream:             # HxWx3 uint8 RGB (or HxW grey, or JPEG bytes)
        r = slam.step(image, odometry=(v, w, dt))
        print(r.frame, r.template_id, r.is_loop_closure, r.pose)
    slam.finish()                                   # writes the run files when run_dir is set

It calls the two cores directly (``algorithms.frontend``, ``algorithms.backend``): the stages of
the chain declared in ``nodes/chain.py``, in that order, as the nodes of ``neoslam run`` call
them, so the same templates and poses as a lossless run of the same frames; the run folder is
written by the same writer as the recorder node's (``nodes/run_folder.py``). No zenoh.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .algorithms.backend import BackEnd, CameraOdometry
from .algorithms.errors import InvalidInput
from .algorithms.frontend import FrontEnd, LocalViewFrontEnd
from .algorithms.records import MapPose, Template
from .config import FullRunConfig
from .nodes.camera import camera_pixels, decode_rgb
from .nodes.chain import neoslam_chain, run_stage
from .nodes.run_folder import RunFolder, mcap_params
from .nodes.topics import BIN_FEATURES, SDR, VISUAL_TEMPLATE
from .runtime.messages import MAX_FRAME

#: what a step's odometry may be: (vtrans m/s, vrot rad/s, dt s), or a mapping with those keys
Odometry = tuple[float, float, float] | dict[str, float]


@dataclass
class FrontEndResult:
    """What NeoSLAM's front end made of one frame: B's on-bits, C's winner cells, D's template."""

    bits: np.ndarray
    cells: np.ndarray
    template: Template


@dataclass
class StepResult:
    """What one camera frame produced. ``template`` is None for a frame removed by ``frame_stride``
    (or with the back end alone); ``pose`` (x, y, theta of the experience map) is None without a
    back end. ``front`` holds NeoSLAM's B bits and C cells of the frame."""

    frame: int
    stamp: float
    template: Template | None = None
    pose: np.ndarray | None = None
    exp_id: int | None = None
    #: (frame, pose) of every pose the step produced
    poses: list[tuple[int, np.ndarray]] = field(default_factory=list)
    front: FrontEndResult | None = None
    #: the odometry the back end integrated, (vtrans, vrot, dt): the caller's or visual odometry's
    odometry: tuple[float, float, float | None] | None = None

    @property
    def template_id(self) -> int | None:
        return None if self.template is None else int(self.template["id"])

    @property
    def is_loop_closure(self) -> bool:
        return bool(self.template and self.template.get("is_loop_closure"))


class _SLAM:
    """Shared by :class:`NeoSLAM` and :class:`RatSLAM`."""

    pipeline = ""

    def __init__(self, config: FullRunConfig | str | Path | None = None, run_dir: str | os.PathLike | None = None,
                 backend: bool = True) -> None:
        """``config``: a :class:`~neoslam_stream.config.FullRunConfig`, the name of a shipped
        config or a YAML path (default: ``default``, what ``neoslam run`` uses). ``run_dir``: write
        templates.csv, trajectory.tum and map.json there at :meth:`finish`. ``backend=False``:
        the front end alone (no odometry needed; results carry templates only)."""
        from .config import load_config

        if config is None or isinstance(config, (str, Path)):
            config = load_config(config or "default")
        config = config.model_copy(deep=True)
        config.run.pipeline = self.pipeline
        self.config = config
        self.front_end = self._make_front_end(config)
        self.front_end.warm_up()
        self.back_end = BackEnd(config.back_end()) if backend else None
        self.camera_odometry = None
        if backend and config.odometry == "visual":
            self.camera_odometry = CameraOdometry(config.visual_odometry, config.platform.speed_mps)
        self.run_folder = None
        if self.back_end is not None:
            self.back_end.warm_up()
            if run_dir is not None:
                os.makedirs(run_dir, exist_ok=True)
                self.run_folder = RunFolder(os.fspath(run_dir), mcap=mcap_params(config.ros2_out))
        self.frame = -1
        self.last_stamp = 0.0
        self.finished = False

    def _make_front_end(self, config: FullRunConfig) -> Any:
        raise NotImplementedError

    def _template(self, data: dict[str, Any], frame: int,
                  stamp: float) -> tuple[Template | None, FrontEndResult | None]:
        raise NotImplementedError

    def step(self, image: np.ndarray | bytes, odometry: Odometry | None = None, stamp: float | None = None,
             frame: int | None = None, encoding: str | None = None) -> StepResult:
        """Process one camera frame.

        ``image``: HxWx3 uint8 (``encoding`` rgb8 by default, or bgr8), HxW uint8 grey, or JPEG /
        PNG bytes. ``odometry``: the motion since the previous frame, (vtrans m/s, vrot rad/s,
        dt s), needed by the back end unless the config uses visual odometry. ``stamp``
        (seconds) defaults to the frame number; ``frame`` to the previous frame + 1.

        Bad input (a malformed image or odometry, a frame a stage cannot use) raises
        :class:`~neoslam_stream.algorithms.errors.InvalidInput`, a ``ValueError`` naming the cause,
        and uses up the frame number; the odometry of that frame is still integrated, and the next
        step works normally. Any other exception is a bug in the code, not in the input.
        """
        data = _image_data(image, encoding)

        def front(res: StepResult) -> tuple[float, float, float | None] | None:
            res.template, res.front = self._template(data, res.frame, res.stamp)
            if self.camera_odometry is not None:
                return self.camera_odometry.on_frame(camera_pixels(data), res.stamp)
            return None

        return self._step(front, odometry, stamp, frame)

    def _step(self, front: Any, odometry: Odometry | None, stamp: float | None, frame: int | None) -> StepResult:
        """One frame: ``front(result)`` fills in its template (and returns the visual odometry, if
        any); then the back end moves by the frame's odometry."""
        if self.finished:
            raise RuntimeError("this instance has finished; build a new one")
        frame = self.frame + 1 if frame is None else int(frame)
        if frame <= self.frame:
            raise ValueError(f"frame {frame} is not after the previous frame {self.frame}")
        if frame > MAX_FRAME:
            raise ValueError(f"frame {frame} does not fit in int64")
        stamp = float(frame if stamp is None else stamp)
        self.frame = frame  # used up even if its input is refused below, like a frame lost on the bus
        odo = self._odometry(odometry)
        res = StepResult(frame, stamp)
        try:
            odo = front(res) or odo
            res.odometry = odo
        finally:  # the frame's motion happened, whatever its image was
            if self.back_end is not None and odo is not None:
                self._move(res, odo, stamp)
        return res

    def _odometry(self, odometry: Odometry | None) -> tuple[float, float, float | None] | None:
        if self.back_end is None or self.camera_odometry is not None:
            return None
        if odometry is None:
            raise ValueError("this config integrates wheel odometry (odometry: wheel): pass "
                             "odometry=(vtrans, vrot, dt), use odometry: visual, or backend=False")
        if isinstance(odometry, dict):
            v, w, dt = odometry["vtrans"], odometry["vrot"], odometry.get("dt")
        else:
            v, w, dt = odometry
        odo = (float(v), float(w), None if dt is None else float(dt))
        for name, value in zip(("vtrans", "vrot", "dt"), odo, strict=True):
            if value is not None and not math.isfinite(value):
                raise InvalidInput(f"odometry {name} {value} is not finite")
        return odo

    def _move(self, res: StepResult, odo: tuple[float, float, float | None], stamp: float) -> None:
        """The back end's step: the frame's template (if it has one), then its odometry."""
        tmpl = res.template
        p: MapPose = self.back_end.step(None if tmpl is None else int(tmpl["id"]),
                                        float(tmpl.get("relative_rad", 0.0)) if tmpl else 0.0, *odo, stamp=stamp)
        res.pose, res.exp_id = p.pose, p.exp_id
        res.poses.append((res.frame, p.pose))
        self.last_stamp = stamp
        if self.run_folder is not None:
            if tmpl is not None:
                self.run_folder.on_template(res.frame, stamp, tmpl)
            self.run_folder.on_pose(res.frame, stamp, p)

    def finish(self) -> dict[str, Any] | None:
        """End the stream; with a ``run_dir``, write the files. Returns the final map (None
        without a back end)."""
        if self.finished or self.back_end is None:
            self.finished = True
            return None if self.back_end is None else self.map()
        self.finished = True
        export = self.map()
        if self.run_folder is not None:
            self.run_folder.on_map(export)
            self.run_folder.finish()
            self.run_folder.close()
        return export

    def map(self) -> dict[str, Any]:
        """The experience map now: nodes (id, x, y, theta, stamp) and links (map.json's content)."""
        if self.back_end is None:
            raise ValueError("this instance runs the front end alone (backend=False): it has no map")
        return self.back_end.experience_map.export()

    def info(self) -> dict[str, Any]:
        """Facts about the cores (backbone that ran, templates, experiences...)."""
        out: dict[str, Any] = {}
        if isinstance(self.front_end, FrontEnd):
            if "extractor" in self.front_end.__dict__:
                out["A"] = {"backbone": self.front_end.extractor.backbone}
            d = self.front_end.spatial_view
            out["D"] = d.info()
            if d.config.calibration.enabled:  # what the run settled on
                out["D"]["calibration"] = d.calibration.report()
        elif self.front_end.config.calibration.enabled:
            out["local_view"] = {"calibration": self.front_end.calibration.report()}
        if self.back_end is not None:
            out["pose_cells"] = self.back_end.pose_cells.info()
            out["experience_map"] = {"experiences": self.back_end.experience_map.n_experiences}
        return out

    def __enter__(self) -> _SLAM:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.finish()


def _image_data(image: np.ndarray | bytes, encoding: str | None) -> dict[str, Any]:
    if isinstance(image, (bytes, bytearray, memoryview)):
        return {"compressed": bytes(image)}
    arr = np.asarray(image)
    return {"image": arr, "encoding": encoding or ("mono8" if arr.ndim == 2 else "rgb8")}


class NeoSLAM(_SLAM):
    """NeoSLAM: A (features), B (projector), C (neocortex), D (spatial-view cells) and the RatSLAM
    back end (pose cells, experience map). ``front_end`` and ``back_end`` are the two cores."""

    pipeline = "neoslam"

    def _make_front_end(self, config: FullRunConfig) -> FrontEnd:
        fe = FrontEnd(config.front_end())
        #: the stages of the chain, in order (``nodes/chain.py``)
        self.chain = neoslam_chain(fe.config)
        return fe

    def _template(self, data: dict[str, Any], frame: int,
                  stamp: float) -> tuple[Template | None, FrontEndResult | None]:
        if not self.front_end.keep(frame):
            return None, None
        x: list[Any] = [decode_rgb(data)]
        out = {}
        for stage in self.chain:
            x = run_stage(self.front_end, stage, x, [stamp])
            out[stage.gives] = x[0]
        return out[VISUAL_TEMPLATE], FrontEndResult(out[BIN_FEATURES].bits, out[SDR].cells, out[VISUAL_TEMPLATE])

    def step_cells(self, cells: np.ndarray, odometry: Odometry | None = None, stamp: float | None = None,
                   frame: int | None = None) -> StepResult:
        """A frame given by C's winner cells (a recording of C's output, when A, B and C need not
        run again): D and the back end, as :meth:`step` runs them."""
        def front(res: StepResult) -> None:
            res.template = self.front_end.template(np.asarray(cells), res.stamp)

        return self._step(front, odometry, stamp, frame)


class RatSLAM(_SLAM):
    """The baseline: RatSLAM's local-view cells and the same back end."""

    pipeline = "ratslam"

    def _make_front_end(self, config: FullRunConfig) -> LocalViewFrontEnd:
        return LocalViewFrontEnd(config.local_view, config.platform)

    def _template(self, data: dict[str, Any], frame: int,
                  stamp: float) -> tuple[Template | None, FrontEndResult | None]:
        return self.front_end.template(camera_pixels(data), stamp), None


__all__ = ["NeoSLAM", "RatSLAM", "StepResult"]
