"""Stage D on constructed SDRs; expected values worked by hand from the paper's definitions."""

import numpy as np
import pytest

import neoslam_stream.algorithms.interval_index as ii
from neoslam_stream.algorithms.spatial_view import SpatialViewCells
from neoslam_stream.nodes.frontend import make_node
from neoslam_stream.runtime.messages import Message


def sdr(*bits):
    return np.array(bits, dtype=np.uint32)


def block(i, width=6):
    """A distinct SDR per i (disjoint bits)."""
    return np.arange(i * width, (i + 1) * width, dtype=np.uint32)


def svc(**kw):
    params = dict(theta_alpha=3, theta_rho=2, theta_sigma=4, exclude_recent_intervals=1, sdr_size=256)
    params.update(kw)
    return SpatialViewCells(**params)


def test_similar_sdr_extends_the_interval():
    c = svc()
    r0 = c.compute(sdr(0, 1, 2, 3))
    r1 = c.compute(sdr(0, 1, 2, 9))  # alpha = 3 >= theta_alpha, duration 0 < theta_rho
    assert c.n_intervals == 1 and r0["id"] == r1["id"] == 0
    assert sorted(c.unions[0]) == [0, 1, 2, 3, 9]  # the union grows


def test_dissimilar_sdr_opens_a_new_interval_and_template():
    c = svc()
    c.compute(block(0))
    r = c.compute(block(1))  # alpha = 0
    assert c.n_intervals == 2 and r["id"] == 1 and not r["is_loop_closure"]


def test_interval_closes_after_theta_rho():
    c = svc(exclude_recent_intervals=2)
    a = block(0)
    for _ in range(3):  # durations 0 and 1 extend; the interval spans frames 0..2 = theta_rho + 1
        c.compute(a)
    assert c.n_intervals == 1 and (c.interval_start[0], c.interval_end[0]) == (0, 2)
    r = c.compute(a)  # duration 2 is not < theta_rho -> new interval; interval 0 is excluded (omega 2)
    assert c.n_intervals == 2 and r["id"] == 1 and not r["is_loop_closure"]


def test_no_match_inside_the_excluded_recent_intervals():
    c = svc(exclude_recent_intervals=3)
    for i in range(3):
        c.compute(block(i))
    r = c.compute(block(0))  # 4 intervals now; candidates k < 4 - 3 = 1: interval 0 is one
    assert r["is_loop_closure"] and r["best_interval"] == 0
    c = svc(exclude_recent_intervals=3)
    for i in range(2):
        c.compute(block(i))
    r = c.compute(block(0))  # 3 intervals; candidates k < 0: none, although interval 0 is identical
    assert not r["is_loop_closure"] and r["id"] == 2


def test_loop_closure_reuses_the_template_of_the_matched_interval_not_its_neighbour():
    c = svc()
    ids = [c.compute(block(i))["id"] for i in range(5)]
    assert ids == [0, 1, 2, 3, 4]  # consecutive from 0
    r = c.compute(block(2))
    assert r["is_loop_closure"] and r["best_interval"] == 2 and r["id"] == 2
    assert r["best_score"] == 6
    # the interval opened by the revisit keeps the matched template
    assert c.interval_template[-1] == 2
    r = c.compute(block(7))  # a new place after the loop: the next fresh id
    assert r["id"] == 5


def test_score_must_exceed_theta_sigma_strictly():
    c = svc(theta_sigma=6)
    for i in range(3):
        c.compute(block(i))
    r = c.compute(block(0))  # score 6 is not > 6
    assert not r["is_loop_closure"]


def test_union_normalised_threshold_scales_theta_sigma_to_the_union():
    # interval 0 merges two frames: Y_0 = {0..5} | {0..3, 6, 7} = {0..7}, 8 cells; a query sharing 5
    # of its 6 cells with Y_0 scores 5 > theta_sigma 4 (the paper's rule: a closure), but
    # normalised 5 * 6 / max(8, 6) = 3.75 is not > 4; onto a single-frame interval (|Y| = |y| = 6)
    # the same score 5 stays a closure, so the scaling changes nothing there
    query = sdr(0, 1, 2, 3, 4, 100)
    for normalised, closure, score in ((False, True, 5), (True, False, 3.75)):
        c = svc(union_normalised=normalised)
        c.compute(sdr(0, 1, 2, 3, 4, 5))
        c.compute(sdr(0, 1, 2, 3, 6, 7))  # alpha 4 >= 3: extends interval 0
        c.compute(block(5))
        assert c.n_intervals == 2 and len(c.unions[0]) == 8
        r = c.compute(query)
        assert r["best_score"] == score and r["is_loop_closure"] is closure
    c = svc(union_normalised=True)
    c.compute(sdr(0, 1, 2, 3, 4, 5))
    c.compute(block(5))
    r = c.compute(query)
    assert r["best_score"] == 5 and r["is_loop_closure"] and r["best_interval"] == 0


