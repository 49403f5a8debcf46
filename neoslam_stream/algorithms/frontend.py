"""The NeoSLAM front end as one core, A -> B -> C -> D, and RatSLAM's local view as the baseline's.

:class:`FrontEnd` turns a camera frame into a visual template: A's CNN features, B's sLSBH bits,
C's winner cells, D's template id and loop-closure flag. Each part is built on first use, so a
caller that starts from features (a bench replaying A's output) never loads torch, and each stage
can also be called alone (``features``, ``bits``, ``cells``, ``template``): the nodes of a pipeline
run call the same algorithms one stage per process. :class:`LocalViewFrontEnd` gives RatSLAM's
local-view cells the same shape. ``FrontEndConfig.resolved`` decides "auto" once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .features import FEATURE_DIMS, FeatureConfig, VisualFeatureExtractor
from .neocortex import Neocortex, NeocortexConfig
from .projector import BinaryProjector, ProjectorConfig, TorchProjection
from .ratslam.local_view import LocalViewCells, LocalViewConfig
from .spatial_view import SpatialViewCells, SpatialViewConfig
from .weights import resolve_backbone, resolve_device

#: the keys of D's result that make a frame's visual template
TEMPLATE_KEYS = ("id", "is_loop_closure", "best_interval", "relative_rad", "best_score", "second_interval",
                 "second_score", "interval")


class FrontEndConfig(BaseModel):
    """The front end's sections, as in a run's config."""

    model_config = ConfigDict(extra="forbid")

    features: FeatureConfig = Field(default_factory=FeatureConfig)
    projector: ProjectorConfig = Field(default_factory=ProjectorConfig)
    neocortex: NeocortexConfig = Field(default_factory=NeocortexConfig)
    spatial_view: SpatialViewConfig = Field(default_factory=SpatialViewConfig)

    def resolved(self) -> FrontEndConfig:
        """This config with "auto" decided, once for every caller: A's backbone (AlexNet when its
        weights are found, else EfficientNet-Lite0), B's input size n from it, and B's torch
        device; a B on a device shares it with A (only bits leave the device)."""
        feats = self.features.model_copy(update={"backbone": resolve_backbone(self.features)})
        device = resolve_device(self.projector.device) if self.projector.device == "auto" else self.projector.device
        if device != "cpu":
            if feats.device == "auto":
                feats = feats.model_copy(update={"device": device})
            elif feats.device != device:
                raise ValueError(f"projector.device {device} needs features.device {device} or auto "
                                 f"(A and B share the device), not {feats.device}")
        proj = self.projector.model_copy(update={"device": device, "input_dim": FEATURE_DIMS[feats.backbone]})
        return self.model_copy(update={"features": feats, "projector": proj})


@dataclass
class FrontEndResult:
    """What one frame produced: B's on-bits, C's winner cells and D's template (``TEMPLATE_KEYS``)."""

    bits: np.ndarray
    cells: np.ndarray
    template: dict[str, Any]


class FrontEnd:
    """Camera frames -> visual templates (stages A, B, C, D of NeoSLAM)."""

    def __init__(self, config: FrontEndConfig | None = None, **overrides: Any) -> None:
        self.config = make_config(FrontEndConfig, config, overrides).resolved()

    @cached_property
    def extractor(self) -> VisualFeatureExtractor:
        """A: image -> CNN features (loads torch)."""
        return VisualFeatureExtractor(self.config.features)

    @cached_property
    def projector(self) -> BinaryProjector:
        """B: features -> 512 on-bits of 2048 (random projection, sLSBH)."""
        return BinaryProjector(self.config.projector)

    @cached_property
    def torch_projection(self) -> TorchProjection | None:
        """B on A's torch device when ``projector.device`` is not cpu, else None."""
        if self.config.projector.device == "cpu":
            return None
        return TorchProjection(self.projector, self.extractor.device)

    @cached_property
    def neocortex(self) -> Neocortex:
        """C: on-bits -> winner cells of the Temporal Memory."""
        return Neocortex(self.config.neocortex)

    @cached_property
    def spatial_view(self) -> SpatialViewCells:
        """D: winner cells -> visual template, loop closure."""
        return SpatialViewCells(self.config.spatial_view)

    def keep(self, frame: int) -> bool:
        """``frame_stride`` s: frames 0, s, 2s, ... are processed, the others removed on purpose."""
        return frame % self.config.features.frame_stride == 0

    def features(self, rgbs: Sequence[np.ndarray]) -> np.ndarray:
        """A: HxWx3 uint8 RGB frames -> (n, feature_dim) float32."""
        return self.extractor.extract_batch(rgbs)

    def bits(self, features: np.ndarray) -> list[np.ndarray]:
        """B: (n, feature_dim) features -> each row's sorted on-bits."""
        return self.projector.bits_batch(features)

    def bits_of_frames(self, rgbs: Sequence[np.ndarray]) -> list[np.ndarray]:
        """A then B; on a torch device the features never leave it."""
        if self.torch_projection is not None:
            return self.torch_projection.bits_batch(self.extractor.extract_tensor_batch(rgbs))
        return self.bits(self.features(rgbs))

    def cells(self, bits: np.ndarray) -> np.ndarray:
        """C: one frame's on-bits -> its winner cells (one learning step)."""
        return self.neocortex.compute(bits)

    def template(self, cells: np.ndarray) -> dict[str, Any]:
        """D: one frame's winner cells -> its visual template (``TEMPLATE_KEYS``)."""
        res = self.spatial_view.compute(cells)
        return {k: res[k] for k in TEMPLATE_KEYS}

    def step_bits(self, bits: np.ndarray) -> FrontEndResult:
        """C then D for one frame's on-bits."""
        cells = self.cells(bits)
        return FrontEndResult(bits, cells, self.template(cells))

    def step(self, rgb: np.ndarray, frame: int) -> FrontEndResult | None:
        """One camera frame; None for a frame that ``frame_stride`` removes."""
        if not self.keep(frame):
            return None
        return self.step_bits(self.bits_of_frames([rgb])[0])

    def warm_up(self) -> None:
        """Compile B's, C's and D's kernels before the first frame."""
        self.projector.warm_up()
        self.neocortex.warm_up()
        self.spatial_view.warm_up()


class LocalViewFrontEnd:
    """RatSLAM's local-view cells as a front end: a frame -> its visual template. A loop closure is
    an existing template other than the previous frame's."""

    def __init__(self, config: LocalViewConfig | None = None, **overrides: Any) -> None:
        self.cells = LocalViewCells(make_config(LocalViewConfig, config, overrides))
        self.prev = -1

    def template(self, pixels: np.ndarray) -> dict[str, Any]:
        """``pixels``: HxW grey or HxWx3 colour, as OpenRatSLAM reads frames."""
        n_before = len(self.cells.templates)
        vt, rad = self.cells.on_image(pixels)
        loop = len(self.cells.templates) == n_before and vt != self.prev
        self.prev = vt
        return {"id": vt, "relative_rad": rad, "is_loop_closure": bool(loop), "best_interval": -1,
                "best_score": float(self.cells.last_error)}

    def warm_up(self) -> None:
        self.cells.warm_up()

    def state_dict(self) -> dict[str, Any]:
        return {"lv": self.cells.state_dict(), "prev": self.prev}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.cells.load_state_dict(st["lv"])
        self.prev = int(st["prev"])
