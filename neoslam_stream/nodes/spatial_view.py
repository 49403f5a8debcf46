"""Node of stage D: ``sdr`` -> ``visual_template`` (see ``algorithms.spatial_view``)."""

from __future__ import annotations

from typing import Any

from ..algorithms.calibration import PlatformConfig
from ..algorithms.errors import InvalidInput
from ..algorithms.frontend import TEMPLATE_KEYS
from ..algorithms.spatial_view import SpatialViewCells, SpatialViewConfig
from ..runtime.messages import Message
from ..runtime.node import Node, Output, StageInputError
from .topics import SDR, VISUAL_TEMPLATE


class SpatialViewNode(Node):
    """``sdr`` -> ``visual_template`` (template id, loop-closure flag, best interval and its score,
    the runner-up interval and its score, the current interval)."""

    inputs = (SDR,)
    outputs = (VISUAL_TEMPLATE,)

    def __init__(self, platform: dict[str, Any] | None = None, **params: Any) -> None:
        super().__init__()
        self.cells = SpatialViewCells(SpatialViewConfig(**params), platform=PlatformConfig(**(platform or {})))
        self.loops = 0

    def setup(self) -> None:
        self.cells.warm_up()

    def process(self, topic: str, msg: Message) -> Output:
        try:
            res = self.cells.compute(msg["cells"], msg.stamp)
        except InvalidInput as exc:
            raise StageInputError(str(exc)) from None
        self.loops += res["is_loop_closure"]
        # best_score as the algorithm gave it (an overlap count; a float when union_normalised):
        # templates.csv writes it unchanged
        return [(VISUAL_TEMPLATE, msg.derive(VISUAL_TEMPLATE, {k: res[k] for k in TEMPLATE_KEYS}))]

    def info(self) -> dict[str, Any]:
        out = {"intervals": self.cells.n_intervals, "indexed_intervals": len(self.cells.indexed),
               "templates": self.cells.n_templates, "loop_closures": self.loops}
        if self.cells.config.calibration.enabled:  # what the run settled on (report.json)
            out["calibration"] = self.cells.calibration.report()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"cells": self.cells.state_dict(), "loops": self.loops}

    def new_session(self) -> None:
        self.loops = 0

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.cells.load_state_dict(state["cells"])
        self.loops = int(state["loops"])


def make_node(**params: Any) -> SpatialViewNode:
    return SpatialViewNode(**params)