def test_union_normalised_ranks_a_single_frame_above_a_larger_union():
    # the first three frames share >= 3 cells (theta_alpha) with interval 0: Y_0 = {0..5, 8, 9} (8
    # cells); the fourth shares 5 but interval 0 already spans theta_rho + 1 = 3 frames, so it opens
    # interval 1 = {0, 1, 2, 3, 4, 20}; two disjoint frames open intervals 2 and 3. For the
    # query {0, 1, 2, 3, 4, 100}: raw s_0 = 5, s_1 = 5 (a tie: the paper picks interval 0);
    # normalised s_0 = 5 * 6 / 8 = 3.75, s_1 = 5 * 6 / 6 = 5: interval 1 wins, runner-up interval 0
    frames = [sdr(0, 1, 2, 3, 4, 5), sdr(0, 1, 2, 3, 8, 9), sdr(0, 1, 2, 8, 9, 5), sdr(0, 1, 2, 3, 4, 20),
              block(10), block(11)]
    query = sdr(0, 1, 2, 3, 4, 100)
    for normalised, best, second in ((False, (0, 5), (1, 5)), (True, (1, 5.0), (0, 3.75))):
        c = svc(theta_sigma=3, union_normalised=normalised)
        for f in frames:
            c.compute(f)
        assert [len(u) for u in c.unions[:2]] == [8, 6] and c.n_intervals == 4
        r = c.compute(query)
        assert (r["best_interval"], r["best_score"]) == best and r["is_loop_closure"]
        assert (r["second_interval"], r["second_score"]) == second


@pytest.mark.parametrize("normalised", [False, True])
def test_theta_margin_refuses_a_winner_close_to_its_runner_up(normalised):
    # two single-frame intervals: the query shares 6 cells with interval 0 and 4 with interval 1,
    # so the winner's margin is 6 - 4 = 2 (normalised the same: every |Y| = |y| = 8)
    frames = [sdr(0, 1, 2, 3, 4, 5, 6, 7), sdr(0, 1, 2, 3, 50, 51, 52, 53), block(20, 8)]
    query = sdr(0, 1, 2, 3, 4, 5, 98, 99)
    for margin, closure in ((0, True), (2, True), (2.5, False), (3, False)):
        c = svc(theta_alpha=5, theta_margin=margin, union_normalised=normalised)
        for f in frames:
            c.compute(f)
        assert c.n_intervals == 3
        r = c.compute(query)
        assert (r["best_score"], r["second_interval"], r["second_score"]) == (6, 1, 4)
        assert r["is_loop_closure"] is closure and r["best_interval"] == (0 if closure else -1), margin


def test_ties_go_to_the_lowest_interval():
    c = svc(theta_alpha=100)  # never extend
    c.compute(block(0))
    c.compute(block(0))  # interval 1 also holds block 0 (interval 0 excluded at that time)
    c.compute(block(5))
    r = c.compute(block(0))
    assert r["is_loop_closure"] and r["best_interval"] == 0


def test_same_interval_keeps_the_current_template():
    c = svc(theta_sigma=100)
    c.compute(sdr(1, 2, 3, 4))
    r = c.compute(sdr(1, 2, 3, 5))
    assert r["id"] == 0 and not r["is_loop_closure"]


def test_state_round_trip_continues_identically():
    rng = np.random.default_rng(0)
    seq = [rng.choice(256, 12, replace=False).astype(np.uint32) for _ in range(60)]
    seq += seq[:20]  # revisits
    a = svc(theta_alpha=6, theta_sigma=8)
    for y in seq[:45]:
        a.compute(y)
    b = svc(theta_alpha=6, theta_sigma=8)
    b.load_state_dict(a.state_dict())
    for y in seq[45:]:
        assert a.compute(y) == b.compute(y)


