"""B's centring counted in places, B's descriptors, and D's re-ranking of its shortlist by them:
hand-worked cases."""

from __future__ import annotations

import numpy as np
import pytest

from neoslam_stream.algorithms.descriptors import IntervalDescriptors
from neoslam_stream.algorithms.projector import BinaryProjector, RunningCentre, int8_descriptor
from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig
from neoslam_stream.nodes.frontend import make_node
from neoslam_stream.runtime.messages import Message


def test_without_kappa_every_frame_enters_a_window_of_frames():
    c = RunningCentre(2, 0.0, np.zeros(1))
    out = [float(c(np.array([v]))[0]) for v in (4.0, 8.0, 2.0)]
    # m = 4, then 4 + (8 - 4) / 2 = 6, then 6 + (2 - 6) / 2 = 4
    assert out == [0.0, 2.0, -2.0]


def test_with_kappa_a_frame_enters_only_when_it_moved_from_the_last_that_entered():
    """Worked by hand in 2-D, W 10, kappa 0.5 (the spread: RMS distance to the cumulative mean)."""
    c = RunningCentre(10, 0.5, np.zeros(2))
    rows = [np.array(v) for v in ((0.0, 0.0), (4.0, 0.0), (4.1, 0.0), (0.0, 4.0))]
    out = [c(r) for r in rows]
    # 1: enters (the first); mean (0, 0)
    np.testing.assert_allclose(out[0], [0.0, 0.0])
    # 2: spread sqrt(8 / 2) = 2, moved 4 >= 1: enters, mean (0, 0) + (4, 0) / 2 = (2, 0)
    np.testing.assert_allclose(out[1], [2.0, 0.0])
    # 3: spread sqrt((8 + 2.1 * 1.4) / 3) = 1.91, moved 0.1 < 0.95: stays out, centred by (2, 0)
    np.testing.assert_allclose(out[2], [2.1, 0.0])
    # 4: moved |(0, 4) - (4, 0)| = 5.66 >= 0.5 * 2.67: enters, mean (2, 0) + ((0, 4) - (2, 0)) / 3
    np.testing.assert_allclose(out[3], [0.0, 4.0] - np.array([2 - 2 / 3, 4 / 3]))
    assert c.n_entered == 3 and c.n_seen == 4


def test_the_descriptor_is_the_centred_features_at_a_peak_of_127():
    np.testing.assert_array_equal(int8_descriptor(np.array([0.5, -1.0, 0.25])), [64, -127, 32])
    np.testing.assert_array_equal(int8_descriptor(np.zeros(3)), [0, 0, 0])


def test_b_gives_its_bits_and_the_descriptor_of_what_it_projected():
    bp = BinaryProjector(input_dim=64, seed=3, centre_window=4, centre_kappa=0.5, descriptor=True)
    ref = BinaryProjector(input_dim=64, seed=3, centre_window=4, centre_kappa=0.5)
    feats = np.random.default_rng(0).standard_normal((5, 64)).astype(np.float32)
    codes = bp.codes_batch(feats)
    centred = ref.centre(feats)  # the same rule on the same frames
    for code, c, bits in zip(codes, centred, BinaryProjector(input_dim=64, seed=3, centre_window=4,
                                                           centre_kappa=0.5).bits_batch(feats), strict=True):
        np.testing.assert_array_equal(code.bits, bits)
        np.testing.assert_array_equal(code.descriptor, int8_descriptor(c))
    assert BinaryProjector(input_dim=64, seed=3).codes_batch(feats)[0].descriptor is None


def test_a_running_mean_counted_in_places_survives_a_state_and_refuses_another_kappa():
    feats = np.random.default_rng(1).standard_normal((12, 16)).astype(np.float32)
    a = BinaryProjector(input_dim=16, seed=0, centre_window=3, centre_kappa=0.5)
    a.bits_batch(feats[:6])
    b = BinaryProjector(input_dim=16, seed=0, centre_window=3, centre_kappa=0.5)
    b.load_state_dict(a.state_dict())
    for x, y in zip(a.bits_batch(feats[6:]), b.bits_batch(feats[6:]), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="centre_kappa"):
        BinaryProjector(input_dim=16, seed=0, centre_window=3).load_state_dict(a.state_dict())


