"""Temporal Memory unit cases worked by hand from the algorithm's definition (htm.core rules)."""

import numpy as np
import pytest

from neoslam_stream.algorithms.temporal_memory import TemporalMemory


def tiny(**kw):
    p = dict(columns=4, cells_per_column=3, activation_threshold=2, initial_permanence=0.6,
             connected_permanence=0.5, min_threshold=1, max_new_synapse_count=3, permanence_increment=0.1,
             permanence_decrement=0.1, predicted_segment_decrement=0.0, seed=42, max_segments_per_cell=10,
             max_synapses_per_segment=10)
    p.update(kw)
    return TemporalMemory(**p)


def test_bursting_column_activates_all_its_cells():
    tm = tiny()
    tm.compute([1])
    assert tm.active_cells.tolist() == [3, 4, 5]
    assert tm.winner_cells.tolist() == [3]  # least used, lowest index
    assert tm.anomaly == 1.0


def test_predicted_column_activates_only_predicted_cells():
    tm = tiny()
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.6)
    tm.add_synapse(seg, 1, 0.6)
    tm.compute([0], learn=False)  # bursts column 0: cells 0, 1, 2 active
    assert tm.predicted_cells().tolist() == [4]
    tm.compute([1], learn=False)
    assert tm.active_cells.tolist() == [4]
    assert tm.winner_cells.tolist() == [4]
    assert tm.anomaly == 0.0


def test_burst_winner_is_least_used_cell_lowest_index_on_ties():
    tm = tiny()
    seg = tm.createSegment(3)  # cell 3 now has a segment; 4 and 5 have none
    tm.add_synapse(seg, 11, 0.6)
    tm.compute([1], learn=False)
    assert tm.winner_cells.tolist() == [4]


def test_best_matching_segment_by_active_potential_synapses():
    tm = tiny(activation_threshold=3)
    s4 = tm.createSegment(4)
    tm.add_synapse(s4, 0, 0.2)  # 1 active potential synapse
    s5 = tm.createSegment(5)
    tm.add_synapse(s5, 0, 0.2)
    tm.add_synapse(s5, 1, 0.2)  # 2 active potential synapses: the best match
    tm.compute([0], learn=False)
    tm.compute([1], learn=False)
    assert tm.winner_cells.tolist() == [5]
    assert tm.active_cells.tolist() == [3, 4, 5]  # not predicted: it bursts


def test_new_segment_grows_min_of_max_new_and_prev_winners():
    tm = tiny(max_new_synapse_count=3)
    tm.compute([0, 2])  # winners: cells 0 and 6
    assert tm.winner_cells.tolist() == [0, 6]
    tm.compute([1])  # bursts without matching segment: new segment on cell 3
    segs = tm.segments_of_cell(3)
    assert len(segs) == 1
    pre, perm = tm.synapses_of_segment(segs[0])
    assert sorted(pre.tolist()) == [0, 6]  # min(3, 2) = 2 synapses
    np.testing.assert_allclose(perm, 0.6)
    tm2 = tiny(max_new_synapse_count=1)
    tm2.compute([0, 2])
    tm2.compute([1])
    pre, _ = tm2.synapses_of_segment(tm2.segments_of_cell(3)[0])
    assert pre.size == 1 and pre[0] in (0, 6)  # min(1, 2) = 1


def test_adapt_increments_decrements_and_destroys_below_epsilon():
    tm = tiny()
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.6)
    tm.add_synapse(seg, 1, 0.6)
    tm.add_synapse(seg, 11, 0.05)  # inactive presynaptic cell: 0.05 - 0.1 < 1e-6 -> destroyed
    tm.add_synapse(seg, 10, 0.5)  # inactive: 0.5 - 0.1 = 0.4
    tm.compute([0], learn=False)
    tm.compute([1], learn=True)  # predicted: adapt the active segment
    pre, perm = tm.synapses_of_segment(seg)
    got = dict(zip(pre.tolist(), perm.tolist(), strict=True))
    assert 11 not in got
    assert got[0] == pytest.approx(0.7, abs=1e-6) and got[1] == pytest.approx(0.7, abs=1e-6)
    assert got[10] == pytest.approx(0.4, abs=1e-6)


