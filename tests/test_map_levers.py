"""The levers of issue #14 that the default keeps, on hand-worked cases: the sequence filter of
loop closures (algorithms.sequence, D's ``sequence`` settings) and the robust experience-map
relaxation (``exp_robust_m``)."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.pose_cells import CREATE_EDGE, CREATE_NODE
from neoslam_stream.algorithms.sequence import SequenceFilter
from neoslam_stream.algorithms.spatial_view import SpatialViewCells

# ---------------------------------------------------------------- sequence filter


def test_sequence_filter_accepts_a_consistent_run_and_refuses_an_isolated_match():
    f = SequenceFilter(length=3, max_step=2.0, slack=1)
    # frames 100..103 match reference frames 10..13: the first three build the run, the fourth
    # has three consistent predecessors (|13 - 12| <= 1*2 + 1, |13 - 11| <= 2*2 + 1, ...)
    got = [f.check(100 + i, 10 + i) for i in range(4)]
    assert got == [False, False, False, True]
    # an isolated match: frames without a candidate, then one candidate
    for t in range(104, 110):
        assert f.check(t, -1) is False
    assert f.check(110, 50) is False


def test_sequence_filter_accepts_a_revisit_in_the_other_direction():
    f = SequenceFilter(length=2, max_step=2.0, slack=0)
    assert [f.check(200 + i, 40 - i) for i in range(4)] == [False, False, True, True]


def test_sequence_filter_refuses_a_jump_and_restarts_after_it():
    f = SequenceFilter(length=2, max_step=1.0, slack=1)
    for i in range(3):
        f.check(i, 10 + i)
    # reference jumps by 30 frames: |42 - 12| > 1*1 + 1
    assert f.check(3, 42) is False
    assert f.check(4, 43) is False  # frame 2 matched 12, far from 43: still refused
    assert f.check(5, 44) is True  # frames 4 and 3 matched 43 and 42


def test_sequence_filter_off_accepts_every_candidate():
    f = SequenceFilter(length=0)
    assert f.check(0, 5) is True and f.check(1, -1) is False


def _disjoint(i: int) -> np.ndarray:
    return np.arange(64, dtype=np.int64) + 64 * i


def test_spatial_view_closes_a_loop_only_after_a_consistent_run():
    # disjoint SDRs open a new interval each (alpha 0 < theta_alpha), so interval k starts at frame k
    cells = SpatialViewCells(theta_alpha=32, theta_rho=0, theta_sigma=32, exclude_recent_intervals=1,
                             sequence={"length": 2, "max_step": 1.0, "slack": 0})
    plain = SpatialViewCells(theta_alpha=32, theta_rho=0, theta_sigma=32, exclude_recent_intervals=1)
    first = [cells.compute(_disjoint(i)) for i in range(20)]
    for i in range(20):
        plain.compute(_disjoint(i))
    # an isolated look-alike of place 7 among new places: the paper's rule closes, the filter not
    for c in (cells, plain):
        c.compute(_disjoint(100))
    assert plain.compute(_disjoint(7))["is_loop_closure"] is True
    r = cells.compute(_disjoint(7))
    assert r["is_loop_closure"] is False and r["id"] not in {x["id"] for x in first}
    cells.compute(_disjoint(101))
    # a real revisit of places 3, 4, 5, 6: closures from the third frame on, to the right templates
    out = [cells.compute(_disjoint(i)) for i in (3, 4, 5, 6)]
    assert [o["is_loop_closure"] for o in out] == [False, False, True, True]
    assert [o["id"] for o in out[2:]] == [first[5]["id"], first[6]["id"]]


def test_spatial_view_sequence_state_round_trip():
    kw = dict(theta_alpha=32, theta_rho=0, theta_sigma=32, exclude_recent_intervals=1,
              sequence={"length": 2})
    a = SpatialViewCells(**kw)
    for i in list(range(10)) + [2, 3]:
        a.compute(_disjoint(i))
    b = SpatialViewCells(**kw)
    b.load_state_dict(a.state_dict())
    assert a.compute(_disjoint(4)) == b.compute(_disjoint(4))


# ---------------------------------------------------------------- robust relaxation


def _square(em: ExperienceMap, last: float = 1.1) -> None:
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    for k, d in enumerate([1.0, 1.0, 1.0]):
        em.on_odo(d, 0.0, 1.0)
        em.on_action(CREATE_NODE, k, k + 1, 0.0)
        em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_odo(last, 0.0, 1.0)
    em.on_odo(0.0, math.pi / 2, 1.0)
    em.on_action(CREATE_EDGE, 3, 0, 0.0)


def test_robust_relaxation_leaves_a_consistent_loop_as_the_plain_one_does():
    plain = ExperienceMap(exp_initial_em_deg=0, exp_loops=200)
    robust = ExperienceMap(exp_initial_em_deg=0, exp_loops=200, exp_robust_m=1.0)
    _square(plain)
    _square(robust)
    # the loop's 0.1 m error is far below 1 m: every Cauchy weight is >= 1 / (1 + 0.1^2) = 0.99,
    # so both relax to the same shape (within a few millimetres)
    assert np.allclose(plain.x, robust.x, atol=5e-3) and np.allclose(plain.y, robust.y, atol=5e-3)


def test_robust_relaxation_limits_the_pull_of_one_wrong_link():
    def chain(**kw):
        em = ExperienceMap(exp_initial_em_deg=0, exp_loops=20, **kw)
        em.on_action(CREATE_NODE, 0, 0, 0.0)
        for k in range(1, 11):  # 10 m straight along x, one node per metre
            em.on_odo(1.0, 0.0, 1.0)
            em.on_action(CREATE_NODE, k - 1, k, 0.0)
        # a wrong closure: node 10 "is" node 0 (0 m apart), then 20 relaxations
        em.on_action(CREATE_EDGE, 10, 0, 0.0)
        for _ in range(20):
            em.iterate()
        return float(em.x[10] - em.x[0])

    plain, robust = chain(), chain(exp_robust_m=0.5)
    # the wrong link's error is ~10 m, so its weight is ~0.25 / 100: the chain of ten correct
    # links keeps the map within 10 % of its true 10 m; the plain rule folds the chain up
    assert robust > 9.0
    assert plain < 0.5 * robust


# ---------------------------------------------------------------- odometry gate

def test_odometry_gate_refuses_a_place_odometry_cannot_explain_and_accepts_a_real_return():
    from neoslam_stream.algorithms.ratslam.odometry_gate import OdometryGate

    g = OdometryGate(radius_m=1.0, drift=0.05)
    assert g.check(0) is True  # a new template: its place (0, 0) is recorded
    for _ in range(10):  # 10 m along +x
        g.on_odo(1.0, 0.0, 1.0)
    assert g.check(1) is True  # new template at (10, 0)
    # template 0 again, 10 m from the estimate; allowed 1 + 0.05 * 10 = 1.5 m: refused
    assert g.check(0) is False and g.refused == 1
    g.on_odo(0.0, math.pi, 1.0)  # turn round and drive 9.5 m back: at (0.5, 0)
    for _ in range(19):
        g.on_odo(0.5, 0.0, 1.0)
    assert g.allowed_m() == pytest.approx(1.0 + 0.05 * 19.5)
    assert g.check(0) is True  # 0.5 m from its place: accepted, the estimate moves there
    assert (g.x, g.y, g.path_m) == pytest.approx((0.0, 0.0, 0.0))


def test_odometry_gate_off_accepts_everything():
    from neoslam_stream.algorithms.ratslam.odometry_gate import OdometryGate

    g = OdometryGate()
    g.check(0)
    g.on_odo(100.0, 0.0, 1.0)
    assert g.check(1) and g.check(0)


def test_min_gap_leaves_recent_intervals_out_before_the_best_is_picked():
    kw = dict(theta_alpha=32, theta_rho=0, theta_sigma=32, exclude_recent_intervals=1)
    cells = SpatialViewCells(**kw, sequence={"min_gap_frames": 10})
    plain = SpatialViewCells(**kw)
    for c in (cells, plain):
        for i in range(20):
            c.compute(_disjoint(i))
    # frame 20 shows place 15 again (opened at frame 15, 5 frames ago): a closure by the paper's
    # rule, none with a 10-frame gap
    assert plain.compute(_disjoint(15))["is_loop_closure"] is True
    assert cells.compute(_disjoint(15))["is_loop_closure"] is False
    # frame 21 shows part of place 3 (score 40, 18 frames ago) and all of place 18 (score 64, 3
    # frames ago): the paper's rule picks 18, the gap leaves it out before the best is picked
    both = np.concatenate([_disjoint(3)[:40], _disjoint(18)])
    assert plain.compute(both)["best_interval"] == 18
    r = cells.compute(both)
    assert r["is_loop_closure"] is True and r["best_interval"] == 3


def test_pose_cell_node_keeps_a_refused_template_from_the_network():
    from neoslam_stream.nodes.ratslam import make_pose_cells_node
    from neoslam_stream.runtime.messages import Message

    node = make_pose_cells_node(odometry_gate={"radius_m": 1.0, "drift": 0.0})
    for f, (v, vt) in enumerate([(0.0, 0), (10.0, 1), (0.0, 0)]):  # template 0 again, 10 m away
        node.process("odom", Message("odom", f, float(f), {"vtrans": v, "vrot": 0.0, "dt": 1.0}))
        node.process("visual_template", Message("visual_template", f, float(f), {"id": vt}))
    node.flush()
    assert node.gate.refused == 1
    assert node.pc.current_vt == 1  # the network never saw the refused recognition
    assert node.info()["gate_refused"] == 1
