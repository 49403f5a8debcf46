"""Node of the oracle front end: ``groundtruth`` -> ``visual_template`` (see ``algorithms.oracle``).

Hosted instead of A, B, C and D by the ``oracle`` pipeline (`neoslam run --oracle-templates`): the
back end then maps with template ids derived from ground truth.
"""

from __future__ import annotations

from typing import Any

from ..algorithms.oracle import OracleConfig, OracleTemplates
from ..algorithms.records import Template
from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .topics import GROUNDTRUTH, VISUAL_TEMPLATE


class OracleNode(Node):
    """``groundtruth`` -> ``visual_template`` (template id, loop-closure flag, distance to the
    matched template's place as its score, the runner-up's distance). Parameters: :class:`OracleConfig`'s."""

    inputs = (GROUNDTRUTH,)
    outputs = (VISUAL_TEMPLATE,)

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.oracle = OracleTemplates(OracleConfig(**params))
        self.loops = 0

    def process(self, topic: str, msg: Message) -> Output:
        res = self.oracle.compute(msg["pose"])
        self.loops += res["is_loop_closure"]
        data: Template = {"id": res["id"], "is_loop_closure": res["is_loop_closure"], "best_interval": -1,
                          "relative_rad": 0.0, "best_score": res["best_score"]}
        if res["second_score"] is not None:
            data["second_score"] = res["second_score"]
        if res["is_loop_closure"]:  # the nearer the place, the surer (records.Template.confidence)
            data["confidence"] = self.oracle.radius - float(res["best_score"])
        return [(VISUAL_TEMPLATE, msg.derive(VISUAL_TEMPLATE, data))]

    def info(self) -> dict[str, Any]:
        return {"templates": self.oracle.n_templates, "loop_closures": self.loops,
                "radius_m": self.oracle.radius}

    def state_dict(self) -> dict[str, Any]:
        return {"oracle": self.oracle.state_dict(), "loops": self.loops}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.oracle.load_state_dict(state["oracle"])
        self.loops = int(state["loops"])

    def new_session(self) -> None:
        self.loops = 0


def make_node(**params: Any) -> OracleNode:
    return OracleNode(**params)
