"""Named pipelines: which nodes a run hosts, in which order, and the topic that ends a frame.

The runtime reaches algorithms only through the dotted factory paths of these plans: the
supervisor groups the :class:`NodeSpec` lists into worker processes and the workers import the
factories. The in-process API (``neoslam_stream.api``) hosts the same plans in one process.
"""

from __future__ import annotations

from typing import Any

from ..config import FullRunConfig, load_config
from ..runtime.config import RunConfig
from ..runtime.node import NodeSpec
from ..runtime.plan import PipelinePlan
from .chain import neoslam_chain
from .run_folder import mcap_params
from .topics import (
    ALGORITHM_TOPICS,
    BIN_FEATURES,
    EXPERIENCE_MAP,
    EXPERIENCE_POSE,
    POSE_CELL_ACTION,
    SDR,
    VISUAL_FEATURES,
    VISUAL_TEMPLATE,
)

FRONT_END_NODE = "neoslam_stream.nodes.frontend:make_node"
RECORDER = "neoslam_stream.nodes.recorder:make_node"
RATSLAM_NODES = "neoslam_stream.nodes.ratslam"
ROS2_OUT = "neoslam_stream.nodes.ros2_out:make_node"
#: the recorder reads these; it must not lose a row when the experience map's worker is busy
RECORDER_CAPACITY = {"visual_template": 4096, "experience_map/pose": 4096, "experience_map/map": 4}
#: the back end's input queues unless bus.capacity names them: actions are tiny, and path
#: integration must not lose one. Templates are tiny too and cost the pose cells about a millisecond:
#: a ring as deep as the templates that may wait for their odometry (PoseCellsNode.max_odom_lag)
#: rides out a stall of the cores that the stages share instead of losing the frame, and costs no
#: latency when nothing stalls
BACKEND_CAPACITY = {str(POSE_CELL_ACTION): 256, str(VISUAL_TEMPLATE): 64}


def build_emulated(cfg: FullRunConfig) -> PipelinePlan:
    from ..runtime.emulated import EMULATED, emulated_pipeline

    specs = emulated_pipeline(cfg.emulated.tau_ms, cfg.emulated.busy)
    return PipelinePlan(specs, final_topic=f"emulated/{len(specs)}", entry_stages=[specs[0].name],
                        topics=[EMULATED])


def _backend_plan(specs: list[NodeSpec], entry_stages: list[str], source_topics: list[str],
                  capacity: dict[str, int] | None = None) -> PipelinePlan:
    """A plan that ends in the back end: a frame is done when its experience-map pose arrives."""
    return PipelinePlan(specs, final_topic=str(EXPERIENCE_POSE), entry_stages=entry_stages,
                        consumed_source_topics=source_topics, topics=list(ALGORITHM_TOPICS),
                        capacity={**BACKEND_CAPACITY, **(capacity or {})})


def batch_capacity(cfg: FullRunConfig) -> dict[str, int]:
    """The rings along the front end's path hold a whole batch unless ``bus.capacity`` names them:
    after A, B and C always, and in a real-time run the image ring before A too. After A and B: a
    stage that fell behind takes up to ``run.max_batch`` frames at once and publishes them
    together, and a ring of two behind it would evict one of the burst whenever the next stage is
    busy, losing a frame that the stages before had already paid for. After C: C turns B's burst
    into as many SDRs within a few milliseconds, and D, cheap as it is, loses its share of two cores
    for that long (a ring of two there evicted as many frames as A's at 60 FPS). Before A, in real
    time: a frame that arrives while A is busy waits instead of being evicted, and A, once free,
    takes the waiting frames as one batch; a frame is lost only when A is ``run.max_batch`` periods
    late, not two. When nothing falls behind these rings hold nothing and add no latency; where A
    cannot keep up at all, a frame waits up to ``run.max_batch`` periods before it
    (``bus.capacity: {image: 2}`` keeps the freshest frames instead). A lossless run loses nothing
    by waiting, and its image queue of two keeps A's batches at two, which cost less per frame than
    eight on a small CPU (docs/runtime.md)."""
    depth = max(cfg.bus.default_capacity, cfg.run.max_batch)
    out = {str(VISUAL_FEATURES): depth, str(BIN_FEATURES): depth, str(SDR): depth}
    if cfg.run.mode == "realtime":
        out["image"] = depth
    return out


def recorder_params(cfg: FullRunConfig) -> dict[str, Any]:
    """The recorder's parameters: with ``ros2_out.mcap``, the ROS 2 messages of outputs.mcap."""
    mcap = mcap_params(cfg.ros2_out)
    return {} if mcap is None else {"mcap": mcap}


