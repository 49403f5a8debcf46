"""Node of stage B: ``visual_features`` -> ``bin_features`` (see ``algorithms.projector``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..algorithms.projector import N_BITS, BinaryProjector, ProjectorConfig, TorchProjection
from ..algorithms.weights import resolve_device
from ..runtime.messages import Message
from ..runtime.node import Node, Output, StageInputError
from .topics import BIN_FEATURES, VISUAL_FEATURES


class ProjectorNode(Node):
    """``visual_features`` -> ``bin_features`` (bits: sorted uint16 indices of 2048)."""

    inputs = (VISUAL_FEATURES,)
    outputs = (BIN_FEATURES,)
    batchable = True

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.config = ProjectorConfig(**params)
        self.projector: BinaryProjector | None = None
        self.torch: Any = None

    def setup(self) -> None:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(self.config.threads)
        except ImportError:
            pass
        self.projector = BinaryProjector(self.config)
        self.projector.warm_up()
        # a device other than cpu: torch there (pipelines fuse B with A instead; this is for a B
        # hosted alone, e.g. by a custom plan)
        self.torch = None
        if self.config.device != "cpu":
            dev = resolve_device(self.config.device)
            self.torch = TorchProjection(self.projector, dev) if dev != "cpu" else None

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        assert self.projector is not None
        feats = []
        for m in msgs:
            f = np.asarray(m["features"])
            if f.ndim != 1 or f.shape[0] != self.config.input_dim:
                raise StageInputError(f"features of shape {f.shape}, expected ({self.config.input_dim},)")
            if not np.all(np.isfinite(f)):
                raise StageInputError(f"features of frame {m.frame} contain NaN or infinite values")
            feats.append(f)
        bits = (self.torch or self.projector).bits_batch(np.stack(feats))
        return [(BIN_FEATURES, m.derive(BIN_FEATURES, {"bits": b, "size": N_BITS}))
                for m, b in zip(msgs, bits, strict=True)]

    def info(self) -> dict[str, Any]:
        return {"projection": self.config.projection, "input_dim": self.config.input_dim,
                "matrix": self.config.matrix_path or f"generated (seed {self.config.seed})",
                "centre_window": self.config.centre_window}

    def state_dict(self) -> dict[str, Any]:
        if self.torch is not None:
            return self.torch.state_dict()
        return self.projector.state_dict() if self.projector is not None else {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.projector is None:
            self.setup()
        assert self.projector is not None
        (self.torch or self.projector).load_state_dict(state)


def make_node(**params: Any) -> ProjectorNode:
    return ProjectorNode(**params)
