"""Named pipelines (which stages, in which order) and named sources.

The runtime reaches algorithms only through these dotted factory paths: the topology builds
``StageSpec`` lists from here and worker processes import the factories.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pydantic import Field

from stages.features import FeatureConfig
from stages.neocortex import NeocortexConfig
from stages.projector import ProjectorConfig
from stages.ratslam.experience_map import ExperienceMapConfig
from stages.ratslam.local_view import LocalViewConfig
from stages.ratslam.pose_cells import PoseCellConfig
from stages.ratslam.visual_odometry import VisualOdometryConfig
from stages.spatial_view import SpatialViewConfig

from .config import RunConfig
from .stage import StageSpec


class FullRunConfig(RunConfig):
    """The runtime's sections plus every algorithm's (defaults = the paper's / reference code's)."""

    features: FeatureConfig = Field(default_factory=FeatureConfig)
    projector: ProjectorConfig = Field(default_factory=ProjectorConfig)
    neocortex: NeocortexConfig = Field(default_factory=NeocortexConfig)
    spatial_view: SpatialViewConfig = Field(default_factory=SpatialViewConfig)
    pose_cells: PoseCellConfig = Field(default_factory=PoseCellConfig)
    experience_map: ExperienceMapConfig = Field(default_factory=ExperienceMapConfig)
    local_view: LocalViewConfig = Field(default_factory=lambda: LocalViewConfig(
        template_x_size=60, template_y_size=20, vt_shift_match=4, vt_step_match=1))
    visual_odometry: VisualOdometryConfig = Field(default_factory=VisualOdometryConfig)
    #: wheel: odometry from the source; visual: RatSLAM's visual odometry stage
    odometry: str = Field("wheel", pattern="^(wheel|visual)$")


@dataclass
class PipelinePlan:
    """The stages of a run, the topic whose arrival marks a frame as done, and the image entry stages."""

    stages: list[StageSpec]
    final_topic: str
    entry_stages: list[str] = field(default_factory=list)
    #: source topics with a consumer: the source waits for their subscribers before the first frame
    consumed_source_topics: list[str] = field(default_factory=lambda: ["image"])


def build_emulated(cfg: FullRunConfig) -> PipelinePlan:
    from .emulated import emulated_pipeline

    specs = emulated_pipeline(cfg.emulated.tau_ms, cfg.emulated.busy)
    return PipelinePlan(specs, final_topic=f"emulated/{len(specs)}", entry_stages=[specs[0].name])


def _backend_specs(cfg: FullRunConfig, specs: list[StageSpec]) -> None:
    """Pose cells + experience map, and visual odometry when the config asks for it."""
    if cfg.odometry == "visual":
        specs.append(StageSpec("visual_odometry", "stages.ratslam.adapters:make_visual_odometry_stage",
                               cfg.visual_odometry.model_dump()))
    specs.append(StageSpec("pose_cells", "stages.ratslam.adapters:make_pose_cells_stage",
                           cfg.pose_cells.model_dump()))
    specs.append(StageSpec("experience_map", "stages.ratslam.adapters:make_experience_map_stage",
                           cfg.experience_map.model_dump()))


def build_neoslam(cfg: FullRunConfig) -> PipelinePlan:
    """NeoSLAM: A (features), B (projector), C (neocortex), D (spatial-view cells), RatSLAM back end."""
    from stages.features import FEATURE_DIMS, find_alexnet_weights

    feats = cfg.features.model_dump()
    backbone = feats["backbone"]
    if backbone == "auto":  # decide here so that B knows its input size
        try:
            found = find_alexnet_weights(feats["weights_path"]) is not None or feats["download_weights"]
        except FileNotFoundError:
            found = False
        backbone = "alexnet" if found else "efficientnet_lite0"
        feats["backbone"] = backbone
    proj = cfg.projector.model_dump()
    proj["input_dim"] = FEATURE_DIMS[backbone]
    specs = [StageSpec("A", "stages.features:make_stage", feats, threads=cfg.features.threads),
             StageSpec("B", "stages.projector:make_stage", proj, threads=cfg.projector.threads),
             StageSpec("C", "stages.neocortex:make_stage", cfg.neocortex.model_dump()),
             StageSpec("D", "stages.spatial_view:make_stage", cfg.spatial_view.model_dump())]
    _backend_specs(cfg, specs)
    return PipelinePlan(specs, final_topic="experience_map/pose", entry_stages=["A"],
                        consumed_source_topics=["image", "odom"])


def build_ratslam(cfg: FullRunConfig) -> PipelinePlan:
    """The baseline: RatSLAM's local-view cells instead of NeoSLAM's front end."""
    specs = [StageSpec("local_view", "stages.ratslam.adapters:make_local_view_stage", cfg.local_view.model_dump())]
    _backend_specs(cfg, specs)
    return PipelinePlan(specs, final_topic="experience_map/pose", entry_stages=["local_view"],
                        consumed_source_topics=["image", "odom"])


RATSLAM_BRANCH_TOPICS = ("visual_template", "pose_cells/action", "experience_map/pose", "experience_map/map")


def build_compare(cfg: FullRunConfig) -> PipelinePlan:
    """NeoSLAM and the RatSLAM baseline in one run: the image (and odometry) topics fan out to both.

    The RatSLAM branch's stages are prefixed ``rs_``, publish under ``ratslam/...`` and write their
    files into ``<run folder>/ratslam/``.
    """
    plan = build_neoslam(cfg)
    rs = build_ratslam(cfg)
    remap = {t: f"ratslam/{t}" for t in RATSLAM_BRANCH_TOPICS}
    for spec in rs.stages:
        spec.name = f"rs_{spec.name}"
        spec.remap = dict(remap)
        spec.output_subdir = "ratslam"
        if spec.factory.endswith("make_visual_odometry_stage"):  # one odometry for both branches
            continue
        plan.stages.append(spec)
    return plan


#: pipeline name -> builder(config) -> PipelinePlan
PIPELINES: dict[str, Any] = {
    "emulated": build_emulated,
    "neoslam": build_neoslam,
    "ratslam": build_ratslam,
    "compare": build_compare,
}

#: source kind -> "module:factory"
SOURCES: dict[str, str] = {
    "emulated": "neoslam_stream.emulated:EmulatedSource",
    "synthetic": "neoslam_stream.sources.synthetic:SyntheticWorldSource",
    "folder": "neoslam_stream.sources.files:ImageFolderSource",
    "video": "neoslam_stream.sources.files:VideoSource",
    "bag": "neoslam_stream.sources.bag:BagSource",
    "zenoh-ros2": "neoslam_stream.sources.zenoh_camera:ZenohRos2CameraSource",
    "zenoh": "neoslam_stream.sources.zenoh_camera:ZenohImageSource",
}


def build_plan(cfg: FullRunConfig) -> PipelinePlan:
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
