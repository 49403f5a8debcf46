"""Pose cells: hand-worked cases of path integration, mass, injection and the fixed quirks."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.pose_cells import (
    CREATE_EDGE,
    CREATE_NODE,
    NO_ACTION,
    SET_NODE,
    PoseCellNetwork,
)


def delta_net(compat=False, **kw):
    pc = PoseCellNetwork(openratslam_compat=compat, pc_cell_x_size=1.0, **kw)
    pc.P[:] = 0
    return pc


def test_single_cell_moves_exactly_one_cell_for_one_cell_of_travel():
    pc = delta_net()
    pc.P[0, 5, 7] = 1.0  # layer theta = 0: moves along +y (pose-cell space mirrors the map)
    pc.P[9, 3, 3] = 1.0  # layer theta = 90 deg: moves along +x
    pc._path_integration(1.0, 0.0)
    assert pc.P[0, 6, 7] == pytest.approx(1.0, abs=1e-12)
    assert pc.P[9, 3, 4] == pytest.approx(1.0, abs=1e-12)
    assert pc.P.sum() == pytest.approx(2.0)


def test_half_cell_splits_between_neighbours_and_wraps():
    pc = delta_net()
    N = pc.config.pc_dim_xy
    pc.P[0, N - 1, 2] = 1.0
    pc._path_integration(0.5, 0.0)  # half a cell along +y from the last row: wraps to row 0
    assert pc.P[0, N - 1, 2] == pytest.approx(0.5)
    assert pc.P[0, 0, 2] == pytest.approx(0.5)


def test_mass_conserved_when_fixed_and_leaks_in_compat_mode():
    rng = np.random.default_rng(0)
    field = rng.random((36, 21, 21))
    for compat, conserved in ((False, True), (True, False)):
        pc = delta_net(compat)
        pc.P = field.copy()
        before = pc.P.sum()
        pc._path_integration(0.7, 0.0)
        after = pc.P.sum()
        if conserved:
            assert after == pytest.approx(before, rel=1e-12)
        else:
            # the C++ fold-back drops two padded entries per layer: mass wrapping through one corner
            assert after < before * (1 - 1e-5)


def test_rotation_is_linear_interpolation_along_theta():
    pc = delta_net()
    pc.P[4, 2, 2] = 1.0
    pc._path_integration(0.0, 1.5 * pc.C)
    assert pc.P[5, 2, 2] == pytest.approx(0.5) and pc.P[6, 2, 2] == pytest.approx(0.5)


def test_packet_settles_and_injection_moves_it():
    pc = PoseCellNetwork(pc_dim_xy=21)
    for _ in range(20):
        pc.on_odo(0.0, 0.0, 1.0)
    assert pc.best[0] == pytest.approx(10, abs=1e-6) and pc.best[1] == pytest.approx(10, abs=1e-6)
    # remember a template at a distant pose, then repeatedly inject there
    pc.templates[0] = [3.0, 3.0, 18.0, 1.0, 0.0]  # x, y, th, decay, creation rank
    for k in range(1, 12):
        pc.templates[k] = [10.0, 10.0, 18.0, 1.0, float(k)]  # 11 more so that template 0 may inject (signed guard)
    pc.current_vt = 5
    for _ in range(40):
        pc.on_view_template(0, 0.0)
        pc.current_vt = 5  # alternate so the decay stays low and energy keeps flowing
        pc.on_odo(0.0, 0.0, 1.0)
    assert pc.best[0] == pytest.approx(3, abs=0.5) and pc.best[1] == pytest.approx(3, abs=0.5)


def test_guard_fixed_vs_compat_with_few_templates():
    for compat, injects in ((True, True), (False, False)):
        pc = PoseCellNetwork(openratslam_compat=compat)
        pc.on_view_template(0)
        pc.on_view_template(1)
        before = pc.P.copy()
        pc.on_view_template(0)  # known template; only 2 exist: the 10-newest rule forbids injection
        assert (not np.array_equal(pc.P, before)) == injects


def test_injection_index_rounds_in_fixed_mode_truncates_in_compat():
    for compat, cell in ((True, (18, 4, 6)), (False, (18, 5, 7))):
        pc = PoseCellNetwork(openratslam_compat=compat)
        pc.P[:] = 0
        pc.templates = {k: [10.0, 10.0, 18.0, 1.0, float(k)] for k in range(12)}
        pc.templates[0] = [6.7, 4.6, 18.2, 1.0, 0.0]
        pc.current_vt = 3
        pc.on_view_template(0)
        assert pc.P[cell] > 0


def test_actions_create_link_and_set_node():
    pc = PoseCellNetwork(exp_delta_pc_threshold=2.0)
    pc.on_view_template(0)
    pc.on_odo(0, 0, 1)
    assert pc.get_action()[0] == CREATE_NODE
    pc.on_odo(0, 0, 1)
    assert pc.get_action()[0] == NO_ACTION  # no template update since
    pc.on_view_template(1)
    pc.on_odo(0, 0, 1)
    assert pc.get_action()[:3] == (CREATE_NODE, 0, 1)
    pc.on_view_template(0)
    pc.on_odo(0, 0, 1)
    assert pc.get_action()[:3] == (SET_NODE, 1, 0)  # already linked 0-1: fixed mode sets the node
    compat = PoseCellNetwork(openratslam_compat=True)
    for vt in (0, 1, 0):
        compat.on_view_template(vt)
        compat.on_odo(0, 0, 1)
        action = compat.get_action()[0]
    assert action == CREATE_EDGE  # the C++ never sends SET_NODE


def test_skipped_and_repeated_template_ids_do_not_crash():
    pc = PoseCellNetwork()
    for vt in (0, 5, 5, 2, 40, 0, 3):
        pc.on_view_template(vt)
        pc.on_odo(0.1, 0.05, 1.0)
        pc.get_action()
    assert set(pc.templates) == {0, 2, 3, 5, 40}


def test_nan_odometry_rejected():
    with pytest.raises(ValueError):
        PoseCellNetwork().on_odo(math.nan, 0, 1)


def _full_excite_inhibit(P, pc):
    """Reference: the whole-torus OpenRatSLAM update with explicit 3-D kernels and np.roll."""
    def conv(A, g):
        r = len(g) // 2
        out = np.zeros_like(A)
        for a in range(-r, r + 1):
            for b in range(-r, r + 1):
                for c in range(-r, r + 1):
                    out += g[a + r] * g[b + r] * g[c + r] * np.roll(A, (a, b, c), axis=(0, 1, 2))
        return out

    E = conv(P, pc.w_e)
    Q = E - conv(E, pc.w_i)
    Q = np.where(Q >= pc.config.pc_global_inhib, Q - pc.config.pc_global_inhib, 0.0)
    return Q / Q.sum()


@pytest.mark.parametrize("where", ["middle", "across_the_seams", "two_packets"])
def test_bounded_box_update_equals_whole_torus_update(where):
    pc = delta_net(pc_dim_xy=15)
    rng = np.random.default_rng(5)
    if where == "middle":
        pc.P[10:13, 6:9, 5:8] = rng.random((3, 3, 3))
    elif where == "across_the_seams":  # wraps in theta, y and x at once
        idx = np.ix_([35, 0, 1], [14, 0], [13, 14, 0])
        pc.P[idx] = rng.random((3, 2, 3))
    else:  # far apart in every axis: the box falls back to the full torus
        pc.P[3, 2, 2] = 1.0
        pc.P[21, 9, 9] = 0.5
    expected = _full_excite_inhibit(pc.P.copy(), pc)
    pc._excite_inhibit()
    np.testing.assert_allclose(pc.P, expected, rtol=0, atol=1e-15)


def test_settled_packet_matches_cpp_measurements():
    # OpenRatSLAM C++ (research notes 1.2): from one cell with no input the packet settles within
    # ~20 steps to 93 active cells, peak 0.0428, profile 0.273/0.75/1/0.75/0.273 through the peak
    for n in (11, 21, 30):
        pc = PoseCellNetwork(pc_dim_xy=n)
        for _ in range(40):
            pc.on_odo(0.0, 0.0, 1.0)
        assert np.count_nonzero(pc.P) == 93
        k, j, i = np.unravel_index(np.argmax(pc.P), pc.P.shape)
        peak = pc.P[k, j, i]
        assert peak == pytest.approx(0.0428, abs=5e-5)
        np.testing.assert_allclose(pc.P[k, j, i - 2:i + 3] / peak, [0.273, 0.75, 1, 0.75, 0.273], atol=5e-4)


def test_ten_newest_guard_counts_creation_order_not_ids():
    pc = PoseCellNetwork()
    ids = [500, 3, 77, 12, 9, 41, 8, 6, 60, 2, 90, 33]  # 12 templates, ids skipping about
    for vt in ids:
        pc.on_view_template(vt)
    before = pc.P.copy()
    pc.on_view_template(500)  # the oldest: outside the 10 newest, so it injects though its id is large
    assert not np.array_equal(pc.P, before)
    before = pc.P.copy()
    pc.on_view_template(3)  # the second oldest template id 3 also may inject
    assert not np.array_equal(pc.P, before)
    before = pc.P.copy()
    pc.on_view_template(2)  # among the 10 newest: no injection although id 2 < 12 - 10
    assert np.array_equal(pc.P, before)


def test_relative_rad_is_not_stale_when_fixed():
    for compat, expected in ((False, 0.0), (True, math.pi / 2)):
        pc = PoseCellNetwork(openratslam_compat=compat)
        for vt in range(12):
            pc.on_view_template(vt)
        pc.on_view_template(0, math.pi / 2)  # a panoramic match a quarter turn off: injects
        pc.on_odo(0, 0, 1)
        assert pc.get_action()[3] == pytest.approx(math.pi / 2)
        pc.on_view_template(12, 0.0)  # a new view: no rotation relative to anything
        pc.on_odo(0, 0, 1)
        assert pc.get_action()[3] == pytest.approx(expected)


def test_large_steps_stay_exact_when_fixed():
    pc = delta_net()
    pc.P[9, 4, 4] = 1.0  # theta 90 deg: +x
    pc._path_integration(2.5, 0.0)  # 2.5 cells at once (the C++ scheme handles at most one)
    assert pc.P[9, 4, 6] == pytest.approx(0.5) and pc.P[9, 4, 7] == pytest.approx(0.5)


def test_state_round_trip():
    pc = PoseCellNetwork()
    for vt in (0, 1, 2, 0, 1):
        pc.on_view_template(vt)
        pc.on_odo(0.4, 0.1, 1.0)
        pc.get_action()
    twin = PoseCellNetwork()
    twin.load_state_dict(pc.state_dict())
    for p in (pc, twin):
        p.on_view_template(2)
        p.on_odo(0.3, -0.2, 1.0)
    assert twin.get_action() == pc.get_action() and twin.best == pc.best


@pytest.mark.parametrize("field, value", [("pc_dim_xy", 11), ("pc_dim_th", 24)])
def test_a_checkpoint_of_another_size_is_refused(field, value):
    state = PoseCellNetwork().state_dict()  # pc_dim_xy 21, pc_dim_th 36
    other = PoseCellNetwork(**{field: value})
    with pytest.raises(ValueError, match=rf"{field}: the checkpoint's is {21 if field == 'pc_dim_xy' else 36}, "
                                         rf"the config's {value}"):
        other.load_state_dict(state)
    assert other.P.shape == (other.config.pc_dim_th, other.config.pc_dim_xy, other.config.pc_dim_xy)


def _odom(f, dt=0.1):
    from neoslam_stream.runtime.messages import Message

    data = {"vtrans": 0.5, "vrot": 0.1}
    if dt is not None:
        data["dt"] = dt
    return Message("odom", f, f * 0.1, data)


def _tmpl(f, vt):
    from neoslam_stream.runtime.messages import Message

    return Message("visual_template", f, f * 0.1, {"id": vt})


def _replay(events, **kw):
    from neoslam_stream.nodes.ratslam import PoseCellsNode

    st = PoseCellsNode(**kw)
    out = []
    for topic, m in events:
        out += st.process(topic, m)
    out += st.flush()
    return [(m.frame, m["action"], m["src_id"], m["dst_id"], m["vtrans"], m["dt"]) for _, m in out]


def test_stage_with_strided_templates_is_deterministic_and_complete():
    odo = [("odom", _odom(f)) for f in range(12)]
    tpl = [("visual_template", _tmpl(f, f // 4)) for f in range(0, 12, 3)]  # frame_stride 3
    interleaved = sorted(odo + tpl, key=lambda e: (e[1].frame, e[0] == "odom"))  # templates first
    late_front_end = odo[:4] + tpl[:1] + odo[4:9] + tpl[1:3] + odo[9:] + tpl[3:]
    a, b = _replay(interleaved), _replay(late_front_end)
    assert a == b
    assert [r[0] for r in a] == list(range(12))  # one action per odometry, in frame order
    # reference: the same events applied directly in frame order (template before its odometry)
    pc = PoseCellNetwork()
    ref = []
    for f in range(12):
        if f % 3 == 0:
            pc.on_view_template(f // 4)
        pc.on_odo(0.5, 0.1, 0.1)
        ref.append(pc.get_action()[:3])
    assert [r[1:4] for r in a] == ref


def test_stage_does_not_wait_forever_for_lost_templates():
    from neoslam_stream.nodes.ratslam import PoseCellsNode

    st = PoseCellsNode(max_odom_lag=4)
    st.process("visual_template", _tmpl(0, 0))
    out = []
    for f in range(10):  # templates of frames 1.. were dropped
        out += st.process("odom", _odom(f))
    assert [m.frame for _, m in out] == list(range(6))  # at most max_odom_lag odometry waits


def test_stage_takes_dt_from_stamps_when_odometry_has_none():
    rows = _replay([("visual_template", _tmpl(0, 0))] + [("odom", _odom(f, dt=None)) for f in range(3)])
    assert [r[5] for r in rows] == pytest.approx([0.0, 0.1, 0.1])  # the first odometry moves nothing


def test_stage_refuses_negative_template_ids():
    from neoslam_stream.nodes.ratslam import PoseCellsNode
    from neoslam_stream.runtime.node import StageInputError

    with pytest.raises(StageInputError):
        PoseCellsNode().process("visual_template", _tmpl(0, -1))


def test_template_decay_relaxes_on_every_step_as_its_definition_says():
    """Every template step relaxes every template's decay by pc_vt_restore (floor vt_active_decay)
    and a guarded template seen again while current gains vt_active_decay: checked against that
    definition, run eagerly over every template, through a long sequence and a checkpoint."""
    pc = PoseCellNetwork(pc_dim_xy=21, pc_vt_restore=0.04)
    a, r = pc.config.vt_active_decay, pc.config.pc_vt_restore
    seq = list(range(12)) + [0] * 6 + list(range(1, 12)) + [0, 0] + [5, 6] * 20 + [0, 3, 3, 3, 11]
    expected: dict[int, list[float]] = {}
    current = pc.current_vt
    for i, vt in enumerate(seq):
        if i == 40:  # resume from a checkpoint half way
            state = pc.state_dict()
            pc = PoseCellNetwork(pc_dim_xy=21, pc_vt_restore=0.04)
            pc.load_state_dict(state)
        size = len(expected)
        if vt not in expected:
            expected[vt] = [a, float(size)]
        elif expected[vt][1] < size - 10 and vt == current:
            expected[vt][0] += a
        for e in expected.values():
            e[0] = max(a, e[0] - r)
        current = vt
        pc.on_view_template(vt)
        pc.on_odo(0.0, 0.0, 1.0)
    got = {int(k): v[3] for k, v in pc.state_dict()["templates"].items()}
    assert got == {k: v[0] for k, v in expected.items()}
    assert max(got.values()) > a  # the sequence did raise a decay above the floor