def test_a_state_made_with_other_parameters_is_refused():
    a = svc(theta_sigma=8)
    for i in range(4):
        a.compute(block(i))
    state = a.state_dict()
    with pytest.raises(ValueError, match=r"theta_sigma: the state was made with 8, the config has 4"):
        svc().load_state_dict(state)
    with pytest.raises(ValueError, match=r"sdr_size: the state was made with 256, the config has 512"):
        svc(theta_sigma=8, sdr_size=512).load_state_dict(state)
    # parameters a state does not depend on may differ
    b = svc(theta_sigma=8, theta_margin=1.0)
    b.load_state_dict(state)
    assert b.n_intervals == 4 and b.config.theta_margin == 1.0


def test_invalid_sdr_is_rejected():
    c = svc()
    with pytest.raises(ValueError):
        c.compute(np.array([1, 300]))


def test_node_emits_templates_and_the_recorder_writes_them(tmp_path):
    from neoslam_stream.nodes.recorder import RecorderNode

    st = make_node("template_of", spatial_view=dict(theta_alpha=3, theta_rho=2, theta_sigma=4,
                                                exclude_recent_intervals=1, sdr_size=256))
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    outs = []
    for f, i in enumerate([0, 1, 2, 1]):
        out = st.process("sdr", Message("sdr", f, f * 0.1, {"cells": block(i), "size": 256}))
        for topic, m in out:
            rec.process(topic, m)
        outs += out
    assert [m["id"] for _, m in outs] == [0, 1, 2, 1]
    assert outs[-1][1]["is_loop_closure"] is True
    rec.flush()
    lines = (tmp_path / "templates.csv").read_text().splitlines()
    assert lines[0] == "frame,stamp,template_id,is_loop_closure,best_interval,best_score"
    # frame 3 revisits block 1 (interval 1): template 1, a closure, its score |block 1| = 6 cells
    assert lines[4] == "3,0.300000,1,1,1,6"


def _brute_force_full(frames, theta_alpha, theta_rho, theta_sigma, omega):
    """Every output of compute() by the paper's rule with Python sets, scoring every interval:
    (id, is_loop_closure, best_interval, best_score) and the runner-up (interval, score)."""
    unions, start, end, templates, out = [], [], [], [], []
    n_templates, current = 0, -1
    for t, y in enumerate(frames):
        y = set(int(v) for v in y)
        new = not unions or not (len(unions[-1] & y) >= theta_alpha and end[-1] - start[-1] < theta_rho)
        if new:
            unions.append(set(y))
            start.append(t)
            end.append(t)
            templates.append(-1)
        else:
            unions[-1] |= y
            end[-1] = t
        scores = [len(u & y) for u in unions[: max(0, len(unions) - omega)]]
        ranked = sorted(range(len(scores)), key=lambda k: (-scores[k], k))
        best = ranked[0] if ranked else -1
        best_score = scores[best] if ranked else 0
        second, second_score = (ranked[1], scores[ranked[1]]) if len(ranked) > 1 else (-1, 0)
        loop = best >= 0 and best_score > theta_sigma
        if loop:
            template = templates[best]
        elif new:
            template, n_templates = n_templates, n_templates + 1
        else:
            template = current
        if new:
            templates[-1] = template
        current = template
        out.append((template, loop, best if loop else -1, best_score, second, second_score))
    return out


def test_index_compaction_gives_the_same_templates_as_a_brute_force_scan(monkeypatch):
    # compact after every few frames, so scores come from the CSR part, the linked part and both
    monkeypatch.setattr(ii, "COMPACT_MIN", 40)
    rng = np.random.default_rng(3)
    places = [rng.choice(400, 30, replace=False) for _ in range(12)]
    frames = []
    for _ in range(5):  # revisit the same 12 places, with noise
        for p in places:
            noisy = np.union1d(p[rng.random(30) > 0.1], rng.choice(400, 3))
            frames.append(noisy)
    params = dict(theta_alpha=24, theta_rho=2, theta_sigma=22, exclude_recent_intervals=2)
    svc = SpatialViewCells(sdr_size=400, **params)
    got = [svc.compute(f)["id"] for f in frames]
    svc.index.compact()  # waits for a background merge still running
    assert svc.index.merges >= 1 and svc.index._post.shape[0] > 0  # merges did happen, in the background
    expected = [o[0] for o in _brute_force_full(frames, params["theta_alpha"], params["theta_rho"],
                                                params["theta_sigma"], params["exclude_recent_intervals"])]
    assert got == expected
    assert len(set(expected)) < len(frames)  # loop closures happened, so the test exercises them


