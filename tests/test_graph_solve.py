"""The experience map's least-squares relaxation (graph_solve.py, ``relaxation: least_squares``) on
hand-worked graphs: what each link says is met where the links agree, a loop's misclosure is shared
equally by its links, whole turns are read as the current map reads them, and the map keeps its
centroid and mean heading, as the sweeps do."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.actions import CREATE_EDGE, CREATE_NODE, SET_NODE
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap, ExperienceMapConfig
from neoslam_stream.algorithms.ratslam.graph_solve import relax_least_squares


def _links(rows):
    a = np.array(rows, dtype=float)
    return a[:, 0].astype(np.int64), a[:, 1].astype(np.int64), a[:, 2], a[:, 3], a[:, 4]


def test_links_that_agree_leave_the_map_as_it_is():
    # a unit square walked anticlockwise, each node facing along its next side
    x, y = np.array([0.0, 1, 1, 0]), np.array([0.0, 0, 1, 1])
    th = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2])
    lf, lt, d, head, face = _links([(0, 1, 1, 0, math.pi / 2), (1, 2, 1, 0, math.pi / 2),
                                    (2, 3, 1, 0, math.pi / 2), (3, 0, 1, 0, math.pi / 2)])
    nx, ny, nth = relax_least_squares(x, y, th, lf, lt, d, head, face)
    np.testing.assert_allclose(nx, x, atol=1e-12)
    np.testing.assert_allclose(ny, y, atol=1e-12)
    np.testing.assert_allclose(np.cos(nth - th), 1.0, atol=1e-12)


def test_a_misclosure_is_shared_equally_by_the_loops_links():
    # three nodes on a line, facing +x: 0->1 and 1->2 say 1 m, the loop link 0->2 says 2.3 m.
    # Least squares over x1-x0 = 1, x2-x1 = 1, x2-x0 = 2.3 leaves each link 0.1 m off:
    # x1-x0 = x2-x1 = 1.1, x2-x0 = 2.2; the centroid (x = 1) stays.
    x, y, th = np.array([0.0, 1.0, 2.0]), np.zeros(3), np.zeros(3)
    lf, lt, d, head, face = _links([(0, 1, 1.0, 0, 0), (1, 2, 1.0, 0, 0), (0, 2, 2.3, 0, 0)])
    nx, ny, nth = relax_least_squares(x, y, th, lf, lt, d, head, face)
    np.testing.assert_allclose(np.diff(nx), [1.1, 1.1], atol=1e-12)
    assert nx.mean() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(ny, 0.0, atol=1e-12)
    np.testing.assert_allclose(nth, 0.0, atol=1e-12)


def test_headings_across_the_half_turn_are_not_unwound():
    # two nodes facing almost backwards (3.1 and -3.1 rad, 0.083 rad apart across +-pi); the link
    # says the second faces 0.083 rad left of the first: already met modulo a whole turn, so no
    # node may swing round by a turn's worth
    th = np.array([3.1, -3.1])
    face = 2 * math.pi - 6.2
    nx, ny, nth = relax_least_squares(np.array([0.0, -1.0]), np.array([0.0, 0.0]), th, np.array([0]),
                                      np.array([1]), np.array([1.0]), np.array([0.0]), np.array([face]))
    np.testing.assert_allclose(np.cos(nth - th), 1.0, atol=1e-12)
    # and the position follows the first node's heading (3.1 rad): (cos 3.1, sin 3.1) from it
    assert nx[1] - nx[0] == pytest.approx(math.cos(3.1)) and ny[1] - ny[0] == pytest.approx(math.sin(3.1))


def test_a_heading_misclosure_is_shared_and_the_mean_heading_stays():
    # a two-link loop: 0->1 says +0.2 rad, 1->0 says +0.1 rad back (it should be -0.2): the loop
    # turns 0.3 rad too much; each link takes half: theta1 - theta0 = 0.2 - 0.15 = 0.05
    th = np.array([0.0, 0.2])
    lf, lt, d, head, face = _links([(0, 1, 0.0, 0, 0.2), (1, 0, 0.0, 0, 0.1)])
    _, _, nth = relax_least_squares(np.zeros(2), np.zeros(2), th, lf, lt, d, head, face)
    assert nth[1] - nth[0] == pytest.approx(0.05)
    assert nth.mean() == pytest.approx(th.mean())


def test_small_sweeps_approach_the_least_squares_map():
    # Gauss-Seidel sweeps with a small correction are a relaxed Kaczmarz iteration, whose limit
    # nears the least-squares solution as the correction goes to 0: an independent check of both
    x, y, th = np.array([0.0, 1.0, 2.0]), np.array([0.0, 0.1, -0.1]), np.zeros(3)
    lf, lt, d, head, face = _links([(0, 1, 1.0, 0, 0), (1, 2, 1.0, 0, 0), (0, 2, 2.3, 0.05, 0)])
    lx, ly, _ = relax_least_squares(x, y, th, lf, lt, d, head, face)
    em = ExperienceMap(exp_loops=20000, exp_correction=0.002)
    em._nodes = np.column_stack([x, y, th, np.zeros(3)])
    em._n, em.ids, em.index = 3, [0, 1, 2], {0: 0, 1: 1, 2: 2}
    em._lf = np.column_stack([lf, lt])
    em._lv = np.column_stack([d, head, face, np.zeros(3)])
    em._m = 3
    em.iterate()
    np.testing.assert_allclose(em.x, lx, atol=1e-3)
    np.testing.assert_allclose(em.y, ly, atol=1e-3)


def test_the_map_solves_after_loop_links_only():
    em = ExperienceMap(exp_initial_em_deg=0, relaxation="least_squares")
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    for k in range(1, 4):  # three 1 m steps straight ahead: every new node lies where its link says
        em.on_odo(1.0, 0.0, 1.0)
        em.on_action(CREATE_NODE, k - 1, k, 0.0)
    np.testing.assert_allclose(em.x, [0, 1, 2, 3], atol=1e-12)
    assert em.relax_time_s == 0.0  # nothing was solved
    em.on_action(SET_NODE, 3, 3, 0.0)
    assert em.relax_time_s == 0.0
    # node 0 recognised after 3.3 m more straight ahead: the loop link 3->0 says node 0 lies 3.3 m
    # ahead of node 3, the chain 3 m behind it; the map becomes the least-squares map of its links
    em.on_odo(3.3, 0.0, 1.0)
    em.on_action(CREATE_EDGE, 3, 0, 0.0)
    assert em.relax_time_s > 0.0
    lf, lv = np.array([k[:2] for k in em.links]), np.array([k[2:5] for k in em.links])
    want = relax_least_squares(np.array([0.0, 1, 2, 3]), np.zeros(4), np.zeros(4), lf[:, 0], lf[:, 1],
                               lv[:, 0], lv[:, 1], lv[:, 2])
    np.testing.assert_allclose(em.x, want[0], atol=1e-12)
    assert em.x.mean() == pytest.approx(1.5)  # the centroid stays


def test_robust_weights_need_the_sweeps():
    with pytest.raises(ValueError, match="exp_robust_m"):
        ExperienceMapConfig(relaxation="least_squares", exp_robust_m=1.0)