def _backend_specs(cfg: FullRunConfig, specs: list[NodeSpec]) -> None:
    """Pose cells + experience map (+ visual odometry when the config asks for it), and the
    recorder that writes the run folder, hosted in the experience map's process."""
    if cfg.odometry == "visual":
        specs.append(NodeSpec("visual_odometry", f"{RATSLAM_NODES}:make_visual_odometry_node",
                              {**cfg.visual_odometry.model_dump(), "speed_mps": cfg.platform.speed_mps}))
    specs.append(NodeSpec("pose_cells", f"{RATSLAM_NODES}:make_pose_cells_node", cfg.pose_cells.model_dump()))
    # served to Foxglove: the map (relaxed) now and then, not only at the end (docs/foxglove.md)
    map_period = {"map_period_s": cfg.foxglove.map_period_s} if cfg.foxglove.listen else {}
    specs.append(NodeSpec("experience_map", f"{RATSLAM_NODES}:make_experience_map_node",
                          {**cfg.experience_map.model_dump(), **map_period}))
    ros = cfg.ros2_out
    specs.append(NodeSpec("recorder", RECORDER, recorder_params(cfg), host="experience_map",
                          capacity=dict(RECORDER_CAPACITY), observer=True))
    if ros.format:
        specs.append(NodeSpec("ros2_out", ROS2_OUT, {**ros.message_params(), "format": ros.format,
                                                     "domain_id": ros.domain_id},
                              host="experience_map", capacity=dict(RECORDER_CAPACITY), observer=True,
                              connect=list(ros.connect)))


def _source_topics(cfg: FullRunConfig) -> list[str]:
    """The source topics the back end reads: the source's odometry, unless the pipeline measures
    visual odometry itself (then the source's is not published: one odometry per frame)."""
    return ["image"] if cfg.odometry == "visual" else ["image", "odom"]


def front_end_specs(cfg: FullRunConfig) -> list[NodeSpec]:
    """One node per stage of the NeoSLAM chain (``nodes/chain.py``), each with its stage's
    sections of the front end's config, "auto" decided here, once per run."""
    resolved = cfg.front_end().resolved()
    # a stage's thread budget is its first section's ``threads`` (A's features, B's projector)
    return [NodeSpec(stage.name, FRONT_END_NODE,
                     {"call": stage.call, **{k: getattr(resolved, k).model_dump() for k in stage.sections}},
                     threads=getattr(getattr(resolved, stage.sections[0]), "threads", 1))
            for stage in neoslam_chain(resolved)]


def build_neoslam(cfg: FullRunConfig) -> PipelinePlan:
    """NeoSLAM: A (features), B (projector), C (neocortex), D (spatial-view cells), RatSLAM back end."""
    specs = front_end_specs(cfg)
    _backend_specs(cfg, specs)
    return _backend_plan(specs, ["A"], _source_topics(cfg), batch_capacity(cfg))


def build_ratslam(cfg: FullRunConfig) -> PipelinePlan:
    """The baseline: RatSLAM's local-view cells instead of NeoSLAM's front end."""
    specs = [NodeSpec("local_view", f"{RATSLAM_NODES}:make_local_view_node",
                      {**cfg.local_view.model_dump(), "platform": cfg.platform.model_dump()})]
    _backend_specs(cfg, specs)
    return _backend_plan(specs, ["local_view"], _source_topics(cfg))


def oracle_params(cfg: FullRunConfig) -> dict[str, Any]:
    """The oracle's parameters, ``radius_m: null`` resolved to the experience map's spacing in
    metres (``exp_delta_pc_threshold`` pose cells of ``pc_cell_x_size``; see ``algorithms.oracle``)."""
    params = cfg.oracle.model_dump()
    if params["radius_m"] is None:
        params["radius_m"] = cfg.pose_cells.exp_delta_pc_threshold * cfg.pose_cells.pc_cell_x_size
    return params


def build_oracle(cfg: FullRunConfig) -> PipelinePlan:
    """The back end with template ids from ground truth (``neoslam run --oracle-templates``): the
    oracle node replaces A, B, C and D, so the map shows what the back end makes of a perfect
    front end. Needs a source with ground truth."""
    specs = [NodeSpec("oracle", "neoslam_stream.nodes.oracle:make_node", oracle_params(cfg))]
    _backend_specs(cfg, specs)
    return _backend_plan(specs, ["oracle"], ["groundtruth", "odom"])


RATSLAM_BRANCH_TOPICS = (VISUAL_TEMPLATE, POSE_CELL_ACTION, EXPERIENCE_POSE, EXPERIENCE_MAP)
#: the topics the back end's nodes publish (a branch's own stages publish them under its prefix)
BACK_END_OUTPUTS = {"pose_cells": (POSE_CELL_ACTION,), "experience_map": (EXPERIENCE_POSE, EXPERIENCE_MAP)}
#: the paper-profile branch of ``neoslam compare``: its config, node prefix, topic prefix, sub-folder
PAPER_PROFILE, PAPER_PREFIX, PAPER_DIR = "paper", "pp_", "paper"


