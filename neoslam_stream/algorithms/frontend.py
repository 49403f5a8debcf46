"""The NeoSLAM front end as one core, A -> B -> C -> D, and RatSLAM's local view as the baseline's.

:class:`FrontEnd` holds the four stages' parts and one method per stage: ``features`` (A: frames
-> CNN features), ``bits`` (B: features -> sLSBH bits; ``bits_of_frames`` is A and B on one torch
device), ``cells`` (C: bits -> winner cells), ``template`` (D: cells -> visual template). Each part
is built on first use, so a caller that starts from features (a bench replaying A's output) never
loads torch, and a process that hosts one stage builds that stage's part only. The order of the
stages is declared once, in ``neoslam_stream.nodes.chain``, from which both the pipeline's nodes
and the in-process API call these methods. :class:`LocalViewFrontEnd` gives RatSLAM's local-view
cells the same shape. ``FrontEndConfig.resolved`` decides "auto" once.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cached_property
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .calibration import CalibrationConfig, PlatformConfig, RunCalibration
from .features import FeatureConfig, VisualFeatureExtractor, feature_dim, resolve_backbone
from .neocortex import Neocortex, NeocortexConfig
from .projector import BinaryProjector, ProjectorConfig, TorchProjection
from .ratslam.local_view import LocalViewCells, LocalViewConfig
from .records import BinaryCode, Template, WinnerCells
from .spatial_view import SpatialViewCells, SpatialViewConfig
from .weights import resolve_device


class FrontEndConfig(BaseModel):
    """The front end's sections, as in a run's config."""

    model_config = ConfigDict(extra="forbid")

    features: FeatureConfig = Field(default_factory=FeatureConfig)
    projector: ProjectorConfig = Field(default_factory=ProjectorConfig)
    neocortex: NeocortexConfig = Field(default_factory=NeocortexConfig)
    spatial_view: SpatialViewConfig = Field(default_factory=SpatialViewConfig)
    #: the robot's physical quantities, from which D's calibrated decisions take their scales
    platform: PlatformConfig = Field(default_factory=PlatformConfig)

    def resolved(self) -> FrontEndConfig:
        """This config with "auto" decided, once for every caller: A's backbone (AlexNet when its
        weights are found, else EfficientNet-Lite0), B's input size n from it and A's input size, and B's torch
        device; a B on a device shares it with A (only bits leave the device)."""
        feats = self.features.model_copy(update={"backbone": resolve_backbone(self.features)})
        device = resolve_device(self.projector.device) if self.projector.device == "auto" else self.projector.device
        if device != "cpu":
            if feats.device == "auto":
                feats = feats.model_copy(update={"device": device})
            elif feats.device != device:
                raise ValueError(f"projector.device {device} needs features.device {device} or auto "
                                 f"(A and B share the device), not {feats.device}")
        n = feature_dim(feats.backbone, feats.input_size)
        proj = self.projector.model_copy(update={"device": device, "input_dim": n})
        return self.model_copy(update={"features": feats, "projector": proj})


class FrontEnd:
    """Camera frames -> visual templates (stages A, B, C, D of NeoSLAM).

    ``resolve=False`` takes the config as already resolved (``FrontEndConfig.resolved``): a node
    that hosts one stage gets only its stage's sections, resolved by the run's plan."""

    def __init__(self, config: FrontEndConfig | None = None, resolve: bool = True, **overrides: Any) -> None:
        config = make_config(FrontEndConfig, config, overrides)
        self.config = config.resolved() if resolve else config

    @cached_property
    def extractor(self) -> VisualFeatureExtractor:
        """A: image -> CNN features (loads torch)."""
        return VisualFeatureExtractor(self.config.features)

    @cached_property
    def projector(self) -> BinaryProjector:
        """B: features -> 512 on-bits of 2048 (random projection, sLSBH)."""
        return BinaryProjector(self.config.projector)

    @cached_property
    def torch_projection(self) -> TorchProjection:
        """B in torch on A's device (``projector.device`` not cpu, or a caller that asks for it)."""
        return TorchProjection(self.projector, self.extractor.device)

    @cached_property
    def neocortex(self) -> Neocortex:
        """C: on-bits -> winner cells of the Temporal Memory."""
        return Neocortex(self.config.neocortex)

    @cached_property
    def spatial_view(self) -> SpatialViewCells:
        """D: winner cells -> visual template, loop closure."""
        return SpatialViewCells(self.config.spatial_view, platform=self.config.platform)

    def keep(self, frame: int) -> bool:
        """``frame_stride`` s: frames 0, s, 2s, ... are processed, the others removed on purpose."""
        return frame % self.config.features.frame_stride == 0

    def features(self, rgbs: Sequence[np.ndarray]) -> np.ndarray:
        """A: HxWx3 uint8 RGB frames -> (n, feature_dim) float32."""
        return self.extractor.extract_batch(rgbs)

    def codes(self, features: np.ndarray) -> list[BinaryCode]:
        """B: (n, feature_dim) features -> each row's code (its sorted on-bits, and its descriptor
        when ``projector.descriptor``)."""
        return self.projector.codes_batch(features)

    def bits(self, features: np.ndarray) -> list[np.ndarray]:
        """B: (n, feature_dim) features -> each row's sorted on-bits."""
        return [c.bits for c in self.codes(features)]

    def codes_on_device(self, rgbs: Sequence[np.ndarray]) -> list[BinaryCode]:
        """A then B in torch on A's device: the features never leave it, only the codes do."""
        return self.torch_projection.codes_batch(self.extractor.extract_tensor_batch(rgbs))

    def bits_on_device(self, rgbs: Sequence[np.ndarray]) -> list[np.ndarray]:
        """A then B in torch on A's device: only the bits come back."""
        return [c.bits for c in self.codes_on_device(rgbs)]

    def bits_of_frames(self, rgbs: Sequence[np.ndarray]) -> list[np.ndarray]:
        """A then B: on the device when ``projector.device`` is not cpu."""
        if self.config.projector.device != "cpu":
            return self.bits_on_device(rgbs)
        return self.bits(self.features(rgbs))

    def cells(self, bits: np.ndarray) -> np.ndarray:
        """C: one frame's on-bits -> its winner cells (one learning step)."""
        return self.neocortex.compute(bits)

    def winner_cells(self, code: BinaryCode) -> WinnerCells:
        """C on B's code: the winner cells and the step's anomaly, the code's descriptor passed on."""
        cells = self.cells(code.bits)
        return WinnerCells(cells, self.neocortex.n_cells, float(self.neocortex.anomaly), code.descriptor)

    def template(self, cells: np.ndarray, stamp: float | None = None, descriptor: np.ndarray | None = None) -> Template:
        """D: one frame's winner cells (its stamp, seconds, and B's descriptor of it) -> its visual
        template."""
        res = self.spatial_view.compute(cells, stamp, descriptor)
        return {k: res[k] for k in Template.__annotations__ if k in res}  # type: ignore[return-value]

    def template_of(self, wc: WinnerCells, stamp: float | None = None) -> Template:
        """D on C's result."""
        return self.template(wc.cells, stamp, wc.descriptor)

    def warm_up(self, parts: Sequence[str] = ("projector", "neocortex", "spatial_view")) -> None:
        """Build ``parts`` and compile the kernels of B's, C's and D's before the first frame (A's
        backbone warms up for a batch size with ``extractor.warm_up``)."""
        for name in parts:
            part = getattr(self, name)
            if name in ("projector", "neocortex", "spatial_view"):
                part.warm_up()