def test_an_interval_descriptor_is_the_mean_of_its_frames_unit_descriptors():
    d = IntervalDescriptors()
    d.add_frame(np.array([10, 0], np.int8))
    d.add_frame(np.array([0, 100], np.int8))  # unit vectors (1, 0) and (0, 1): the mean is diagonal
    d.close_interval(0)
    d.open_interval()
    d.close_interval(1)  # an interval with no descriptor
    cos = d.cosines(np.array([3, 3], np.int8), np.array([0, 1]))
    assert cos[0] == pytest.approx(1.0) and np.isnan(cos[1])
    assert d.cosines(np.array([5, -5], np.int8), np.array([0]))[0] == pytest.approx(0.0)
    again = IntervalDescriptors()
    again.load_state_dict(d.state_dict())
    np.testing.assert_allclose(again.cosines(np.array([1, 2], np.int8), np.array([0, 1])),
                               d.cosines(np.array([1, 2], np.int8), np.array([0, 1])))


def test_d_reranks_its_shortlist_by_the_votes_of_cells_and_descriptors():
    d = SpatialViewCells(SpatialViewConfig(calibration={"enabled": True}, rerank=3))
    for slot, v in enumerate(([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0])):
        d.descriptors.add_frame(np.array(v, np.int8) * 100)
        d.descriptors.close_interval(slot)
        d.descriptors.open_interval()
    scores = np.array([0.9, 0.85, 0.8, 0.1])  # slots 0, 1, 2 are shortlisted
    # standardised over the three: scores 0.9, 0.85, 0.8 vote +1.22, 0, -1.22; a frame like slot 1
    # (cosines 0, 1, 0) votes -0.71, +1.41, -0.71: sums 0.52, 1.41, -1.93, slot 1 wins
    assert d._reranked(scores, np.array([0, 100, 0], np.int8)) == 1
    # a frame like slot 2 only: sums 0.52, -0.71, 0.19: the descriptor alone does not carry slot 2
    assert d._reranked(scores, np.array([0, 0, 100], np.int8)) == 0
    # like slot 3, which is not shortlisted: its descriptor is never read
    assert d._reranked(scores, np.array([100, 100, 0], np.int8)) == 0  # cosines 0.71, 0.71, 0: slot 0
    assert d._reranked(scores, None) is None
    off = SpatialViewCells(SpatialViewConfig(calibration={"enabled": True}))
    assert off._reranked(scores, np.array([0, 100, 0], np.int8)) is None


def test_rerank_needs_the_calibrated_decision():
    with pytest.raises(ValueError, match="rerank needs calibration"):
        SpatialViewConfig(rerank=5)


def test_the_descriptor_travels_from_b_through_c_to_d():
    b = make_node("codes", projector=dict(input_dim=32, seed=1, centre_window=2, descriptor=True))
    c = make_node("winner_cells", neocortex={})
    d = make_node("template_of", spatial_view=dict(calibration={"enabled": True}, rerank=3))
    feats = np.random.default_rng(2).standard_normal(32).astype(np.float32)
    (_, code), = b.process("visual_features", Message("visual_features", 0, 0.0, {"features": feats}))
    assert code["descriptor"].dtype == np.int8 and code["descriptor"].shape == (32,)
    (_, sdr), = c.process("bin_features", code)
    np.testing.assert_array_equal(sdr["descriptor"], code["descriptor"])
    (_, tmpl), = d.process("sdr", sdr)
    assert tmpl["id"] == 0 and d.core.spatial_view.descriptors.n == 0  # the open interval is not indexed yet


def test_the_view_a_place_ago_is_the_newest_kept_view_at_least_that_old():
    d = IntervalDescriptors()
    views = {0.0: [100, 0], 1.0: [0, 100], 2.0: [100, 100]}
    for t, v in views.items():
        d.note_view(t, np.array(v, np.int8), keep_s=1.5)
    q = np.array([100, 0], np.int8)
    # at 3.0 s, 1.5 s ago: the newest view at or before 1.5 s is the one at 1.0 s, orthogonal to q
    assert d.view_ago_cosine(q, 3.0, 1.5) == pytest.approx(0.0)
    # 0.5 s ago: the view at 2.0 s, 45 degrees from q
    assert d.view_ago_cosine(q, 2.5, 0.5) == pytest.approx(np.sqrt(0.5))
    # nothing that old yet
    assert d.view_ago_cosine(q, 3.0, 10.0) is None
    again = IntervalDescriptors()
    again.load_state_dict(d.state_dict())
    assert again.view_ago_cosine(q, 3.0, 1.5) == pytest.approx(0.0)
