"""Node of stage C: ``bin_features`` -> ``sdr`` (see ``algorithms.neocortex``)."""

from __future__ import annotations

from typing import Any

from ..algorithms.errors import InvalidInput
from ..algorithms.neocortex import Neocortex, NeocortexConfig
from ..runtime.messages import Message
from ..runtime.node import Node, Output, StageInputError
from .topics import BIN_FEATURES, SDR


class NeocortexNode(Node):
    """``bin_features`` -> ``sdr`` (winner cells, size 65536, anomaly)."""

    inputs = (BIN_FEATURES,)
    outputs = (SDR,)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.neocortex = Neocortex(NeocortexConfig(**params))

    def setup(self) -> None:
        self.neocortex.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        bits = msg["bits"]
        if int(msg["size"]) != self.neocortex.config.columns:
            raise StageInputError(f"bin_features of size {msg['size']}, the neocortex has "
                                  f"{self.neocortex.config.columns} columns")
        try:
            cells = self.neocortex.compute(bits)
        except InvalidInput as exc:
            raise StageInputError(str(exc)) from None
        return [(SDR, msg.derive(SDR, {"cells": cells, "size": self.neocortex.n_cells,
                                       "anomaly": float(self.neocortex.anomaly)}))]

    def info(self) -> dict[str, Any]:
        n = self.neocortex
        return {"segments": n.tm.segments, "synapses": n.tm.synapses, "steps": n.steps,
                "mean_anomaly": n.anomaly_sum / n.steps if n.steps else None,
                "tie_break": n.config.tie_break}

    def state_dict(self) -> dict[str, Any]:
        return self.neocortex.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.neocortex.load_state_dict(state)


def make_node(**params: Any) -> NeocortexNode:
    return NeocortexNode(**params)