class LocalViewFrontEndConfig(LocalViewConfig):
    """The ``local_view`` section: OpenRatSLAM's local-view cells plus the calibrated decision on
    loop closures (algorithms/calibration.py), the same as D's so that the comparison is fair."""

    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)


class LocalViewFrontEnd:
    """RatSLAM's local-view cells as a front end: a frame -> its visual template. A loop closure is
    an existing template other than the previous frame's.

    With ``calibration.enabled``, a template seen at least a shortest loop ago is recognised only
    when the run's own statistics say it stands out (as D's closures are); younger templates are
    matched by OpenRatSLAM's ``vt_match_threshold`` as before, which keeps the template density.
    """

    def __init__(self, config: LocalViewFrontEndConfig | None = None, platform: PlatformConfig | None = None,
                 **overrides: Any) -> None:
        self.config = make_config(LocalViewFrontEndConfig, config, overrides)
        self.cells = LocalViewCells(self.config)
        self.prev = -1
        self.frame = 0
        #: each template's creation stamp and frame
        self.created: list[tuple[float, int]] = []
        #: each template's place: itself, or the older template that confirmed evidence showed it
        #: to duplicate (as D's, SpatialViewCells._confirm_duplicates)
        self.place: list[int] = []
        self.calibration = RunCalibration(self.config.calibration, platform or PlatformConfig())
        #: set by :meth:`new_session` until the session's first frame: the old sessions' last stamp
        self._old_last_stamp: float | None = None

    def template(self, pixels: np.ndarray, stamp: float | None = None) -> Template:
        """``pixels``: HxW grey or HxWx3 colour, as OpenRatSLAM reads frames."""
        stamp = float(self.frame if stamp is None else stamp)
        if self._old_last_stamp is not None:  # a new session's first frame: the old stamps move back
            shift = self.calibration.session_shift(self._old_last_stamp, stamp)
            self.created = [(s + shift, f) for s, f in self.created]
            self._old_last_stamp = None
        n_before = len(self.cells.templates)
        if self.config.calibration.enabled:
            vt, rad = self._calibrated(pixels, stamp)
        else:
            vt, rad = self.cells.on_image(pixels)
        if len(self.cells.templates) > n_before:
            self.created.append((stamp, self.frame))
            self.place.append(len(self.place))
        loop = len(self.cells.templates) == n_before and vt != self.prev
        self.prev = vt
        self.frame += 1
        out: Template = {"id": vt, "relative_rad": rad, "is_loop_closure": bool(loop), "best_interval": -1,
                         "best_score": float(self.cells.last_error)}
        # what the decision was sure of (records.Template.confidence); none for a match to a young
        # template under the calibrated decision (OpenRatSLAM's rule decided it, on another scale)
        if loop and not self.config.calibration.enabled:
            out["confidence"] = float(self.config.vt_match_threshold - self.cells.last_error)
        elif loop and self.calibration.evidence >= 0:  # the calibrated decision accepted it
            out["confidence"] = float(self.calibration.evidence)
        return out

    def _calibrated(self, pixels: np.ndarray, stamp: float) -> tuple[int, float]:
        cells, cal = self.cells, self.calibration
        cal.on_stamp(stamp)
        t = cells.view_template(pixels)
        err, rad = cells.errors(t)
        born = np.array([c[0] for c in self.created], dtype=np.float64)
        old = np.flatnonzero(born <= stamp - cal.min_gap_s)
        recent = None if self.prev < 0 else -float(err[self.prev])
        a = cal.assess(-err[old], born[old], recent) if old.size else None
        matched = int(old[a.best]) if a is not None else -1
        ref = self.created[self.place[matched]][1] if a is not None else -1  # the place's first frame
        closure = cal.accept(self.frame, ref, a.confidence if a is not None else -np.inf)
        cal.frame_done()
        if closure:
            k = matched
            for dup, m in cal.confirmed(self.frame):  # the revisit is confirmed: see SpatialViewCells
                self.place[dup] = self.place[m]
        else:  # OpenRatSLAM's rule among the templates too young to be a loop closure
            young = np.setdiff1d(np.arange(err.shape[0]), old)
            k = int(young[np.argmin(err[young])]) if young.size else -1
            if k >= 0 and err[k] > self.config.vt_match_threshold:
                k = -1
        if k < 0:
            cells.last_error = float(err.min()) if err.size else float("inf")
            cells.current_id, cells.relative_rad = cells.add_template(t), 0.0
            if matched >= 0:
                cal.on_new_template(self.frame, cells.current_id, matched)
            return cells.current_id, 0.0
        cells.last_error = float(err[k])
        cells.current_id, cells.relative_rad = self.place[k], float(rad[k])
        return cells.current_id, cells.relative_rad

    def warm_up(self) -> None:
        self.cells.warm_up()

    def new_session(self) -> None:
        """A new session on a stored map: as D's (SpatialViewCells.new_session), the templates'
        creation stamps move back at its first frame to end a shortest loop before it."""
        if self.created:
            last = self.calibration.last_stamp
            self._old_last_stamp = float(self.created[-1][0] if last is None else last)
        self.calibration.new_session()
        self.prev = -1

    def state_dict(self) -> dict[str, Any]:
        return {"lv": self.cells.state_dict(), "prev": self.prev, "frame": self.frame,
                "created": [[s, f] for s, f in self.created], "calibration": self.calibration.state_dict(),
                "place": list(self.place)}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.cells.load_state_dict(st["lv"])
        self.prev = int(st["prev"])
        self.frame = int(st["frame"])
        self.created = [(float(s), int(f)) for s, f in st["created"]]
        self.place = [int(x) for x in st["place"]]
        self.calibration.load_state_dict(st["calibration"])
