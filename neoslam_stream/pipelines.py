"""Named pipelines (which stages, in which order) and named sources.

The runtime reaches algorithms only through these dotted factory paths: the topology builds
``StageSpec`` lists from here and worker processes import the factories.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .config import RunConfig
from .stage import StageSpec


@dataclass
class PipelinePlan:
    """The stages of a run, the topic whose arrival marks a frame as done, and the image entry stages."""

    stages: list[StageSpec]
    final_topic: str
    entry_stages: list[str] = field(default_factory=list)


def build_emulated(cfg: RunConfig) -> PipelinePlan:
    from .emulated import emulated_pipeline

    specs = emulated_pipeline(cfg.emulated.tau_ms, cfg.emulated.busy)
    return PipelinePlan(specs, final_topic=f"emulated/{len(specs)}", entry_stages=[specs[0].name])


#: pipeline name -> builder(config) -> PipelinePlan
PIPELINES: dict[str, Any] = {
    "emulated": build_emulated,
}

#: source kind -> "module:factory"
SOURCES: dict[str, str] = {
    "emulated": "neoslam_stream.emulated:EmulatedSource",
}

FullRunConfig = RunConfig


def build_plan(cfg: RunConfig) -> PipelinePlan:
    try:
        builder = PIPELINES[cfg.run.pipeline]
    except KeyError:
        raise ValueError(f"unknown pipeline {cfg.run.pipeline!r}; known: {sorted(PIPELINES)}") from None
    plan = builder(cfg)
    for spec in plan.stages:
        spec.threads = cfg.run.threads.get(spec.name, spec.threads)
    return plan


def source_factory(kind: str) -> str:
    if ":" in kind:  # a user's own source class
        return kind
    try:
        return SOURCES[kind]
    except KeyError:
        raise ValueError(f"unknown source kind {kind!r}; known: {sorted(SOURCES)} "
                         f"(or 'package.module:Class')") from None
