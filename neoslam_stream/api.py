"""The in-process API: NeoSLAM or RatSLAM in your own Python process, one camera frame at a time.

    from neoslam_stream import NeoSLAM, load_config

    slam = NeoSLAM(load_config("default"))          # or NeoSLAM() for the same default
    for image, (v, w, dt) in my_stream:             # HxWx3 uint8 RGB (or HxW grey, or JPEG bytes)
        r = slam.step(image, odometry=(v, w, dt))
        print(r.frame, r.template_id, r.is_loop_closure, r.pose)
    slam.finish()                                   # flush; writes the run files when run_dir is set

It hosts exactly the nodes that ``neoslam run`` hosts in its worker processes (``nodes.pipelines``),
called in sequence in this process: the same code, so the same templates and poses as a lossless
run of the same frames. Benches, tests and notebooks use it; it needs no zenoh.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .runtime.local import LocalChain
from .runtime.messages import MAX_FRAME, Message

#: what a step's odometry may be: (vtrans m/s, vrot rad/s, dt s), or a mapping with those keys
Odometry = tuple[float, float, float] | dict[str, float]


@dataclass
class StepResult:
    """What one camera frame produced. ``template`` is None for a frame removed by ``frame_stride``;
    ``pose`` (x, y, theta of the experience map) is None while the back end waits for this
    frame's odometry. ``poses`` lists every pose the step produced (frames that waited included)."""

    frame: int
    stamp: float
    template: dict[str, Any] | None = None
    pose: np.ndarray | None = None
    exp_id: int | None = None
    poses: list[tuple[int, np.ndarray]] = field(default_factory=list)
    #: every (topic, data) the nodes produced for this step, in order
    outputs: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    @property
    def template_id(self) -> int | None:
        return None if self.template is None else int(self.template["id"])

    @property
    def is_loop_closure(self) -> bool:
        return bool(self.template and self.template.get("is_loop_closure"))


class _SLAM:
    """Shared by :class:`NeoSLAM` and :class:`RatSLAM`."""

    pipeline = ""

    def __init__(self, config: Any = None, run_dir: str | os.PathLike | None = None,
                 backend: bool = True) -> None:
        """``config``: a :class:`~neoslam_stream.config.FullRunConfig`, the name of a shipped
        config or a YAML path (default: ``default``, what ``neoslam run`` uses). ``run_dir``: write
        templates.csv, trajectory.tum and map.json there at :meth:`finish`. ``backend=False``:
        the front end alone (no odometry needed; results carry templates only)."""
        from .config import load_config
        from .nodes.pipelines import build_plan

        if config is None or isinstance(config, (str, Path)):
            config = load_config(config or "default")
        config = config.model_copy(deep=True)
        config.run.pipeline = self.pipeline
        self.config = config
        specs = build_plan(config).stages
        if not backend:
            specs = [s for s in specs if s.name in self._front_end]
        self.backend = backend
        self.wheel_odometry = backend and config.odometry == "wheel"
        self.chain = LocalChain(specs, run_dir)
        self.frame = -1

    _front_end: tuple[str, ...] = ()

    @property
    def nodes(self) -> dict[str, Any]:
        """The hosted nodes by name (their algorithm objects: ``nodes["D"].cells`` ...)."""
        return {n.name: n for n in self.chain.nodes}

    def step(self, image: np.ndarray | bytes, odometry: Odometry | None = None, stamp: float | None = None,
             frame: int | None = None, encoding: str | None = None) -> StepResult:
        """Process one camera frame.

        ``image``: HxWx3 uint8 (``encoding`` rgb8 by default, or bgr8), HxW uint8 grey, or JPEG /
        PNG bytes. ``odometry``: the motion since the previous frame, (vtrans m/s, vrot rad/s,
        dt s), needed by the back end unless the config uses visual odometry. ``stamp``
        (seconds) defaults to the frame number; ``frame`` to the previous frame + 1.

        Bad input raises the node's error (``StageInputError``, ``MessageError``: both
        ``ValueError``) and uses up the frame number; the next step works normally. Any other
        exception is a bug in the code, not in the input.
        """
        frame = self.frame + 1 if frame is None else int(frame)
        if frame <= self.frame:
            raise ValueError(f"frame {frame} is not after the previous frame {self.frame}")
        if frame > MAX_FRAME:
            raise ValueError(f"frame {frame} does not fit in int64")
        stamp = float(frame if stamp is None else stamp)
        self.frame = frame  # used up even if its input is refused below, like a frame lost on the bus
        out = []
        if odometry is not None and self.backend:
            if isinstance(odometry, dict):
                v, w, dt = odometry["vtrans"], odometry["vrot"], odometry.get("dt")
            else:
                v, w, dt = odometry
            data = {"vtrans": float(v), "vrot": float(w)}
            if dt is not None:
                data["dt"] = float(dt)
            out += self.chain.push("odom", Message("odom", frame, stamp, data))
        elif self.wheel_odometry:
            raise ValueError("this config integrates wheel odometry (odometry: wheel): pass "
                             "odometry=(vtrans, vrot, dt), use odometry: visual, or backend=False")
        if isinstance(image, (bytes, bytearray, memoryview)):
            data = {"compressed": bytes(image)}
        else:
            arr = np.asarray(image)
            data = {"image": arr, "encoding": encoding or ("mono8" if arr.ndim == 2 else "rgb8")}
        out += self.chain.push("image", Message("image", frame, stamp, data))
        return self._result(frame, stamp, out)

    def _result(self, frame: int, stamp: float, out: list) -> StepResult:
        res = StepResult(frame, stamp, outputs=[(t, m.data) for t, m in out])
        for t, m in out:
            if t == "visual_template" and m.frame == frame:
                res.template = dict(m.data)
            elif t == "experience_map/pose":
                res.poses.append((m.frame, np.asarray(m.data["pose"])))
                if m.frame == frame:
                    res.pose = np.asarray(m.data["pose"])
                    res.exp_id = m.data.get("exp_id")
        return res

    def finish(self) -> list[tuple[str, dict[str, Any]]]:
        """End the stream: events still waiting are processed, the map is published and, with a
        ``run_dir``, the files are written. Returns what that produced."""
        return [(t, m.data) for t, m in self.chain.finish()]

    def map(self) -> dict[str, Any]:
        """The experience map now: nodes (id, x, y, theta, stamp) and links (map.json's content)."""
        if "experience_map" not in self.nodes:
            raise ValueError("this instance runs the front end alone (backend=False): it has no map")
        return self.nodes["experience_map"].em.export()

    def info(self) -> dict[str, Any]:
        """Each node's facts (backbone that ran, templates, TM size, experiences...)."""
        return self.chain.info()

    def __enter__(self) -> _SLAM:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.finish()


class NeoSLAM(_SLAM):
    """NeoSLAM: A (features), B (projector), C (neocortex), D (spatial-view cells) and the RatSLAM
    back end (pose cells, experience map)."""

    pipeline = "neoslam"
    _front_end = ("A", "B", "C", "D")


class RatSLAM(_SLAM):
    """The baseline: RatSLAM's local-view cells and the same back end."""

    pipeline = "ratslam"
    _front_end = ("local_view",)
