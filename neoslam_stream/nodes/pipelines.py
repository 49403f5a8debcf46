"""Named pipelines: which nodes a run hosts, in which order, and the topic that ends a frame.

The runtime reaches algorithms only through the dotted factory paths of these plans: the
supervisor groups the :class:`NodeSpec` lists into worker processes and the workers import the
factories. The in-process API (``neoslam_stream.api``) hosts the same plans in one process.
"""

from __future__ import annotations

from typing import Any

from ..runtime.node import NodeSpec
from ..runtime.topology import PipelinePlan

RECORDER = "neoslam_stream.nodes.recorder:make_node"
RATSLAM_NODES = "neoslam_stream.nodes.ratslam"
#: the recorder reads these; it must not lose a row when the experience map's worker is busy
RECORDER_CAPACITY = {"visual_template": 4096, "experience_map/pose": 4096, "experience_map/map": 4}


def build_emulated(cfg: Any) -> PipelinePlan:
    from ..runtime.emulated import emulated_pipeline

    specs = emulated_pipeline(cfg.emulated.tau_ms, cfg.emulated.busy)
    return PipelinePlan(specs, final_topic=f"emulated/{len(specs)}", entry_stages=[specs[0].name])


def _backend_specs(cfg: Any, specs: list[NodeSpec]) -> None:
    """Pose cells + experience map (+ visual odometry when the config asks for it), and the
    recorder that writes the run folder, hosted in the experience map's process."""
    if cfg.odometry == "visual":
        specs.append(NodeSpec("visual_odometry", f"{RATSLAM_NODES}:make_visual_odometry_node",
                              cfg.visual_odometry.model_dump()))
    specs.append(NodeSpec("pose_cells", f"{RATSLAM_NODES}:make_pose_cells_node", cfg.pose_cells.model_dump()))
    specs.append(NodeSpec("experience_map", f"{RATSLAM_NODES}:make_experience_map_node",
                          cfg.experience_map.model_dump()))
    specs.append(NodeSpec("recorder", RECORDER, host="experience_map", capacity=dict(RECORDER_CAPACITY),
                          observer=True))


def neoslam_feature_params(cfg: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """Stage A's and B's parameters, with ``backbone: auto`` decided here so that B knows its
    input size (the dimension of the backbone that will run)."""
    from ..algorithms.features import FEATURE_DIMS, find_alexnet_weights

    feats = cfg.features.model_dump()
    backbone = feats["backbone"]
    if backbone == "auto":
        try:
            found = find_alexnet_weights(feats["weights_path"]) is not None or feats["download_weights"]
        except FileNotFoundError:
            found = False
        backbone = "alexnet" if found else "efficientnet_lite0"
        feats["backbone"] = backbone
    proj = cfg.projector.model_dump()
    proj["input_dim"] = FEATURE_DIMS[backbone]
    return feats, proj


def build_neoslam(cfg: Any) -> PipelinePlan:
    """NeoSLAM: A (features), B (projector), C (neocortex), D (spatial-view cells), RatSLAM back end."""
    feats, proj = neoslam_feature_params(cfg)
    if proj["device"] == "auto":  # asked for explicitly (the default is cpu): torch decides
        import torch

        proj["device"] = "cuda" if torch.cuda.is_available() else "cpu"
    if proj["device"] != "cpu":
        # B in torch on a device: fused with A in one node there, so only bits leave the device
        if feats["device"] == "auto":
            feats["device"] = proj["device"]
        elif feats["device"] != proj["device"]:
            raise ValueError(f"projector.device {proj['device']} needs features.device {proj['device']} or "
                             f"auto (A and B share the device), not {feats['device']}")
        front = [NodeSpec("A", "neoslam_stream.nodes.features:make_fused_node",
                          {"features": feats, "projector": proj}, threads=cfg.features.threads)]
    else:
        front = [NodeSpec("A", "neoslam_stream.nodes.features:make_node", feats, threads=cfg.features.threads),
                 NodeSpec("B", "neoslam_stream.nodes.projector:make_node", proj, threads=cfg.projector.threads)]
    specs = front + [
        NodeSpec("C", "neoslam_stream.nodes.neocortex:make_node", cfg.neocortex.model_dump()),
        NodeSpec("D", "neoslam_stream.nodes.spatial_view:make_node", cfg.spatial_view.model_dump())]
    _backend_specs(cfg, specs)
    return PipelinePlan(specs, final_topic="experience_map/pose", entry_stages=["A"],
                        consumed_source_topics=["image", "odom"])


def build_ratslam(cfg: Any) -> PipelinePlan:
    """The baseline: RatSLAM's local-view cells instead of NeoSLAM's front end."""
    specs = [NodeSpec("local_view", f"{RATSLAM_NODES}:make_local_view_node", cfg.local_view.model_dump())]
    _backend_specs(cfg, specs)
    return PipelinePlan(specs, final_topic="experience_map/pose", entry_stages=["local_view"],
                        consumed_source_topics=["image", "odom"])


RATSLAM_BRANCH_TOPICS = ("visual_template", "pose_cells/action", "experience_map/pose", "experience_map/map")


def build_compare(cfg: Any) -> PipelinePlan:
    """NeoSLAM and the RatSLAM baseline in one run: the image (and odometry) topics fan out to both.

    The RatSLAM branch's nodes are prefixed ``rs_``, publish under ``ratslam/...`` and write their
    files into ``<run folder>/ratslam/``.
    """
    plan = build_neoslam(cfg)
    rs = build_ratslam(cfg)
    remap = {t: f"ratslam/{t}" for t in RATSLAM_BRANCH_TOPICS}
    for spec in rs.stages:
        spec.name = f"rs_{spec.name}"
        spec.remap = dict(remap)
        spec.output_subdir = "ratslam"
        if spec.host:
            spec.host = f"rs_{spec.host}"
            spec.capacity = {remap.get(t, t): c for t, c in spec.capacity.items()}
        if spec.factory.endswith("make_visual_odometry_node"):  # one odometry for both branches
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


def build_plan(cfg: Any) -> PipelinePlan:
    """The plan of ``cfg.run.pipeline`` with the per-stage thread budgets of ``cfg.run.threads``."""
    try:
        builder = PIPELINES[cfg.run.pipeline]
    except KeyError:
        raise ValueError(f"unknown pipeline {cfg.run.pipeline!r}; known: {sorted(PIPELINES)}") from None
    plan = builder(cfg)
    for spec in plan.stages:
        spec.threads = cfg.run.threads.get(spec.name, spec.threads)
    return plan
