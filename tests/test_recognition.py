"""The recognition figures of bench/stages.py (neoslam_stream/evaluation/recognition.py), worked
out by hand on tiny cases, and the causal mean-removed cosine against a direct computation."""

from __future__ import annotations

import numpy as np
import pytest

from neoslam_stream.evaluation.recognition import (
    best_matches,
    causal_centred_cosine,
    cosine,
    decision_curve,
    downsample,
    figures,
    overlaps,
    pr_curve,
    ranking_curve,
    sequence_curve,
)

#: 4 queries x 3 candidates; the right candidates: q0 -> c0, q1 -> c0, q2 -> c2, q3 none
SCORES = np.array([[0.9, 0.1, 0.3],
                   [0.2, 0.8, 0.4],
                   [0.5, 0.6, 0.7],
                   [0.1, 0.2, 0.3]])
RIGHT = np.array([[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 0]], bool)


def test_the_best_match_is_the_highest_allowed_score():
    best, score = best_matches(SCORES)
    assert best.tolist() == [0, 1, 2, 2] and score.tolist() == [0.9, 0.8, 0.7, 0.3]
    allowed = np.ones_like(RIGHT)
    allowed[0, 0] = False  # q0 may not match c0: its best is then c2
    allowed[3] = False  # q3 has no candidate at all
    best, score = best_matches(SCORES, allowed)
    assert best.tolist() == [2, 1, 2, -1] and score[0] == 0.3 and np.isnan(score[3])


def test_the_curve_of_best_matches_worked_by_hand():
    # best matches by score: 0.9 right, 0.8 wrong (q1's best is c1), 0.7 right, 0.3 wrong (q3 has
    # no right candidate); 3 positives (q0, q1, q2)
    c = ranking_curve(SCORES, np.ones_like(RIGHT), RIGHT)
    assert c.threshold.tolist() == [0.9, 0.8, 0.7, 0.3]
    assert c.precision == pytest.approx([1, 1 / 2, 2 / 3, 2 / 4])
    assert c.recall == pytest.approx([1 / 3, 1 / 3, 2 / 3, 2 / 3])
    assert c.positives == 3
    assert c.final_recall == pytest.approx(2 / 3)  # recall@1
    # the step-wise area: 1/3 gained at precision 1, 1/3 more at precision 2/3
    assert c.area() == pytest.approx(1 / 3 + 1 / 3 * 2 / 3)
    assert c.recall_at(0.9) == pytest.approx(1 / 3) and c.recall_at(1.0) == pytest.approx(1 / 3)
    assert c.recall_at(0.6) == pytest.approx(2 / 3) and c.recall_at(0.5) == pytest.approx(2 / 3)
    f = figures(c)
    assert f["recall_at_1"] == pytest.approx(2 / 3) and f["pr_area"] == pytest.approx(5 / 9)
    assert f["recall_at_precision"] == pytest.approx({"0.9": 1 / 3, "0.95": 1 / 3, "1.0": 1 / 3})


def test_equal_scores_are_accepted_together():
    # overlap counts 5, 5, 3: the two 5s come in at one threshold, one right of them
    c = pr_curve(np.array([5, 3, 5]), np.array([True, True, False]), positives=2)
    assert c.threshold.tolist() == [5, 3]
    assert c.precision == pytest.approx([1 / 2, 2 / 3]) and c.recall == pytest.approx([1 / 2, 1])
    assert c.area() == pytest.approx(1 / 2 * 1 / 2 + 1 / 2 * 2 / 3)
    assert c.recall_at(1.0) == 0.0  # no point reaches precision 1


def test_a_decision_ends_at_its_recall():
    # q0 decided c0 (right) on score 2, q1 decided onto a frame that is no candidate (wrong) on 5,
    # q2 decided nothing, q3 decided c2 (wrong: q3 has no right candidate) on 1
    c = decision_curve(np.array([True, True, False, True]), np.array([0, -1, 0, 2]),
                       np.array([2.0, 5.0, 9.0, 1.0]), RIGHT)
    assert c.threshold.tolist() == [5.0, 2.0, 1.0]
    assert c.precision == pytest.approx([0, 1 / 2, 1 / 3]) and c.recall == pytest.approx([0, 1 / 3, 1 / 3])
    assert c.final_recall == pytest.approx(1 / 3)  # decided and right / positives
    assert c.area() == pytest.approx(1 / 3 * 1 / 2)
    empty = decision_curve(np.zeros(4, bool), np.full(4, -1), np.zeros(4), RIGHT)
    assert empty.final_recall == 0.0 and empty.area() == 0.0 and empty.recall_at(0.9) == 0.0


