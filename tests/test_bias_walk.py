"""The map's ``bias_walk`` relaxation and the yaw-rate bias's measured wander that weighs it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.actions import CREATE_EDGE, CREATE_NODE, SET_NODE
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.algorithms.ratslam.odometry_bias import YawBiasEstimator
from neoslam_stream.algorithms.ratslam.pose_graph import bias_walk_weights
from neoslam_stream.evaluation import ape

N, DT, RADIUS = 126, 0.2, 2.0  # one circle in N steps of DT seconds: a regular N-gon
W = 2 * math.pi / (N * DT)


def _drive(est: YawBiasEstimator, bias: float, seconds: float, dt: float = 0.5) -> None:
    for _ in range(round(seconds / dt)):
        est.correct(bias, dt)  # standing still: the raw yaw rate is the bias


def test_wander_is_the_mean_squared_change_of_the_bias_per_second(tmp_path):
    # forgetting so fast that the estimate is the latest sample's rate; by hand:
    # t = 40: experience 0 (born at 0) seen again after 40 s at bias 0.01 -> b = 0.01, nothing
    #   30 s older to compare with;
    # t = 80: experience 1 (born at 40) after 40 s at 0.03 -> b = 0.03; the sample at 40 is 40 s
    #   older: (0.03 - 0.01)^2 / 40;
    # t = 100: experience 1 again after 60 s (all at 0.03) -> b = 0.03; the latest sample at least
    #   30 s older is still the one at 40 (80 is only 20 s back): (0.03 - 0.01)^2 / 60
    est = YawBiasEstimator(enabled=True, min_gap_s=30.0, forget_s=1e-9, max_residual_rad_s=1.0, reference="first")
    est.on_action(CREATE_NODE, 0)
    _drive(est, 0.01, 40.0)
    est.on_action(SET_NODE, 0)
    assert est.bias == pytest.approx(0.01) and est.wander == 0.0
    est.on_action(CREATE_NODE, 1)
    _drive(est, 0.03, 40.0)
    est.on_action(SET_NODE, 1)
    assert est.bias == pytest.approx(0.03) and est.wander == pytest.approx(0.02 ** 2 / 40)
    est.on_action(CREATE_NODE, 2)
    _drive(est, 0.03, 20.0)
    est.on_action(SET_NODE, 1)
    assert est.samples == 3 and est.wander == pytest.approx((0.02 ** 2 / 40 + 0.02 ** 2 / 60) / 2)
    # through a checkpoint file whole
    from neoslam_stream.runtime.checkpoint import load_state_file, save_state_file

    save_state_file(tmp_path / "s", est.state_dict())
    again = YawBiasEstimator(enabled=True, min_gap_s=30.0, forget_s=1e-9, max_residual_rad_s=1.0, reference="first")
    again.load_state_dict(load_state_file(tmp_path / "s"))
    assert again.wander == est.wander and list(again._history) == list(est._history)


@pytest.mark.parametrize("reference,after", [("latest", 0.03), ("first", 0.02)])
def test_a_return_is_compared_with_the_places_latest_visit(reference, after):
    # standing still, by hand: bias 0.01 rad/s for 40 s, back at place 0 (drift 0.4 rad over 40 s);
    # then 0.03 rad/s for 40 s and back again: against the latest visit 1.2 rad over 40 s (the bias
    # now), against the first 1.6 rad over 80 s (its mean since then); a return 20 s after the
    # latest one is under min_gap_s and leaves the reference where it was
    est = YawBiasEstimator(enabled=True, min_gap_s=30.0, forget_s=1e-9, max_residual_rad_s=1.0,
                           samples_from="templates", reference=reference)
    est.on_template(0)
    est.on_template(1)
    _drive(est, 0.01, 40.0)
    est.on_template(0)
    assert est.bias == pytest.approx(0.01)
    est.on_template(2)  # each time away, a view not seen before: no sample but place 0's
    _drive(est, 0.03, 20.0)
    est.on_template(0)
    assert est.samples == (1 if reference == "latest" else 2)
    est.on_template(3)
    _drive(est, 0.03, 20.0)
    est.on_template(0)
    assert est.bias == pytest.approx(after)
    assert est.born[0] == pytest.approx((0.4 + 1.2, 80.0) if reference == "latest" else (0.0, 0.0))


def test_the_weights_are_inverse_variances_of_each_link():
    ld, ldt = np.array([0.0, 1.0, 2.0]), np.array([0.5, 1.0, 1.5])
    wp, wt, wb = bias_walk_weights(ld, ldt, position_rel=0.5, heading_var=0.01, wander=1e-4)
    # a turn on the spot is read as a tenth of the median length: sd 0.5 x 0.1 m
    np.testing.assert_allclose(wp, [1 / 0.05 ** 2, 1 / 0.5 ** 2, 1 / 1.0 ** 2])
    np.testing.assert_allclose(wt, [1 / 0.005, 1 / 0.01, 1 / 0.015])
    np.testing.assert_allclose(wb, [1 / (1e-4 * 0.75), 1 / (1e-4 * 1.25)])
    # a map of turns on the spot only (median length 0): read as 1 mm, a finite weight
    wp, _, _ = bias_walk_weights(np.zeros(3), ldt, position_rel=0.5, heading_var=0.01, wander=1e-4)
    np.testing.assert_allclose(wp, 1 / (0.5 * 1e-3) ** 2)


def test_bias_walk_solves_a_map_of_turns_on_the_spot():
    # four experiences a quarter turn apart on the spot, the last linked back to the first with
    # a heading 0.1 rad off: finite poses, all still at the origin
    em = ExperienceMap(exp_initial_em_deg=0, relaxation="bias_walk")
    em.bias_wander = 1e-4
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    for k in range(1, 4):
        em.on_odo(0.0, math.pi / 2, 1.0)
        em.on_action(CREATE_NODE, k - 1, k, 0.0)
    em.on_odo(0.0, math.pi / 2 + 0.1, 1.0)
    em.on_action(CREATE_EDGE, 3, 0, 0.0)
    assert np.isfinite(np.c_[em.x, em.y, em.th]).all()
    np.testing.assert_allclose(np.c_[em.x, em.y], 0.0, atol=1e-9)
    # the links measured three quarter turns and a quarter turn + 0.1 rad: each now turns by its
    # measurement less a quarter of the 0.1 rad misclosure (equal durations, equal shares)
    turns = np.angle(np.exp(1j * (np.r_[em.th[1:], em.th[0]] - em.th)))
    np.testing.assert_allclose(turns, np.array([0, 0, 0, 0.1]) + math.pi / 2 - 0.025, atol=1e-6)


def drive_circle(em: ExperienceMap, bias_at) -> np.ndarray:
    """Drive one circle on ``em`` with the yaw rate W + bias_at(t), an experience per step (the
    start not yet recognised); the experiences' true positions (the same rotate-then-advance
    integration without the bias, so that a map without bias closes exactly)."""
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    truth, x, y, th = [(0.0, 0.0)], 0.0, 0.0, 0.0
    step = 2 * RADIUS * math.sin(W * DT / 2) / DT  # speed whose chord per step lies on the circle
    for k in range(1, N + 1):
        em.on_odo(step, W + bias_at(k * DT), DT)
        th += W * DT
        x, y = x + step * DT * math.cos(th), y + step * DT * math.sin(th)
        if k < N:
            em.on_action(CREATE_NODE, k - 1, k, 0.0)
            truth.append((x, y))
    return np.array(truth)


def _circle(bias_at, **config) -> tuple[ExperienceMap, np.ndarray]:
    em = ExperienceMap(exp_initial_em_deg=0, **config)
    return em, drive_circle(em, bias_at)


def _close(em: ExperienceMap, wander: float) -> None:
    em.bias_wander = wander
    em.on_action(CREATE_EDGE, N - 1, 0, 0.0)  # back at the start, facing as then


def test_bias_walk_is_least_squares_until_the_run_measured_a_wander():
    def drift(t):
        return 0.04 * t / (N * DT)

    ls, _ = _circle(drift, relaxation="least_squares")
    _close(ls, 0.0)
    walk, _ = _circle(drift, relaxation="bias_walk")
    _close(walk, 0.0)
    np.testing.assert_array_equal(np.c_[walk.x, walk.y, walk.th], np.c_[ls.x, ls.y, ls.th])


def test_bias_walk_bends_a_drifting_bias_back():
    # the bias grows from 0 to 0.04 rad/s over the circle, so the heading error grows with the
    # square of time; least squares shares the misclosure equally by the links (a constant bias),
    # the walk's rates may follow the ramp: the wander is a random walk's that strays as far over
    # the circle (0.04 rad/s in N DT s), the links' own errors are small
    def drift(t):
        return 0.04 * t / (N * DT)

    ls, truth = _circle(drift, relaxation="least_squares")
    _close(ls, 0.0)
    walk, _ = _circle(drift, relaxation="bias_walk", walk_position_rel=0.05, walk_heading_var=1e-6)
    _close(walk, 0.04 ** 2 / (N * DT))
    err_ls, err_walk = ape(np.c_[ls.x, ls.y], truth)["mean_m"], ape(np.c_[walk.x, walk.y], truth)["mean_m"]
    assert err_ls > 0.02  # the case is a real test of the least-squares solve
    assert err_walk < err_ls / 2


def test_the_pose_cells_send_the_wander_and_the_map_reads_it():
    from neoslam_stream.nodes.ratslam import make_experience_map_node, make_pose_cells_node
    from neoslam_stream.runtime.messages import Message

    node = make_pose_cells_node(odometry_bias={"enabled": True})
    node.stage.bias._sum_q, node.stage.bias._pairs = 3e-6, 2  # as if two pairs had been measured
    node.process("visual_template", Message("visual_template", 0, 0.0, {"id": 0}))
    ((_, action),) = node.process("odom", Message("odom", 0, 0.0, {"vtrans": 1.0, "vrot": 0.5, "dt": 0.1}))
    assert action["bias_wander"] == pytest.approx(1.5e-6)
    em_node = make_experience_map_node(relaxation="bias_walk")
    em_node.process("pose_cells/action", action)
    assert em_node.em.bias_wander == pytest.approx(1.5e-6)
    # an action from a pose-cell process that sends no wander (an older one): not measured
    del action.data["bias_wander"]
    action.frame += 1
    em_node.process("pose_cells/action", action)
    assert em_node.em.bias_wander == 0.0

