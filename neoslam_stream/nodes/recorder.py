"""The recorder node: writes a run's outputs from the topics, so no algorithm node writes files.

It subscribes to ``visual_template`` (templates.csv: frame -> template id, loop closures),
``experience_map/pose`` (trajectory.tum: the experience-map pose per frame) and
``experience_map/map`` (map.json: nodes and links, published once at the end of the run), and
writes them into its ``run_dir`` when the run ends. It is an observer: hosted in the experience
map's worker, it does not keep those topics off the bus. Its rows are its state, so checkpoints,
``--resume`` and crash restarts give the same files as an uninterrupted run.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..runtime.messages import Message
from ..runtime.node import Node, Output
from ..tum import write_tum
from .topics import EXPERIENCE_MAP, EXPERIENCE_POSE, VISUAL_TEMPLATE

TEMPLATES_HEADER = "frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"


def write_templates_csv(path: str | Path, rows: list) -> None:
    """templates.csv: one row per frame (frame, stamp, template id, loop closure 0/1, best interval,
    best score as the front end gave it: D's overlap count, the local view's match error)."""
    with open(path, "w") as fh:
        fh.write(TEMPLATES_HEADER)
        for r in rows:
            fh.write(f"{r[0]},{r[1]:.6f},{r[2]},{r[3]},{r[4]},{r[5]}\n")


class RecorderNode(Node):
    """Writes templates.csv, trajectory.tum and map.json into ``run_dir`` at the end of the run."""

    inputs = (VISUAL_TEMPLATE, EXPERIENCE_POSE, EXPERIENCE_MAP)
    outputs = ()
    unordered_inputs = (EXPERIENCE_MAP,)
    observer = True

    def __init__(self) -> None:
        super().__init__()
        self.templates: list[tuple[int, float, int, int, int, Any]] = []
        self.trajectory: list[tuple[int, float, float, float, float, int]] = []
        self.map_export: dict[str, Any] | None = None

    def process(self, topic: str, msg: Message) -> Output:
        d = msg.data
        if topic == VISUAL_TEMPLATE:
            self.templates.append((msg.frame, msg.stamp, int(d["id"]), int(bool(d.get("is_loop_closure", False))),
                                   int(d.get("best_interval", -1)), d.get("best_score", -1)))
        elif topic == EXPERIENCE_POSE:
            x, y, th = (float(v) for v in d["pose"])
            self.trajectory.append((msg.frame, msg.stamp, x, y, th, int(d.get("exp_id", -1))))
        else:
            self.map_export = d.get("export")
        return []

    def flush(self) -> Output:
        if not self.run_dir:
            return []
        out = Path(self.run_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_templates_csv(out / "templates.csv", self.templates)
        if self.map_export is not None:
            (out / "map.json").write_text(json.dumps(self.map_export))
        write_tum(out / "trajectory.tum", [(stamp, x, y, th) for _f, stamp, x, y, th, _e in self.trajectory])
        return []

    def info(self) -> dict[str, Any]:
        return {"template_rows": len(self.templates), "trajectory_rows": len(self.trajectory)}

    def state_dict(self) -> dict[str, Any]:
        return {"templates": [list(r) for r in self.templates], "trajectory": [list(r) for r in self.trajectory]}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        self.templates = [(int(r[0]), float(r[1]), int(r[2]), int(r[3]), int(r[4]), r[5]) for r in st["templates"]]
        self.trajectory = [(int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]), int(r[5]))
                           for r in st["trajectory"]]

    def new_session(self) -> None:
        self.templates, self.trajectory, self.map_export = [], [], None  # this session's outputs only


def make_node() -> RecorderNode:
    return RecorderNode()