def test_segment_destroyed_below_min_threshold():
    tm = tiny(min_threshold=2, activation_threshold=2, permanence_decrement=0.5)
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.2)  # active, potential
    tm.add_synapse(seg, 1, 0.2)  # active, potential
    tm.add_synapse(seg, 9, 0.3)  # inactive: 0.3 - 0.5 < 0 -> destroyed
    tm.compute([0], learn=False)
    # column 1 bursts, the segment matches (pot 2): adapt leaves 2 synapses >= minThreshold
    tm.compute([1], learn=True)
    assert tm.segments_of_cell(4) == [seg]
    tm2 = tiny(min_threshold=2, activation_threshold=2, permanence_decrement=0.5)
    s = tm2.createSegment(4)
    tm2.add_synapse(s, 0, 0.2)
    tm2.add_synapse(s, 1, 0.2)
    tm2.add_synapse(s, 9, 0.3)
    tm2.compute([0, 3], learn=False)  # activates cells 0,1,2 and 9,10,11
    tm2.compute([2], learn=True)  # column 1 inactive: no learning on it; nothing destroyed
    assert tm2.segments_of_cell(4) == [s]


def test_punishment_of_predicted_but_inactive_column():
    tm = tiny(predicted_segment_decrement=0.05)
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.6)
    tm.add_synapse(seg, 1, 0.6)
    tm.add_synapse(seg, 10, 0.6)  # inactive presynaptic: unchanged by punishment
    tm.compute([0], learn=False)
    tm.compute([2], learn=True)  # column 1 was predicted but is not active
    pre, perm = tm.synapses_of_segment(seg)
    got = dict(zip(pre.tolist(), perm.tolist(), strict=True))
    assert got[0] == pytest.approx(0.55, abs=1e-6) and got[1] == pytest.approx(0.55, abs=1e-6)
    assert got[10] == pytest.approx(0.6, abs=1e-6)


def test_segment_eviction_by_smallest_sum_of_squared_permanences():
    tm = tiny(max_segments_per_cell=2)
    a = tm.createSegment(5)
    tm.add_synapse(a, 11, 0.9)  # sum of squares 0.81
    b = tm.createSegment(5)
    tm.add_synapse(b, 10, 0.3)
    tm.add_synapse(b, 9, 0.3)  # 0.18: the least useful, although created last
    c = tm.createSegment(5)
    assert tm.segments_of_cell(5) == [a, c]
    assert c == b  # its id is reused (last freed first)


def test_synapse_cap_removes_weakest_non_candidates():
    tm = tiny(max_synapses_per_segment=4, max_new_synapse_count=2, activation_threshold=3)
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.3)  # onto a future candidate (prev winner): kept
    tm.add_synapse(seg, 9, 0.2)
    tm.add_synapse(seg, 10, 0.4)
    tm.add_synapse(seg, 11, 0.45)
    tm.compute([0, 1], learn=False)  # winners: cells 0 and 3
    assert tm.winner_cells.tolist() == [0, 3]
    # column 1 bursts, segment matches (pot 1); grow maxNew - pot = 1: overrun 4 + 1 - 4 = 1
    tm.compute([1], learn=True)
    pre, perm = tm.synapses_of_segment(seg)
    assert 9 not in pre.tolist()  # the weakest non-candidate went
    assert 0 in pre.tolist() and len(pre) == 4


def test_repeated_sequence_becomes_predicted_with_default_parameters():
    rng = np.random.default_rng(7)
    tm = TemporalMemory(columns=2048, cells_per_column=32)  # htm.core defaults
    seq = [np.sort(rng.choice(2048, 40, replace=False)) for _ in range(4)]  # A B C D
    for _ in range(12):
        anomalies = [(tm.compute(x), tm.anomaly)[1] for x in seq]
    assert anomalies == [0.0, 0.0, 0.0, 0.0]


def test_deterministic_for_a_seed():
    rng = np.random.default_rng(3)
    xs = [np.sort(rng.choice(256, 20, replace=False)) for _ in range(60)]
    a = tiny(columns=256, cells_per_column=8, tie_break="random", seed=5)
    b = tiny(columns=256, cells_per_column=8, tie_break="random", seed=5)
    for x in xs:
        np.testing.assert_array_equal(a.compute(x), b.compute(x))