def test_a_ranking_with_the_decisions_evidence_worked_by_hand():
    # query frames 10..14 against candidate frames 0..4; each query's best match by score:
    # 10 -> c0, 11 -> c1, 12 -> c2, 13 -> c4 (a jump of 2), 14 -> c0 (back to the start)
    queries, candidates = np.arange(10, 15), np.arange(5)
    scores = np.full((5, 5), 0.1)
    for q, (c, s) in enumerate([(0, 0.5), (1, 0.6), (2, 0.7), (4, 0.9), (0, 0.4)]):
        scores[q, c] = s
    right = np.zeros((5, 5), bool)
    for q, c in enumerate([0, 1, 2, 3, 0]):  # 13's right place is c3: its best match c4 is wrong
        right[q, c] = True
    allowed = np.ones_like(right)
    # length 0: every best match is scored by itself (the ranking's own curve)
    alone = sequence_curve(scores, allowed, right, queries, candidates, 0, 1.0, 0)
    direct = ranking_curve(scores, allowed, right)
    assert alone.threshold.tolist() == direct.threshold.tolist()
    assert alone.precision.tolist() == direct.precision.tolist()
    # length 1, max_step 1, no slack: the frame before must lie within 1 of this frame's match.
    # 10: frame 9 is no query -> never accepted; 11 (c1 after c0): mean(0.5, 0.6) = 0.55, right;
    # 12 (c2 after c1): 0.65, right; 13 (c4 after c2, 2 apart): refused; 14 (c0 after c4): refused
    seq = sequence_curve(scores, allowed, right, queries, candidates, 1, 1.0, 0)
    assert seq.threshold == pytest.approx([0.65, 0.55])
    assert seq.precision == pytest.approx([1, 1]) and seq.recall == pytest.approx([1 / 5, 2 / 5])
    # a slack of 1 lets 13's jump through, a wrong match scored mean(0.7, 0.9) = 0.8, first
    slack = sequence_curve(scores, allowed, right, queries, candidates, 1, 1.0, 1)
    assert slack.threshold == pytest.approx([0.8, 0.65, 0.55])
    assert slack.precision == pytest.approx([0, 1 / 2, 2 / 3])


def test_the_downsampled_curve_keeps_its_ends():
    n = 200
    c = pr_curve(np.arange(n, 0, -1, dtype=float), np.arange(n) % 3 == 0, positives=n)
    d = downsample(c, 50)
    assert len(d["recall"]) == 50
    assert d["threshold"][0] == n and d["threshold"][-1] == 1
    assert d["recall"][-1] == pytest.approx(c.recall[-1], abs=1e-4)


def test_overlaps_count_shared_indices():
    sets = [np.array([1, 5, 9]), np.array([9, 5, 10]), np.array([2]), np.array([], np.int64)]
    assert overlaps(sets).tolist() == [[3, 2, 0, 0], [2, 3, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]]


def test_the_causal_centred_cosine_equals_the_direct_computation():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(9, 6)) + 2.0  # a common component, as CNN features have
    got = causal_centred_cosine(f)
    for q in range(1, len(f)):
        mu = f[:q + 1].mean(axis=0)  # what was seen up to the query
        a = f[q] - mu
        for r in range(len(f)):
            b = f[r] - mu
            assert got[q, r] == pytest.approx(a @ b / np.linalg.norm(a) / np.linalg.norm(b), abs=1e-9)
    assert np.all(got[0] == 0.0)  # the first frame is its own mean: nothing left to compare


def test_cosine_of_rows():
    f = np.array([[3.0, 4.0], [4.0, 3.0], [0.0, 0.0], [-3.0, -4.0]])
    assert cosine(f) == pytest.approx(np.array([[1, 24 / 25, 0, -1], [24 / 25, 1, 0, -24 / 25],
                                                [0, 0, 0, 0], [-1, -24 / 25, 0, 1]]))


# ------------------------------------------------------------------------------ two traversals
def test_a_two_traversal_stream_reads_its_walks_and_its_pairs(tmp_path, monkeypatch):
    """bench/streams.py's traversals_stream on a tiny copy of the Gardens Point layout: images in
    sorted order, the reference walk first, ``pairs`` and the tolerance from gt.json; absent: skipped."""
    import json
    import sys
    from pathlib import Path

    import cv2

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from streams import MissingData, traversals_stream

    monkeypatch.setenv("NEOSLAM_DATASETS", str(tmp_path))
    with pytest.raises(MissingData, match="gardens_point_walking not found"):
        traversals_stream("gardens", "hard", "a", tmp_path / "cache")
    root = tmp_path / "gardens_point_walking"
    for walk, level in (("day_left", 10), ("night_right", 200)):
        (root / walk).mkdir(parents=True)
        for i in range(4):
            img = np.full((6, 8, 3), level + i, np.uint8)
            img[..., 2] = 0  # red off (OpenCV writes B, G, R): it must come back first, as RGB
            cv2.imwrite(str(root / walk / f"Image{i:03d}.png"), img)
    # query frame 0 shows reference frame 1, query frame 2 reference frame 3; 1 and 3 show none
    (root / "gt.json").write_text(json.dumps({"pairs": [[0, 1], [2, 3]], "tolerance_frames": 1}))
    s = traversals_stream("gardens", "hard", "a", tmp_path / "cache")
    frames = list(s.frames())
    assert len(frames) == 8 and s.stamps.tolist() == list(range(8))
    assert [int(f[0, 0, 1]) for f in frames] == [10, 11, 12, 13, 200, 201, 202, 203]
    assert np.all(frames[0][..., 0] == 0)  # OpenCV's BGR turned to RGB
    queries, candidates, allowed, right = s.recognition_truth()
    assert queries.tolist() == [4, 5, 6, 7] and candidates.tolist() == [0, 1, 2, 3] and allowed.all()
    assert right.tolist() == [[1, 1, 1, 0], [0, 0, 0, 0], [0, 0, 1, 1], [0, 0, 0, 0]]
    # closures: (4 -> 1) right, (6 -> 0) 3 frames off, (5 -> 2) a query with no place, (2 -> 1) in
    # the reference walk (not a query)
    got = s.score([(4, 1), (6, 0), (5, 2), (2, 1)])
    assert got == {"closures": 3, "correct": 1, "precision": 1 / 3, "recall": 1 / 2, "first_traversal_closures": 1}
