"""What a run is made of and what it gives back.

The caller (launch) hands the runtime a :class:`PipelinePlan`: the nodes, the final topic, the
message types and the capacities; :func:`group_workers` turns it into worker processes for a
topology. :class:`RunResult` (or a :class:`RunError`) is what the run gives back;
:func:`make_run_dir` names and creates its folder.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from .config import RunConfig
from .messages import Topic
from .node import NodeSpec


@dataclass
class PipelinePlan:
    """The nodes of a run, the topic whose arrival marks a frame as done, and the image entry stages."""

    stages: list[NodeSpec]
    final_topic: str
    entry_stages: list[str] = field(default_factory=list)
    #: source topics with a consumer: the source waits for their subscribers before the first frame
    consumed_source_topics: list[str] = field(default_factory=lambda: ["image"])
    #: the message types the nodes exchange, with their schemas: every process of the run registers
    #: them at its start (the codec refuses a type nobody registered)
    topics: list[Topic] = field(default_factory=list)
    #: input queue capacity of the plan's own topics, unless ``bus.capacity`` names them
    capacity: dict[str, int] = field(default_factory=dict)


class RunError(RuntimeError):
    """A run could not start or finish; the text says which process and why."""


@dataclass
class RunResult:
    """What a finished run gives back: its folder, its report and how it ended."""

    run_dir: Path
    report: dict[str, Any]
    interrupted: bool = False
    restarts: dict[str, int] = field(default_factory=dict)
    #: the signal that interrupted the run (SIGINT, SIGTERM), if any
    signal: int | None = None


def group_workers(plan: PipelinePlan, topology: str) -> dict[str, list[NodeSpec]]:
    """Worker name -> its NodeSpecs: all in one for ``monolithic``; one each for ``pipeline``,
    except that a node with ``host`` joins the worker of the node it names."""
    if topology == "monolithic":
        return {"monolithic": list(plan.stages)}
    if topology != "pipeline":
        raise ValueError(f"unknown topology {topology!r} (pipeline or monolithic)")
    groups: dict[str, list[NodeSpec]] = {}
    for s in plan.stages:
        if s.host:
            if s.host not in groups:
                raise ValueError(f"node {s.name!r} is to be hosted by {s.host!r}, which is not before it")
            groups[s.host].append(s)
        else:
            groups[s.name] = [s]
    return groups


def make_run_dir(cfg: RunConfig, out: str | Path | None) -> tuple[str, Path]:
    """The run's name (``run.name``, else pipeline, topology and start time) and its folder
    (``out``, else ``run.out``/name), created."""
    name = cfg.run.name or f"{cfg.run.pipeline}-{cfg.run.topology}-{datetime.now():%Y%m%d-%H%M%S}"
    base = Path(out) if out is not None else Path(cfg.run.out) / name
    base.mkdir(parents=True, exist_ok=True)
    return name, base
