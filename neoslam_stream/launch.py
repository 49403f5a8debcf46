"""A run of a named pipeline: the plan from ``nodes.pipelines`` and the source from ``sources``,
hosted by the runtime's supervisor.

The one place where the runtime (which knows no algorithm and no source module) meets the nodes
and the sources: :func:`prepare` checks the source's parameters and applies the odometry rule
before anything starts, :func:`run` runs.
"""

from __future__ import annotations

from pathlib import Path

from .config import FullRunConfig
from .runtime.share import run_share
from .runtime.topology import RunError, RunResult

__all__ = ["RunError", "RunResult", "prepare", "run"]

#: the pipelines whose back end integrates odometry (the source's, or visual odometry's)
ODOMETRY_PIPELINES = ("neoslam", "ratslam", "compare")


def prepare(cfg: FullRunConfig) -> tuple[FullRunConfig, list[str]]:
    """``cfg`` as it will run, and what to say about it at the start. Raises a ``ValueError`` (one
    line) for a source parameter the source does not take or a value it cannot use.

    The odometry rule, one for every source: a source that gives no odometry with its frames (a
    video, an image folder without ``odometry.tum``, a live camera without an odometry topic)
    makes the run measure visual odometry (``odometry: visual``), and the run says so."""
    from .sources import check_source, gives_odometry
    from .sources.params import SourceParamError

    src = cfg.source
    check_source(src.kind, src.params, files=cfg.run.stages is None or "source" in cfg.run.stages)
    notes: list[str] = []
    pipeline = cfg.run.pipeline
    if cfg.odometry == "wheel" and pipeline in (*ODOMETRY_PIPELINES, "oracle") \
            and gives_odometry(src.kind, src.params) is False:
        if pipeline == "oracle":
            raise SourceParamError(f"source {src.kind} gives no odometry: --oracle-templates needs a source "
                                   "with odometry and ground truth")
        cfg = cfg.model_copy(update={"odometry": "visual"})
        vo = cfg.visual_odometry
        scale = (f"its speed scaled to the platform's typical speed {cfg.platform.speed_mps:g} m/s"
                 if vo.scale == "platform" else f"its speed scaled by vtrans_scaling {vo.vtrans_scaling:g}")
        notes.append(f"source {src.kind} gives no odometry: this run measures visual odometry from the "
                     f"images (odometry: visual), {scale}, for a camera whose field of view is "
                     f"{vo.camera_fov_deg:g} degrees (visual_odometry.camera_fov_deg: set yours)")
    return cfg, notes


def run(cfg: FullRunConfig, run_dir: str | Path | None = None, resume: str | Path | None = None,
        map_path: str | Path | None = None) -> RunResult:
    """Run ``cfg`` to the end of its source or until interrupted; returns the report. ``resume``: a run folder to continue from its last
    complete checkpoint; ``map_path``: an exported map to start from (a new session on an old map).
    The config is :func:`prepare`'d first (a bad source parameter: a RunError, before any folder)."""
    from .nodes.pipelines import build_plan
    from .sources import source_factory, with_live_default

    cfg = with_live_default(cfg)  # a live camera runs in real time unless the mode was named
    try:
        cfg, _ = prepare(cfg)
        plan = build_plan(cfg)
        factory = source_factory(cfg.source.kind)
    except ValueError as exc:
        raise RunError(str(exc)) from None
    # run_share: all of the plan, or this host's share of a run split over hosts (run.stages)
    return run_share(cfg, plan, run_dir, resume, map_path, factory)
