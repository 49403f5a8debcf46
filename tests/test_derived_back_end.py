"""derived_back_end: the back end's sections from the platform's physical quantities, on
hand-worked inputs (the rule and its reasoning: the function's docstring)."""

import math

import pytest

from neoslam_stream.algorithms.backend import BackEnd, BackEndConfig, derived_back_end
from neoslam_stream.algorithms.errors import InvalidInput


def test_synthetic_world_a_ring_in_a_small_area():
    # 0.3 m/s, a 23.7 m lap in a 10 m area: cell 0.3 m; 23.7 > 2.2 * 10 = 22, a ring, so headings
    # are compared over a whole turn; gate radius 0.3 * 100 = 30 m >= 10 m: off; the bias's
    # anchoring over one lap at 0.3 m/s, 23.7 / 0.3 = 79 s
    s = derived_back_end(speed_mps=0.3, shortest_loop_m=23.7, area_m=10.0)
    pc, em = s["pose_cells"], s["experience_map"]
    assert pc["pc_dim_xy"] == 21 and pc["exp_delta_pc_threshold"] == 2.0
    assert math.isclose(pc["pc_cell_x_size"], 0.3)
    bias = dict(pc["odometry_bias"])
    assert math.isclose(bias.pop("anchor_s"), 79.0)
    assert bias == {"enabled": True, "samples_from": "templates", "forget_s": 5.0, "bidirectional": False}
    assert pc["odometry_gate"]["radius_m"] == 0.0
    # experiences closer than the pose cells tell apart (2 cells of 0.3 m) merge into an earlier
    # visit's (one at least 23.7 / 0.6 s before) once they are 23.7 / 0.3 s old (map_pruning.py)
    assert em.keys() == {"relaxation", "exp_initial_em_deg", "prune_m", "prune_gap_s", "prune_age_s"}
    assert math.isclose(em["prune_m"], 0.6) and math.isclose(em["prune_gap_s"], 39.5)
    assert math.isclose(em["prune_age_s"], 79.0)
    assert em["relaxation"] == "bias_walk" and em["exp_initial_em_deg"] == 0.0


def test_tuc_corridor_there_and_back_in_a_long_area():
    # 0.4 m/s, there and back along a 167 m corridor (334 m <= 2.2 * 167 = 367.4): modulo half a
    # turn; gate 0.4 * 100 = 40 m < 167 m: on, with 0.1 m per metre driven; cell 0.4 m
    s = derived_back_end(speed_mps=0.4, shortest_loop_m=334.0, area_m=167.0)
    pc = s["pose_cells"]
    assert math.isclose(pc["pc_cell_x_size"], 0.4)
    assert pc["odometry_bias"]["bidirectional"] is True
    assert math.isclose(pc["odometry_gate"]["radius_m"], 40.0) and pc["odometry_gate"]["drift"] == 0.1
    # the bias's anchoring over the way there and back at 0.4 m/s: 835 s
    assert math.isclose(pc["odometry_bias"]["anchor_s"], 835.0)
    # the same back end when the user gives the corridor's length as the loop, but for the times
    # that follow the loop: the map's pruning (its earlier visit and settling time) and the anchoring
    other = derived_back_end(speed_mps=0.4, shortest_loop_m=167.0, area_m=167.0)
    assert math.isclose(other["pose_cells"]["odometry_bias"].pop("anchor_s"), 167.0 / 0.4)
    assert {**other["pose_cells"], "odometry_bias": {**other["pose_cells"]["odometry_bias"], "anchor_s": 835.0}} == pc
    times = ("prune_gap_s", "prune_age_s")
    assert {k: v for k, v in other["experience_map"].items() if k not in times} == \
        {k: v for k, v in s["experience_map"].items() if k not in times}
    assert math.isclose(other["experience_map"]["prune_age_s"], 167.0 / 0.4)


def test_ring_boundary_and_gate_boundary():
    # 2.2 * 10 = 22: a loop of exactly 22 m is not yet a ring
    assert derived_back_end(1.0, 22.0, 10.0)["pose_cells"]["odometry_bias"]["bidirectional"] is True
    assert derived_back_end(1.0, 22.1, 10.0)["pose_cells"]["odometry_bias"]["bidirectional"] is False
    # 0.5 m/s * 100 s = 50 m: off in a 50 m area, on (50 m) in a 50.5 m one
    assert derived_back_end(0.5, 10.0, 50.0)["pose_cells"]["odometry_gate"]["radius_m"] == 0.0
    assert math.isclose(derived_back_end(0.5, 10.0, 50.5)["pose_cells"]["odometry_gate"]["radius_m"], 50.0)


def test_defaults_are_the_platform_defaults_and_the_sections_build_a_back_end():
    s = derived_back_end()
    assert s == derived_back_end(speed_mps=0.5, shortest_loop_m=10.0, area_m=50.0)
    be = BackEnd(BackEndConfig.model_validate(s))
    # 0.5 m/s * 100 s = 50 m in a 50 m area: the gate is off; a 10 m loop in it may go either way
    assert be.pose_cells.bias.enabled and be.pose_cells.bias.config.bidirectional
    assert not be.pose_cells.gate.enabled
    pose = be.step(0, 0.0, 0.5, 0.0, 0.1, 0.1)
    assert pose.pose.shape == (3,)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_non_positive_or_non_finite_inputs_are_refused(bad):
    for kw in ({"speed_mps": bad}, {"shortest_loop_m": bad}, {"area_m": bad}):
        with pytest.raises(InvalidInput):
            derived_back_end(**kw)