def test_save_load_mid_stream_gives_identical_outputs():
    rng = np.random.default_rng(9)
    xs = [np.sort(rng.choice(512, 40, replace=False)) for _ in range(10)] * 4
    a = tiny(columns=512, cells_per_column=8, max_new_synapse_count=5)
    for x in xs[:23]:
        a.compute(x)
    b = tiny(columns=512, cells_per_column=8, max_new_synapse_count=5)
    b.load_state_dict(a.state_dict())
    for x in xs[23:]:
        np.testing.assert_array_equal(a.compute(x), b.compute(x))
        assert a.anomaly == b.anomaly
    assert (a.segments, a.synapses) == (b.segments, b.synapses)


def test_mt19937_matches_std_mt19937():
    from neoslam_stream.algorithms.temporal_memory_kernels import mt_next, mt_seed

    mt = mt_seed(np.uint32(42))
    idx = np.array([624], dtype=np.int64)
    # the first outputs of std::mt19937(42), as documented for g++
    assert [int(mt_next(mt, idx)) for _ in range(3)] == [1608637542, 3421126067, 4083286876]


def test_bad_columns_rejected():
    tm = tiny()
    with pytest.raises(ValueError):
        tm.compute([7])
    with pytest.raises(ValueError):
        tm.compute(np.zeros((2, 2), int))


def test_random_tie_rule_draws_among_the_least_used_after_the_shuffle():
    # fresh TM, K = 3: the shuffle of the 3 cells takes 2 draws of std::mt19937(42), the pick is the
    # 3rd: 4083286876 % 3 = 1 (digit sum 52), so the winner is the column's cell 1
    tm = tiny(tie_break="random")
    tm.compute([2])
    assert tm.winner_cells.tolist() == [2 * 3 + 1]
    assert tm.active_cells.tolist() == [6, 7, 8]


def test_non_integer_columns_rejected():
    tm = tiny()
    with pytest.raises(ValueError, match="integer"):
        tm.compute(np.array([1.0, np.nan]))
    tm.compute(np.array([], dtype=float))  # an empty step is allowed, whatever its dtype
    assert tm.active_cells.size == 0


def test_load_state_from_another_configuration_rejected():
    a = tiny()
    a.compute([0, 1])
    b = tiny(tie_break="random")
    with pytest.raises(ValueError, match="tie_break"):
        b.load_state_dict(a.state_dict())


def test_synapse_cap_ties_go_to_the_lower_synapse_id_not_the_lower_slot():
    tm = tiny(max_synapses_per_segment=4, max_new_synapse_count=3, activation_threshold=3)
    seg = tm.createSegment(4)
    tm.add_synapse(seg, 0, 0.3)  # id 0: onto a previous winner
    tm.add_synapse(seg, 8, 0.05)  # id 1: inactive, falls below epsilon and is destroyed
    tm.add_synapse(seg, 9, 0.3)  # id 2
    tm.add_synapse(seg, 10, 0.3)  # id 3: moves into slot 1 when id 1 goes
    tm.compute([0, 1], learn=False)  # winners: cells 0 and 3
    # column 1 bursts on its matching segment (pot 1): adapt leaves [0, 10, 9] with 9 and 10 at 0.2;
    # grow 3 - 1 = 2 of 2 candidates: overrun 3 + 2 - 4 = 1 removes the weaker non-candidate with
    # the lower synapse id (cell 9, id 2) although cell 10 sits in the earlier slot
    tm.compute([1], learn=True)
    pre, perm = tm.synapses_of_segment(seg)
    assert sorted(pre.tolist()) == [0, 3, 10]
    got = dict(zip(pre.tolist(), perm.tolist(), strict=True))
    assert got[0] == pytest.approx(0.6, abs=1e-6)  # 0.3 + 0.1, then raised to initialPermanence
    assert got[3] == pytest.approx(0.6, abs=1e-6) and got[10] == pytest.approx(0.2, abs=1e-6)
