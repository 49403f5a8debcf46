"""The recorder node: the run folder's writer (``nodes/run_folder.py``) fed from the topics.

It turns ``visual_template``, ``experience_map/pose``, ``experience_map/map`` and ``groundtruth``
messages into calls on one :class:`~neoslam_stream.nodes.run_folder.RunFolder`, the writer the
in-process API calls directly, so no algorithm node writes files. An observer in the experience
map's worker; the writer's rows are its state, so checkpoints, ``--resume`` and crash restarts give
an uninterrupted run's files.
"""

from __future__ import annotations

from typing import Any

from ..algorithms.records import MapPose
from ..runtime.messages import Message
from ..runtime.node import Node, Output
from .run_folder import RunFolder
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, GROUNDTRUTH, VISUAL_TEMPLATE, record_of


class RecorderNode(Node):
    """Hands each message of its topics to the run folder; writes the folder's last files at the end."""

    inputs = (VISUAL_TEMPLATE, EXPERIENCE_POSE, EXPERIENCE_MAP, GROUNDTRUTH)
    outputs = ()
    unordered_inputs = (EXPERIENCE_MAP, GROUNDTRUTH)
    observer = True

    def __init__(self, mcap: dict[str, Any] | None = None) -> None:
        super().__init__()
        self.folder = RunFolder(mcap=mcap, counters=self.counters)

    # the host sets the node's folder and run id: they are the writer's
    @property  # type: ignore[override]
    def run_dir(self) -> str:
        return self.folder.run_dir

    @run_dir.setter
    def run_dir(self, value: str) -> None:
        self.folder.run_dir = value

    @property  # type: ignore[override]
    def run_id(self) -> str:
        return self.folder.run_id

    @run_id.setter
    def run_id(self, value: str) -> None:
        self.folder.run_id = value

    def process(self, topic: str, msg: Message) -> Output:
        if topic == VISUAL_TEMPLATE:
            self.folder.on_template(msg.frame, msg.stamp, msg.data)
        elif topic == GROUNDTRUTH:
            self.folder.on_groundtruth(msg.frame, msg["pose"])
        elif topic == EXPERIENCE_POSE:
            self.folder.on_pose(msg.frame, msg.stamp, record_of(MapPose, msg.data))
        elif msg.data.get("export") is not None:  # the final map (others: a viewer's, arrays only)
            self.folder.on_map(msg.data["export"])
        return []

    def flush(self) -> Output:
        self.folder.finish()
        return []

    def close(self) -> None:
        self.folder.close()

    def info(self) -> dict[str, Any]:
        return self.folder.info()

    def state_dict(self) -> dict[str, Any]:
        return self.folder.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.folder.load_state_dict(state)

    def new_session(self) -> None:
        self.folder.new_session()


def make_node(mcap: dict[str, Any] | None = None) -> RecorderNode:
    return RecorderNode(mcap)
