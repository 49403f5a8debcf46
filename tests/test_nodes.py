"""Plans and hosting: which nodes a run has, where the recorder lives, how a chain routes."""

from __future__ import annotations

import pytest

from neoslam_stream.config import load_config
from neoslam_stream.nodes.pipelines import build_plan
from neoslam_stream.nodes.topics import ALGORITHM_TOPICS, EXPERIENCE_MAP, POSE_CELL_ACTION, VISUAL_TEMPLATE
from neoslam_stream.runtime.messages import SCHEMAS, Field, register_schema, register_topics
from neoslam_stream.runtime.topology import group_workers


def _plan(pipeline):
    return build_plan(load_config("default", {"run": {"pipeline": pipeline}}))


def test_recorder_joins_the_experience_maps_process_in_the_pipeline_topology():
    plan = _plan("neoslam")
    assert [s.name for s in plan.stages] == ["A", "B", "C", "D", "pose_cells", "experience_map", "recorder"]
    groups = group_workers(plan, "pipeline")
    assert list(groups) == ["A", "B", "C", "D", "pose_cells", "experience_map"]
    assert [s.name for s in groups["experience_map"]] == ["experience_map", "recorder"]
    assert [s.name for s in group_workers(plan, "monolithic")["monolithic"]][-1] == "recorder"


def test_compare_gives_the_ratslam_branch_its_own_recorder_on_remapped_topics():
    groups = group_workers(_plan("compare"), "pipeline")
    (rec,) = [s for s in groups["rs_experience_map"] if s.name == "rs_recorder"]
    assert rec.output_subdir == "ratslam" and rec.remap["visual_template"] == "ratslam/visual_template"
    assert set(rec.capacity) == {"ratslam/visual_template", "ratslam/experience_map/pose",
                                 "ratslam/experience_map/map"}


def test_a_node_cannot_be_hosted_by_a_later_one():
    plan = _plan("ratslam")
    plan.stages.insert(0, plan.stages.pop())  # the recorder first: its host does not exist yet
    with pytest.raises(ValueError, match="not before it"):
        group_workers(plan, "pipeline")


def test_topics_register_their_schemas_and_refuse_a_conflicting_one():
    register_topics(ALGORITHM_TOPICS)
    assert SCHEMAS["visual_template"] is not None and VISUAL_TEMPLATE == "visual_template"
    assert {"vtrans", "vrot", "dt"} <= set(SCHEMAS[POSE_CELL_ACTION])
    assert "export" in SCHEMAS[EXPERIENCE_MAP]
    register_schema("visual_template", VISUAL_TEMPLATE.schema)  # the same again: fine
    with pytest.raises(ValueError, match="already registered"):
        register_schema("visual_template", {"id": Field("str")})
