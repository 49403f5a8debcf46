"""Node of stage A: ``image`` -> ``visual_features`` (see ``algorithms.features``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..algorithms.errors import InvalidInput
from ..algorithms.features import FeatureConfig, InvalidImage, VisualFeatureExtractor
from ..algorithms.projector import N_BITS, BinaryProjector, ProjectorConfig, TorchProjection
from ..runtime.messages import Message
from ..runtime.node import Node, Output, StageInputError
from .camera import decode_rgb
from .topics import BIN_FEATURES, IMAGE, VISUAL_FEATURES


class FeatureNode(Node):
    """``image`` -> ``visual_features``; strided frames return nothing and are counted."""

    inputs = (IMAGE,)
    outputs = (VISUAL_FEATURES,)
    batchable = True

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.config = FeatureConfig(**params)
        self.extractor: VisualFeatureExtractor | None = None

    def setup(self) -> None:
        self.extractor = VisualFeatureExtractor(self.config)

    def warm_up(self, max_batch: int) -> None:
        assert self.extractor is not None
        self.extractor.warm_up(max_batch)

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        keep, rgbs, strided = self._decode_kept(msgs)
        try:
            feats = self.extractor.extract_batch(rgbs)
        except InvalidImage as exc:
            raise StageInputError(str(exc)) from None
        # counted only once the batch succeeded: the worker retries a failed batch frame by frame
        self.counters["strided"] += strided
        return [(VISUAL_FEATURES, m.derive(VISUAL_FEATURES, {"features": f, "backbone": self.extractor.backbone}))
                for m, f in zip(keep, feats, strict=True)]

    def _decode_kept(self, msgs: Sequence[Message]) -> tuple[list[Message], list, int]:
        """The messages ``frame_stride`` keeps, their decoded RGB frames, and how many it removed."""
        assert self.extractor is not None
        keep, rgbs, strided = [], [], 0
        for m in msgs:
            if not self.extractor.keep(m.frame):
                strided += 1
                continue
            rgbs.append(decode_rgb(m.data))
            keep.append(m)
        return keep, rgbs, strided

    def info(self) -> dict[str, Any]:
        if self.extractor is None:
            return {}
        return {"backbone": self.extractor.backbone, "backbone_is_random": self.extractor.backbone == "random_alexnet",
                "weights": self.extractor.weights_source, "feature_dim": self.extractor.output_dim,
                "device": str(self.extractor.device), "frame_stride": self.config.frame_stride}


def make_node(**params: Any) -> FeatureNode:
    return FeatureNode(**params)


class DeviceFrontEndNode(FeatureNode):
    """Stages A and B fused on one torch device: ``image`` -> ``bin_features``.

    Built instead of the separate A and B nodes when ``projector.device`` is not ``cpu``: the
    backbone's output stays on the device, B's projection and sLSBH run there
    (:class:`~neoslam_stream.algorithms.projector.TorchProjection`), and only the 512 bit indices
    of each frame come back to the host and onto the bus.
    """

    outputs = (BIN_FEATURES,)

    def __init__(self, features: dict[str, Any], projector: dict[str, Any]) -> None:
        super().__init__(**features)
        self.projector_config = ProjectorConfig(**projector)
        self.projection: Any = None

    def setup(self) -> None:
        super().setup()
        assert self.extractor is not None
        self.projection = TorchProjection(BinaryProjector(self.projector_config), self.extractor.device)

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        assert self.projection is not None
        keep, rgbs, strided = self._decode_kept(msgs)
        bits: list = []
        if rgbs:
            try:
                bits = self.projection.bits_batch(self.extractor.extract_tensor_batch(rgbs))
            except (InvalidImage, InvalidInput) as exc:
                raise StageInputError(str(exc)) from None
        self.counters["strided"] += strided
        return [(BIN_FEATURES, m.derive(BIN_FEATURES, {"bits": b, "size": N_BITS}))
                for m, b in zip(keep, bits, strict=True)]

    def info(self) -> dict[str, Any]:
        out = super().info()
        if self.projection is not None:
            out.update({"fused": "A+B on one device: only bits leave it", "projection": "gaussian (torch)",
                        "matrix_dtype": self.projector_config.matrix_dtype,
                        "centre_window": self.projector_config.centre_window})
        return out

    def state_dict(self) -> dict[str, Any]:
        return self.projection.state_dict() if self.projection is not None else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.projection is None:
            self.setup()
        self.projection.load_state_dict(state)


def make_fused_node(features: dict[str, Any], projector: dict[str, Any]) -> DeviceFrontEndNode:
    return DeviceFrontEndNode(features, projector)
