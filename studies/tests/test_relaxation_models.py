"""studies/relaxation_models.py: the pose-graph solves measured beside the shipped least squares."""

from __future__ import annotations

import numpy as np
import pytest
from relaxation_models import map_class, parse_model, pose_graph
from test_bias_walk import DT, N, drive_circle

from neoslam_stream.algorithms.ratslam.actions import CREATE_EDGE
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap
from neoslam_stream.evaluation import ape

MODELS = ["joint:1", "stretch:1", "walk:10:100", "walk_scaled:0.01:0.001"]


def _circle(cls, bias_at) -> tuple[ExperienceMap, np.ndarray]:
    """A map of one circle (tests/test_bias_walk.py's drive_circle) with the start recognised at
    the end, and the experiences' true positions."""
    em = cls(exp_initial_em_deg=0, relaxation="least_squares")
    truth = drive_circle(em, bias_at)
    em.on_action(CREATE_EDGE, N - 1, 0, 0.0)  # back at the start, facing as then
    return em, truth


def test_a_map_whose_links_agree_is_left_as_it_is():
    for spec in MODELS:
        em, truth = _circle(map_class(parse_model(spec)), lambda t: 0.0)
        np.testing.assert_allclose(np.c_[em.x, em.y], truth, atol=1e-9, err_msg=spec)
        assert em.solves == 1


def test_the_joint_solve_keeps_what_the_least_squares_solve_had_right():
    # links that agree give a sum of squares of 0 before any step: nothing to move
    em, _ = _circle(ExperienceMap, lambda t: 0.0)
    lf, lv = np.array([k[:2] for k in em.links]), np.array([k[2:6] for k in em.links])
    closes = np.r_[np.zeros(N - 1, bool), True]
    _, _, _, info = pose_graph(em.x.copy(), em.y.copy(), em.th.copy(), lf[:, 0].astype(np.int64),
                               lf[:, 1].astype(np.int64), lv[:, 0], lv[:, 1], lv[:, 2], lv[:, 3], closes,
                               parse_model("joint:1"))
    assert info["cost_before"] == pytest.approx(0.0, abs=1e-20) and info["cost"] <= info["cost_before"]


def test_a_drifting_bias_is_bent_back_by_the_random_walk_of_rates():
    # the bias grows from 0 to 0.04 rad/s over the circle, so the heading error grows with the
    # square of time: the least-squares solve shares the heading misclosure equally by the links
    # (a constant bias), the joint solve also lets the position misclosure turn headings, and the
    # random walk of rates (smooth here: its steps weigh 10, the white heading errors 1000) can
    # follow the ramp itself
    def drift(t):
        return 0.04 * t / (N * DT)

    truth = _circle(ExperienceMap, drift)[1]
    err = {}
    for name, cls in (("least_squares", ExperienceMap), ("joint", map_class(parse_model("joint:1"))),
                      ("walk", map_class(parse_model("walk:1000:10")))):
        em = _circle(cls, drift)[0]
        err[name] = ape(np.c_[em.x, em.y], truth)["mean_m"]
    assert err["least_squares"] > 0.02  # the case is a real test of the least-squares solve
    assert err["joint"] < err["least_squares"]
    assert err["walk"] < err["joint"] / 2  # the rates do the work, not the joint solve alone


def test_model_specs_are_checked():
    assert parse_model("walk:10:100") == {"kind": "walk", "args": [10.0, 100.0], "name": "walk:10:100"}
    for bad in ("joint", "walk:1", "walk:1:2:3:4", "sweeps:3", "joint:1:2"):
        with pytest.raises(ValueError, match="expected joint:L"):
            parse_model(bad)
