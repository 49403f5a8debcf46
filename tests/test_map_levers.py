"""The map levers that the default keeps, on hand-worked cases: the sequence filter of
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
    assert node.stage.gate.refused == 1
    assert node.stage.network.current_vt == 1  # the network never saw the refused recognition
    assert node.info()["gate_refused"] == 1


# ------------------------------------------------------------------ yaw-rate bias from closures

def _circle(est, omega: float, bias: float, seconds: float, dt: float = 0.5) -> None:
    """Drive a circle at true yaw rate omega for ``seconds``: the odometry reports omega + bias."""
    for _ in range(round(seconds / dt)):
        est.correct(omega + bias, dt)


def test_yaw_bias_is_the_heading_drift_of_a_closed_loop_over_its_duration():
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
    from neoslam_stream.algorithms.ratslam.pose_cells import SET_NODE

    # by hand: one full circle in T = 100 s (true yaw rate 2 pi / T) with odometry reading 0.01
    # rad/s too much; back at experience 0, the raw heading has turned 2 pi + 1 rad, the true
    # heading 2 pi: drift 1 rad over 100 s, b = 0.01 rad/s
    est = YawBiasEstimator(enabled=True)
    est.on_action(CREATE_NODE, 0)
    _circle(est, 2 * math.pi / 100, 0.01, 100.0)
    est.on_action(SET_NODE, 0)
    assert est.bias == pytest.approx(0.01, rel=1e-9) and est.samples == 1
    assert est.correct(0.3, 0.1) == pytest.approx(0.3 - 0.01)
    # the same place seen the other way round (half a turn off): an outlier, the estimate stays
    est.on_action(CREATE_NODE, 1)
    _circle(est, 2 * math.pi / 100, 0.01, 50.0)  # half a circle: the robot faces the opposite way
    est.on_action(CREATE_EDGE, 1)
    assert est.outliers == 1 and est.samples == 1 and est.bias == pytest.approx(0.01, rel=1e-9)


def test_a_new_session_measures_the_yaw_bias_afresh():
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
    from neoslam_stream.algorithms.ratslam.pose_cells import SET_NODE

    # yesterday: the circle of the test above read 0.025 rad/s too much (drift 2.5 rad over 100 s)
    est = YawBiasEstimator(enabled=True, max_residual_rad_s=0.01)
    est.on_action(CREATE_NODE, 0)
    _circle(est, 2 * math.pi / 100, 0.025, 100.0)
    est.on_action(SET_NODE, 0)
    assert est.bias == pytest.approx(0.025, rel=1e-9)
    est.new_session()
    # today's odometry reads 0.005 rad/s too much: the estimate starts at 0 and the first return
    # sets it (held at 0.025, the return would lie 0.02 rad/s off it: an outlier, kept out)
    assert est.bias == 0.0 and est.correct(0.3, 0.1) == pytest.approx(0.3)
    est.on_action(CREATE_NODE, 7)
    _circle(est, 2 * math.pi / 100, 0.005, 100.0)
    est.on_action(SET_NODE, 7)
    assert est.bias == pytest.approx(0.005, rel=1e-9) and est.samples == 1 and est.outliers == 0


def test_yaw_bias_weighs_older_closures_less_and_ignores_quick_returns(tmp_path):
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
    from neoslam_stream.algorithms.ratslam.pose_cells import SET_NODE

    est = YawBiasEstimator(enabled=True, forget_s=100.0, min_gap_s=30.0, max_residual_rad_s=1.0)
    est.on_action(CREATE_NODE, 0)
    _circle(est, 0.0, 0.02, 20.0)
    est.on_action(SET_NODE, 0)  # 20 s after its creation: under min_gap_s, no sample
    assert est.samples == 0 and est.bias == 0.0
    _circle(est, 0.0, 0.02, 20.0)
    est.on_action(SET_NODE, 0)  # 40 s: drift 0.8 rad over 40 s
    est.on_action(CREATE_NODE, 5)
    _circle(est, 0.0, 0.03, 60.0)
    est.on_action(SET_NODE, 5)  # 60 s later: drift 1.8 rad over 60 s, the first sample 60 s old
    keep = math.exp(-60.0 / 100.0)
    expected = (keep * 0.8 * 40 + 1.8 * 60) / (keep * 40 ** 2 + 60 ** 2)
    assert est.samples == 2 and est.bias == pytest.approx(expected, rel=1e-9)
    # the state goes through a checkpoint file whole
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file

    save_state_file(tmp_path / "s", est.state_dict())
    again = YawBiasEstimator(enabled=True, forget_s=100.0)
    again.load_state_dict(load_state_file(tmp_path / "s"))
    assert again.state_dict()["scalars"] == est.state_dict()["scalars"] and again.born == est.born
    # a new session of a loaded map: old experiences are no heading reference any more, and the
    # bias is measured afresh (test_a_new_session_measures_the_yaw_bias_afresh)
    again.new_session()
    _circle(again, 0.0, 0.03, 60.0)
    again.on_action(SET_NODE, 5)  # experience 5 of the old session: taken as new, no sample
    assert again.samples == 0 and again.bias == 0.0 and 5 in again.born


def test_yaw_bias_off_leaves_the_odometry_alone():
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
    from neoslam_stream.algorithms.ratslam.pose_cells import SET_NODE

    est = YawBiasEstimator()  # the paper's profile: off
    est.on_action(CREATE_NODE, 0)
    _circle(est, 0.0, 0.05, 100.0)
    est.on_action(SET_NODE, 0)
    assert est.samples == 0 and est.correct(0.25, 0.1) == 0.25


def test_pose_cell_node_sends_the_corrected_yaw_rate_to_the_map():
    from neoslam_stream.config import load_config
    from neoslam_stream.nodes.ratslam import make_pose_cells_node
    from neoslam_stream.runtime.messages import Message

    assert load_config("default").pose_cells.odometry_bias.enabled
    assert not load_config("paper").pose_cells.odometry_bias.enabled
    node = make_pose_cells_node(odometry_bias={"enabled": True})
    node.stage.bias.bias = 0.02  # as if closures had measured it
    node.process("visual_template", Message("visual_template", 0, 0.0, {"id": 0}))
    ((_, action),) = node.process("odom", Message("odom", 0, 0.0, {"vtrans": 1.0, "vrot": 0.5, "dt": 0.1}))
    assert action["vrot"] == pytest.approx(0.48)
    assert node.info()["yaw_bias_rad_s"] == pytest.approx(0.02)


def test_yaw_bias_from_templates_samples_returns_and_takes_reversed_views_modulo_pi():
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
    from neoslam_stream.algorithms.ratslam.pose_cells import SET_NODE

    # by hand, as the circle above: template 7 first seen, one circle of 100 s with odometry
    # reading 0.01 rad/s too much, template 7 again: drift 1 rad over 100 s, b = 0.01 rad/s
    est = YawBiasEstimator(enabled=True, samples_from="templates")
    est.on_action(CREATE_NODE, 0)  # actions are not this source's: ignored
    est.on_template(7)
    _circle(est, 0.0, 0.01, 40.0)
    est.on_template(7)  # still the same view (no return): no sample, even after min_gap_s
    assert est.samples == 0 and est.born == {7: (0.0, 0.0)} and est.bias == 0.0
    est.on_template(8)
    _circle(est, 2 * math.pi / 60, 0.01, 60.0)
    est.on_template(7)  # a return, 100 s after its birth: raw heading 2 pi + 0.4 + 0.6 rad
    assert est.samples == 1 and est.bias == pytest.approx(0.01, rel=1e-9)
    est.on_action(SET_NODE, 0)
    assert est.samples == 1

    # the same place seen the other way round (half a turn off, 0.5 rad of drift over 50 s):
    # a forward front end's estimator rejects it (rate pi / 50 s off the estimate), a
    # bidirectional one takes the same 0.5 rad it would have taken facing the first way
    for bidirectional, samples, bias in ((False, 1, 0.01), (True, 2, (1.0 * 100 + 0.5 * 50) / (100**2 + 50**2))):
        e = YawBiasEstimator(enabled=True, samples_from="templates", bidirectional=bidirectional,
                             forget_s=0.0, max_residual_rad_s=0.05)
        e.on_template(7)
        e.on_template(8)
        _circle(e, 2 * math.pi / 100, 0.01, 100.0)
        e.on_template(7)  # drift 1 rad over 100 s, as above
        e.on_template(9)
        _circle(e, math.pi / 50, 0.01, 50.0)  # half a turn: facing the opposite way
        e.on_template(9)  # not a return: 9 was the previous template
        assert e.samples == 1
        e.on_template(3)
        e.on_template(9)
        assert e.samples == samples and e.outliers == 2 - samples
        assert e.bias == pytest.approx(bias, rel=1e-9)


def test_pose_cell_node_feeds_every_template_to_the_bias_before_the_gate():
    from neoslam_stream.nodes.ratslam import make_pose_cells_node
    from neoslam_stream.runtime.messages import Message

    # the gate (1 m) refuses template 0 after 60 m of odometry; the bias still takes its sample
    node = make_pose_cells_node(odometry_bias={"enabled": True, "samples_from": "templates"},
                                odometry_gate={"radius_m": 1.0, "drift": 0.0})
    frame = 0

    def step(template, seconds, vtrans, vrot):
        nonlocal frame
        for _ in range(round(seconds / 0.1)):
            if template is not None:
                node.process("visual_template", Message("visual_template", frame, frame * 0.1, {"id": template}))
            node.process("odom", Message("odom", frame, frame * 0.1, {"vtrans": vtrans, "vrot": vrot, "dt": 0.1}))
            frame += 1

    step(0, 0.1, 0.0, 0.0)
    step(1, 0.1, 0.0, 0.0)
    step(None, 60.0, 1.0, 0.02)  # 60 m straight ahead, the odometry turning 0.02 rad/s (1.2 rad)
    step(0, 0.1, 0.0, 0.0)
    assert node.stage.gate.refused == 1
    assert node.stage.bias.samples == 1 and node.stage.bias.bias == pytest.approx(1.2 / 60.2, rel=1e-6)


def test_nordland_protocol_resolves_the_gap_and_the_calibration_quantile():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from nordland import resolve_params  # the protocol lives with the benches

    # four summer frames of places 0, 100, 400, 700 (tolerance 150): far-apart pairs are every pair
    # but (0, 100); their overlaps are 1 (0-400), 2 (0-700), 3 (100-400), 4 (100-700), 5 (400-700)
    bits = [np.array([0, 1, 2, 3, 4, 5, 50]), np.array([0, 10, 11, 13, 14, 15, 16]),
            np.array([0, 10, 11, 12, 20, 21, 22]), np.array([0, 1, 10, 11, 12, 13, 20])]
    ids = [0, 100, 400, 700]
    o = np.array([[len(np.intersect1d(a, b)) for b in bits] for a in bits])
    far = [o[i, j] for i in range(4) for j in range(4) if i != j and abs(ids[i] - ids[j]) > 150]
    assert sorted(far) == [1, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    p = resolve_params({"theta_sigma": None, "calibration_quantile": 50.0, "min_gap_fraction": 0.5,
                        "sequence": {"length": 1}}, bits, ids, 4, 150, 99.9)
    # the median of the ten overlaps is 3; half of the 4 places per traversal is a 2-frame gap
    assert p == {"theta_sigma": 3, "sequence": {"length": 1, "min_gap_frames": 2}}
    # without the deferred keys: the default quantile (99.9: between the two largest, both 5), no gap
    assert resolve_params({"theta_sigma": None}, bits, ids, 4, 150, 99.9) == {"theta_sigma": 5}
    assert resolve_params({"theta_sigma": 7}, bits, ids, 4, 150, 99.9) == {"theta_sigma": 7}



def test_yaw_bias_anchoring_follows_the_turn_the_odometry_does_not_explain(tmp_path):
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator

    cell = 2 * math.pi / 36
    est = YawBiasEstimator(enabled=True, samples_from="templates", anchor_s=10.0)
    est.on_heading(1.0, 0.1, 1.0, cell)  # the first heading: nothing to compare with
    assert est.bias == 0.0
    # the odometry turned the cells by 0.1 rad, they turned 0.05: a view pulled them back 0.05 rad,
    # the corrected rate is 0.05 rad/s too fast, and the offset moves by 0.05 / anchor_s
    est.on_heading(1.05, 0.1, 1.0, cell)
    assert est.offset == pytest.approx(0.005) and est.bias == pytest.approx(0.005)
    # a step of a pose cell's angle or more is the packet moving elsewhere: left out
    est.on_heading(1.05 + 0.1 + cell, 0.1, 1.0, cell)
    assert est.offset == pytest.approx(0.005)
    # across the wrap of the heading: +pi - 0.01 to -pi + 0.01 is a turn of 0.02 rad, as the odometry's
    est.on_heading(math.pi - 0.01, 0.0, 1.0, cell)
    est.on_heading(-math.pi + 0.01, 0.02, 1.0, cell)
    assert est.offset == pytest.approx(0.005)
    # the returns' least-squares level and the offset add up; both go through a checkpoint
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file

    save_state_file(tmp_path / "s", est.state_dict())
    again = YawBiasEstimator(enabled=True, samples_from="templates", anchor_s=10.0)
    again.load_state_dict(load_state_file(tmp_path / "s"))
    assert (again.level, again.offset, again.bias) == (est.level, est.offset, est.bias)
    again.on_heading(-math.pi + 0.01 + 0.03, 0.02, 1.0, cell)  # the saved heading is the reference
    assert again.offset == pytest.approx(0.005 - 0.01 / 10.0)
    # off (anchor_s 0, the estimator's default): the heading is not read
    plain = YawBiasEstimator(enabled=True, samples_from="templates")
    plain.on_heading(0.0, 0.0, 1.0, cell)
    plain.on_heading(0.5 * cell, 0.0, 1.0, cell)
    assert plain.bias == 0.0


def _anchored_estimates(anchor_s: float, b: float, dt: float, steps: int) -> list[float]:
    """The estimate after each of ``steps`` odometry steps when views hold the cells' heading to the
    true one at every step and the odometry reads b rad/s too much (turning at 0.2 rad/s)."""
    from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator

    omega, cell = 0.2, 2 * math.pi / 36
    est = YawBiasEstimator(enabled=True, samples_from="templates", anchor_s=anchor_s)
    truth = 0.0
    est.on_heading(truth, 0.0, dt, cell)
    out = []
    for _ in range(steps):
        used = est.correct(omega + b, dt)
        truth += omega * dt
        est.on_heading(math.remainder(truth, 2 * math.pi), used, dt, cell)
        out.append(est.bias)
    return out


def test_yaw_bias_anchoring_converges_to_a_bias_at_its_time_constant():
    # the odometry reads b = 0.03 rad/s too much. The residual r = b - estimate shrinks by
    # (1 - dt / anchor_s) a step: after n steps the estimate is b (1 - (1 - dt / tau)^n)
    b, dt, tau = 0.03, 0.1, 5.0
    got = _anchored_estimates(tau, b, dt, 300)
    for n in (50, 150, 300):
        assert got[n - 1] == pytest.approx(b * (1 - (1 - dt / tau) ** n), rel=1e-9)


def test_yaw_bias_anchoring_is_never_faster_than_ten_odometry_steps():
    from neoslam_stream.algorithms.ratslam.odometry_bias import ANCHOR_MIN_STEPS

    # a platform whose loop time is shorter than a few steps (anchor_s 0.05 s at dt 0.1 s) would
    # make the offset overshoot by 20 x each step and oscillate; the guard makes the time constant
    # ANCHOR_MIN_STEPS steps, 1 s here, and the residual shrinks by (1 - dt / 1 s) = 0.9 a step
    assert ANCHOR_MIN_STEPS == 10
    b = 0.03
    got = _anchored_estimates(0.05, b, 0.1, 60)
    for n in range(1, 61):
        assert got[n - 1] == pytest.approx(b * (1 - 0.9 ** n), rel=1e-9)
