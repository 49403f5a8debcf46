"""Experience map: dead reckoning, links and relaxation of a loop with a known error."""

import math

import pytest

from stages.ratslam.experience_map import ExperienceMap
from stages.ratslam.pose_cells import CREATE_EDGE, CREATE_NODE


def test_dead_reckoning_places_nodes():
    em = ExperienceMap(exp_initial_em_deg=0, exp_loops=0)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1.0, 0.0, 2.0)  # 2 m along +x
    em.on_action(CREATE_NODE, 0, 1, 0.0)
    assert (em.x[1], em.y[1]) == pytest.approx((2.0, 0.0))
    em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 1, 2, 0.0)
    assert (em.x[2], em.y[2]) == pytest.approx((2.0, 1.0))
    assert em.th[2] == pytest.approx(math.pi / 2)


def test_relaxation_closes_a_square_loop_with_known_error():
    em = ExperienceMap(exp_initial_em_deg=0, exp_loops=200)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    # a 1 m square driven with 10 % too long odometry on the last side
    sides = [1.0, 1.0, 1.0, 1.1]
    for k, d in enumerate(sides[:3]):
        em.on_odo(d, 0.0, 1.0)
        em.on_action(CREATE_NODE, k, k + 1, 0.0)
        em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_odo(sides[3], 0.0, 1.0)
    em.on_odo(0.0, math.pi / 2, 1.0)  # face the way the loop started, as a real revisit does
    before = math.hypot(em.robot_pose()[0], em.robot_pose()[1])
    assert before == pytest.approx(0.1, abs=1e-9)  # the dead-reckoned gap at the loop's end
    em.on_action(CREATE_EDGE, 3, 0, 0.0)  # recognised the start: close the loop
    assert len(em.links) == 4

    def residual(link):  # where the link says its end node is, versus where it is
        a, b, d, heading, _facing, _t = link
        lx = em.x[a] + d * math.cos(em.th[a] + heading)
        ly = em.y[a] + d * math.sin(em.th[a] + heading)
        return math.hypot(em.x[b] - lx, em.y[b] - ly)

    res = [residual(lk) for lk in em.links]
    # before relaxation the whole 0.1 m sat on the closing link; a loop of 4 links shares it,
    # 0.1 / 4 = 0.025 m each in the least-squares sense: no link may keep more than half of it
    assert max(res) < 0.05
    assert sum(res) == pytest.approx(0.1, abs=0.03)


def test_duplicate_links_not_created():
    em = ExperienceMap()
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    em.on_odo(1, 0, 1)
    em.on_action(CREATE_NODE, 0, 1, 0.0)
    em.on_action(CREATE_EDGE, 1, 0, 0.0)  # 1 -> 0 exists as 0 -> 1
    assert len(em.links) == 1


def test_unknown_experience_rejected():
    em = ExperienceMap()
    with pytest.raises(ValueError):
        em.on_action(CREATE_EDGE, 0, 7, 0.0)