def _branch(specs: list[NodeSpec], prefix: str, remap: dict[str, str], subdir: str) -> list[NodeSpec]:
    """``specs`` renamed ``<prefix><name>``, their topics remapped, their files in ``subdir``; a
    branch reuses the run's odometry (no visual odometry of its own)."""
    out = []
    for spec in specs:
        if spec.factory.endswith("make_visual_odometry_node"):  # one odometry for every branch
            continue
        if spec.factory == ROS2_OUT:  # the ROS 2 topics carry the run's own NeoSLAM outputs
            continue
        spec.name = f"{prefix}{spec.name}"
        spec.remap = dict(remap)
        spec.output_subdir = subdir
        if spec.host:
            spec.host = f"{prefix}{spec.host}"
            spec.capacity = {remap.get(t, t): c for t, c in spec.capacity.items()}
        out.append(spec)
    return out


def paper_profile_config(cfg: FullRunConfig) -> FullRunConfig:
    """``cfg`` with every algorithm section of the paper's profile (``configs/paper.yaml``): the
    run, bus and source sections, the odometry choice and the Foxglove viewer stay ``cfg``'s."""
    paper = load_config(PAPER_PROFILE)
    algo = set(type(cfg).model_fields) - set(RunConfig.model_fields) - {"odometry", "foxglove"}
    return cfg.model_copy(update={k: getattr(paper, k) for k in algo})


def paper_branch(cfg: FullRunConfig, plan: PipelinePlan) -> list[NodeSpec]:
    """The NeoSLAM nodes of the paper's profile beside ``plan``'s (the run's config): the stages
    whose parameters, and whose upstream stages' parameters, are the same are shared (A's CNN runs
    once when only D differs); the first stage that differs and all after it run again as
    ``pp_<stage>``, publishing under ``paper/...``, with their own recorder writing into
    ``RUN_DIR/paper/``. Empty when the two profiles are the same."""
    paper = paper_profile_config(cfg)
    pp = build_neoslam(paper)
    outputs = {**{s.name: (s.gives,) for s in neoslam_chain(paper.front_end().resolved())}, **BACK_END_OUTPUTS}
    mine = {s.name: s for s in plan.stages}
    own: list[NodeSpec] = []
    shared = True
    for spec in pp.stages:
        if spec.factory.endswith("make_visual_odometry_node"):
            continue
        if shared and spec.name in outputs and spec.name in mine and mine[spec.name].params == spec.params:
            continue  # the same stage on the same input: its output serves both branches
        shared = False
        own.append(spec)
    if all(s.name == "recorder" for s in own):
        return []
    remap = {str(t): f"{PAPER_DIR}/{t}" for s in own for t in outputs.get(s.name, ())}
    return _branch(own, PAPER_PREFIX, remap, PAPER_DIR)


def build_compare(cfg: FullRunConfig) -> PipelinePlan:
    """NeoSLAM with the run's config, NeoSLAM with the paper's profile and the RatSLAM baseline in
    one run: the image (and odometry) topics fan out to every branch.

    The paper branch's own nodes are prefixed ``pp_`` (see :func:`paper_branch`); the RatSLAM
    branch's nodes are prefixed ``rs_``, publish under ``ratslam/...`` and write their files into
    ``<run folder>/ratslam/``.
    """
    plan = build_neoslam(cfg)
    rs = build_ratslam(cfg)
    paper = paper_branch(cfg, plan)
    plan.stages += paper
    # the paper branch's own rings after A, B and C (its A reads the run's image ring)
    plan.capacity.update({f"{PAPER_DIR}/{t}": c for t, c in batch_capacity(cfg).items() if t != "image"})
    plan.stages += _branch(rs.stages, "rs_", {str(t): f"ratslam/{t}" for t in RATSLAM_BRANCH_TOPICS}, "ratslam")
    return plan


#: pipeline name -> builder(config) -> PipelinePlan
PIPELINES: dict[str, Any] = {
    "emulated": build_emulated,
    "neoslam": build_neoslam,
    "ratslam": build_ratslam,
    "oracle": build_oracle,
    "compare": build_compare,
}


def build_plan(cfg: FullRunConfig) -> PipelinePlan:
    """The plan of ``cfg.run.pipeline`` with the per-stage thread budgets of ``cfg.run.threads``."""
    try:
        builder = PIPELINES[cfg.run.pipeline]
    except KeyError:
        raise ValueError(f"unknown pipeline {cfg.run.pipeline!r}; known: {sorted(PIPELINES)}") from None
    plan = builder(cfg)
    for spec in plan.stages:
        spec.threads = cfg.run.threads.get(spec.name, spec.threads)
    return plan
