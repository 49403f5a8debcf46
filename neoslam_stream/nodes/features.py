"""Node of stage A: ``image`` -> ``visual_features`` (see ``algorithms.features``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..algorithms.features import FeatureConfig, InvalidImage, VisualFeatureExtractor
from ..runtime.messages import Message
from ..runtime.node import Node, Output, StageInputError
from .camera import decode_rgb
from .topics import IMAGE, VISUAL_FEATURES


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

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        assert self.extractor is not None
        keep, rgbs, strided = [], [], 0
        for m in msgs:
            if not self.extractor.keep(m.frame):
                strided += 1
                continue
            rgbs.append(decode_rgb(m))
            keep.append(m)
        try:
            feats = self.extractor.extract_batch(rgbs)
        except InvalidImage as exc:
            raise StageInputError(str(exc)) from None
        # counted only once the batch succeeded: the worker retries a failed batch frame by frame
        self.counters["strided"] += strided
        return [(VISUAL_FEATURES, m.derive(VISUAL_FEATURES, {"features": f, "backbone": self.extractor.backbone}))
                for m, f in zip(keep, feats, strict=True)]

    def info(self) -> dict[str, Any]:
        if self.extractor is None:
            return {}
        return {"backbone": self.extractor.backbone, "backbone_is_random": self.extractor.backbone == "random_alexnet",
                "weights": self.extractor.weights_source, "feature_dim": self.extractor.output_dim,
                "device": str(self.extractor.device), "frame_stride": self.extractor.frame_stride}


def make_node(**params: Any) -> FeatureNode:
    return FeatureNode(**params)
