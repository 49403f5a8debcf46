"""A run of a named pipeline: the plan from ``nodes.pipelines`` and the source from ``sources``,
hosted by the runtime's supervisor.

The one place where the runtime (which knows no algorithm and no source module) meets the nodes
and the sources.
"""

from __future__ import annotations

from pathlib import Path

from .config import FullRunConfig
from .runtime.share import run_share
from .runtime.topology import RunError, RunResult

__all__ = ["RunError", "RunResult", "run"]


def run(cfg: FullRunConfig, run_dir: str | Path | None = None, resume: str | Path | None = None,
        map_path: str | Path | None = None) -> RunResult:
    """Run ``cfg`` to the end of its source or until interrupted; returns the report. ``resume``: a run folder to continue from its last
    complete checkpoint; ``map_path``: an exported map to start from (a new session on an old map)."""
    from .nodes.pipelines import build_plan
    from .sources import source_factory, with_live_default

    cfg = with_live_default(cfg)  # a live camera runs in real time unless the mode was named
    try:
        plan = build_plan(cfg)
        factory = source_factory(cfg.source.kind)
    except ValueError as exc:
        raise RunError(str(exc)) from None
    # run_share: all of the plan, or this host's share of a run split over hosts (run.stages)
    return run_share(cfg, plan, run_dir, resume, map_path, factory)