# ------------------------------------------------------------- bounded (sublinear) search

def _route_stream(n_frames, n_places, seed, noise, cells=32):
    """SDRs shaped like the neocortex's: 512 active columns of 2048, one winner cell in each, so
    the posting lists are long and overlap like real ones. Frames drift through places (3 frames
    a place, lap after lap: revisits) and each frame swaps a fraction ``noise`` of its cells for
    random ones (another winner cell, another column)."""
    rng = np.random.default_rng(seed)
    base = [np.sort(rng.choice(2048, 512, replace=False)) * cells + rng.integers(0, cells, 512)
            for _ in range(n_places)]
    out = []
    for t in range(n_frames):
        s = base[(t // 3) % n_places].copy()
        swap = rng.random(512) < noise
        s[swap] = rng.choice(2048 * cells, int(swap.sum()), replace=False)
        out.append(np.unique(s).astype(np.uint32))
    return out


@pytest.mark.parametrize("noise,theta_sigma", [(0.08, 440), (0.25, 300)])
def test_bounded_search_equals_a_brute_force_scan_of_every_interval(monkeypatch, noise, theta_sigma):
    # merges every few frames: the search reads the CSR part, a frozen part and the linked part
    monkeypatch.setattr(ii, "COMPACT_MIN", 3000)
    frames = _route_stream(420, 25, seed=1, noise=noise)
    params = dict(theta_alpha=384, theta_rho=3, theta_sigma=theta_sigma, exclude_recent_intervals=3)
    svc = SpatialViewCells(**params)
    got = []
    for f in frames:
        r = svc.compute(f)
        got.append((r["id"], r["is_loop_closure"], r["best_interval"], r["best_score"], *svc.runner_up))
    expected = _brute_force_full(frames, params["theta_alpha"], params["theta_rho"], theta_sigma,
                                 params["exclude_recent_intervals"])
    assert got == expected
    assert svc.index.merges >= 3
    loops = sum(e[1] for e in expected)
    assert 0 < loops < len(frames)  # closures and frames without one (best_score below theta_sigma)


def test_bounded_search_equals_exhaustive_scoring_on_a_long_stream(monkeypatch):
    monkeypatch.setattr(ii, "COMPACT_MIN", 20000)
    frames = _route_stream(2400, 70, seed=2, noise=0.12) + _route_stream(300, 40, seed=3, noise=0.5)
    a = SpatialViewCells(theta_sigma=455)
    a.index.exhaustive = True
    b = SpatialViewCells(theta_sigma=455)
    read = 0
    for i, f in enumerate(frames):
        ra, rb = a.compute(f), b.compute(f)
        assert (ra, a.runner_up) == (rb, b.runner_up), i
        read += b.index.last_search[0]
    assert b.index.merges >= 5 and a.n_intervals > 500
    # and it is a bounded search: far fewer postings read than the index holds per frame
    assert read < 0.5 * sum(len(u) for u in b.unions) * len(frames) / 2


def test_bounded_search_edge_cases():
    # one candidate; candidates sharing no cell (lowest index, score 0); ties (lowest index)
    c = svc(exclude_recent_intervals=1, theta_sigma=5)
    c.compute(block(0))
    c.compute(block(1))
    assert c.runner_up == (-1, 0)  # one candidate: interval 0
    r = c.compute(block(5))  # shares nothing with 0 or 1: best 0 (score 0), runner-up 1
    assert r["best_score"] == 0 and c.runner_up == (1, 0)
    r = c.compute(block(1))  # intervals 0, 1, 2 are candidates; 1 is identical, 0 and 2 tie at 0
    assert r["best_score"] == 6 and c.runner_up == (0, 0)
    c.compute(block(6))  # interval 4; interval 3 (block 1) becomes a candidate
    r = c.compute(block(1))  # interval 5: intervals 1 and 3 tie at 6, the lower index is the best
    assert (r["best_interval"], r["best_score"]) == (1, 6) and c.runner_up == (3, 6)


# ------------------------------------------------------------- bit-sliced count over dense rows

def _dense_stream(n_frames, n_places, seed, noise):
    """Real SDRs' shape (docs/frontend.md): winner cell 0 of 512 of 2048 columns, so only ~2048
    cells ever occur and most get dense rows; plus a few cells anywhere in 65536 (no dense row)."""
    frames = _route_stream(n_frames, n_places, seed, noise, cells=1)
    rng = np.random.default_rng(seed + 100)
    return [np.union1d(f, rng.choice(65536, 4, replace=False)).astype(np.uint32) for f in frames]


@pytest.mark.parametrize("noise,theta_sigma", [(0.08, 440), (0.3, 250)])
def test_bit_sliced_search_equals_a_brute_force_scan_of_every_interval(monkeypatch, noise, theta_sigma):
    # rows appear early and while merges run (their lists then sit in all three parts)
    monkeypatch.setattr(ii, "DENSE_MIN", 8)
    monkeypatch.setattr(ii, "COMPACT_MIN", 3000)
    frames = _dense_stream(480, 25, seed=4, noise=noise)
    params = dict(theta_alpha=384, theta_rho=3, theta_sigma=theta_sigma, exclude_recent_intervals=3)
    svc = SpatialViewCells(**params)
    svc.index.sliced = True
    got, paths = [], []
    for f in frames:
        r = svc.compute(f)
        got.append((r["id"], r["is_loop_closure"], r["best_interval"], r["best_score"], *svc.runner_up))
        paths.append(svc.index.last_path)
    expected = _brute_force_full(frames, params["theta_alpha"], params["theta_rho"], theta_sigma,
                                 params["exclude_recent_intervals"])
    assert got == expected
    assert paths.count("sliced") > 0.9 * len(frames) and svc.index.merges >= 3
    assert 1000 < svc.index._n_dense - 1 < 2100  # the route's cells got rows, the random extra ones did not
    assert 0 < sum(e[1] for e in expected) < len(frames)


def test_bit_sliced_search_across_blocks_and_limits_equals_exhaustive_scoring():
    # > one block of SLICE_BLOCK intervals, loaded like a checkpoint (rows built from the lists)
    rng = np.random.default_rng(5)
    places = [np.sort(rng.choice(2048, 512, replace=False)) for _ in range(40)]
    k = ii.SLICE_BLOCK + 3000
    unions = []
    for i in range(k):
        u = places[i % 40].copy()
        moved = rng.random(512) < 0.1
        u[moved] = rng.integers(0, 2048, int(moved.sum()))
        unions.append(np.unique(u).astype(np.uint32))
    svc = SpatialViewCells()
    svc.load_state_dict({**svc.state_dict(), "unions": unions, "start": np.arange(k) * 4,
                         "end": np.arange(k) * 4 + 3, "template": np.arange(k), "n_templates": k,
                         "current_template": k - 1, "t": 4 * k, "stamps": np.arange(k) * 4.0,
                         "indexed": np.arange(k - 1)})
    index = svc.index
    assert index._n_dense - 1 > 1900
    limits = [2, 63, 64, 65, 4097, ii.SLICE_BLOCK - 1, ii.SLICE_BLOCK, ii.SLICE_BLOCK + 1, k - 3]
    for q in range(12):
        y = svc._validate(np.union1d(places[q * 3 % 40][rng.random(512) > 0.05], rng.choice(65536, 3)))
        for limit in limits:
            index.sliced = True
            got = index.top2_bounded(y, limit)
            assert index.last_path == "sliced"
            assert got == index.top2_exhaustive(y, limit), (q, limit)
        index.sliced = None  # the cost model picks the bit-sliced count for these real-shaped SDRs
        assert index.top2_bounded(y, k - 3) == index.top2_exhaustive(y, k - 3) and index.last_path == "sliced"
        # every score (the calibrated decision's): the bit-sliced count equals counting every posting
        counted = index.all_scores(y, rows=False).copy()
        assert np.array_equal(index.all_scores(y), counted) and index.last_count_path == "sliced"
    # SDRs spread over all 65536 cells keep short lists, no rows: the posting-list search
    sparse = SpatialViewCells()
    for _ in range(300):
        sparse.compute(rng.choice(65536, 512, replace=False))
    assert sparse.index._n_dense == 1 and sparse.index.last_path == "postings"
