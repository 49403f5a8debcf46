"""A loop closure is a revisit: matches to a place just passed are re-recognitions, counted apart
(evaluation/closures.py); the precision-recall curve over the decisions' confidence; the relative
pose error over distances of travel (evaluation/poses.py). Every expected value is worked by hand."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from neoslam_stream.cli import main
from neoslam_stream.evaluation import (
    closures_by_odometry,
    left_distance,
    loop_closure_quality,
    rpe,
    write_tum,
)
from neoslam_stream.evaluation.poses import rpe_pairs
from neoslam_stream.nodes.run_rows import CLOSURES_HEADER, TEMPLATES_HEADER

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

#: out and back along x at 1 m/s, a frame a second: frames 0-10 at x = 0..10, 11-20 at x = 9..0
X = [float(k) for k in range(11)] + [float(20 - k) for k in range(11, 21)]
#: frame -> (matched frame, confidence): three returns and a fourth without a confidence, and
#: four matches to places just passed
MATCHES = {16: (10, 2.0),   # x 4 onto x 10: travelled 6 m > 5: a closure, 6 m off: wrong
           17: (3, 3.0),    # x 3 onto x 3: 14 m: a closure, correct
           18: (5, 0.5),    # x 2 onto x 5: 13 m: a closure, 3 m off: wrong
           19: (1, None),   # x 1 onto x 1: 18 m: a closure, correct, no confidence
           3: (1, 1.0),     # 2 m travelled: a re-recognition (2 m off)
           6: (5, 1.0),     # 1 m: a re-recognition (1 m off: within the radius)
           12: (8, 1.0),    # to x 10 and back to x 8: 4 m: a re-recognition
           13: (8, 1.0)}    # x 7 onto x 8: exactly 5 m, not more: a re-recognition


def _run_folder(tmp_path: Path) -> np.ndarray:
    gt = np.array([[k, x, 0.0, 0.0 if k <= 10 else math.pi] for k, x in enumerate(X)])
    write_tum(tmp_path / "groundtruth.tum", gt)
    tpl = [f"{k},{k:.6f},{MATCHES[k][0] if k in MATCHES else k},{int(k in MATCHES)},-1,0" for k in range(len(X))]
    (tmp_path / "templates.csv").write_text(TEMPLATES_HEADER + "\n".join(tpl) + "\n")
    rows = [f"{k},{k:.6f},{m},{m},,0,,,{'' if c is None else c}" for k, (m, c) in sorted(MATCHES.items())]
    (tmp_path / "closures.csv").write_text(CLOSURES_HEADER + "\n".join(rows) + "\n")
    return gt


def test_a_match_to_a_place_just_passed_is_a_re_recognition(tmp_path):
    gt = _run_folder(tmp_path)
    assert left_distance(1.0) == 5.0  # five radii
    q = loop_closure_quality(tmp_path / "templates.csv", gt, radius=1.0, min_gap_s=5.0,
                             closures_csv=tmp_path / "closures.csv")
    assert (q["closures"], q["correct"], q["precision"]) == (4, 2, 0.5)
    assert q["re_recognitions"] == {"count": 4, "correct": 3}
    # revisits: frames 13-20 (within 1 m of a place seen more than 5 s before); 17 and 19 found
    assert q["revisit_frames"] == 8 and q["recall"] == pytest.approx(2 / 8)
    assert (q["left_m"], q["travelled_from"]) == (5.0, "ground truth")
    # a shorter D makes the return after 4 m (frame 12) a closure too, a longer one none of them
    assert loop_closure_quality(tmp_path / "templates.csv", gt, 1.0, 5.0, tmp_path / "closures.csv",
                                left_m=3.0)["closures"] == 6
    assert loop_closure_quality(tmp_path / "templates.csv", gt, 1.0, 5.0, tmp_path / "closures.csv",
                                left_m=20.0)["closures"] == 0


def test_the_precision_recall_curve_by_hand(tmp_path):
    gt = _run_folder(tmp_path)
    pr = loop_closure_quality(tmp_path / "templates.csv", gt, 1.0, 5.0, tmp_path / "closures.csv")["precision_recall"]
    # by confidence: 17 (3.0, right), 16 (2.0, wrong), 18 (0.5, wrong), then 19 (none, right)
    assert pr["curve"]["confidence"] == [3.0, 2.0, 0.5, None] and pr["unranked"] == 1
    assert pr["curve"]["precision"] == pytest.approx([1, 1 / 2, 1 / 3, 2 / 4])
    assert pr["curve"]["recall"] == pytest.approx([1 / 8, 1 / 8, 1 / 8, 2 / 8])
    assert pr["area"] == pytest.approx(1 / 8 * 1 + 1 / 8 * 2 / 4)  # recall gained x precision there
    assert pr["recall_at_precision"] == pytest.approx({"1.0": 1 / 8, "0.99": 1 / 8, "0.95": 1 / 8})


def test_the_cli_prints_closures_and_re_recognitions_and_draws_the_curve(tmp_path, capsys):
    _run_folder(tmp_path)
    write_tum(tmp_path / "trajectory.tum", np.array([[k, x, 0.0, 0.0] for k, x in enumerate(X)]))
    assert main(["evaluate", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    # the default 30 s gap: no frame of this 20-s run revisits a place (recall n/a)
    assert ("closures: precision 0.50, recall n/a at 1.0 m (2 of 4 correct); 4 re-recognitions of a "
            "place just passed (left after 5 m of travel)") in out
    assert not (tmp_path / "pr_curve.png").exists()  # no revisit, no curve
    # with revisits (a 5 s gap) the curve is drawn
    from neoslam_stream.evaluation import read_tum
    from neoslam_stream.evaluation.plots import plot_pr

    lc = loop_closure_quality(tmp_path / "templates.csv", read_tum(tmp_path / "groundtruth.tum"), 1.0, 5.0,
                              tmp_path / "closures.csv")
    plot_pr({"hand-made": lc}, tmp_path / "pr.png")
    assert (tmp_path / "pr.png").stat().st_size > 0


def test_without_ground_truth_the_odometry_travel_splits_the_matches(tmp_path):
    _run_folder(tmp_path)
    (tmp_path / "groundtruth.tum").unlink()
    # wheel odometry 3 % short, its heading off by 0.1 rad: its positions drift (1 m off after the
    # out-and-back), its travel is 3 % short: the same split (frame 13's 5 m are 4.85 m, 16's 6 m 5.82 m)
    c, s = math.cos(0.1), math.sin(0.1)
    write_tum(tmp_path / "odometry.tum", np.array([[k, 0.97 * x * c, 0.97 * x * s, 0.1] for k, x in enumerate(X)]))
    split = closures_by_odometry(tmp_path)
    assert split == {"closures": 4, "re_recognitions": 4, "left_m": 5.0, "travelled_from": "odometry.tum"}
    (tmp_path / "odometry.tum").unlink()
    assert closures_by_odometry(tmp_path) is None  # nothing says how far the robot went


def test_benches_judge_closures_as_neoslam_evaluate_does(tmp_path):
    from streams import _score_world, _world_truth

    gt = _run_folder(tmp_path)
    q = loop_closure_quality(tmp_path / "templates.csv", gt, 1.0, 5.0, tmp_path / "closures.csv")
    res = _score_world([(k, m) for k, (m, _c) in MATCHES.items()], _world_truth(gt[:, 1:4]))
    for key in ("closures", "correct", "precision", "re_recognitions", "left_m"):
        assert res[key] == q[key], key
    # the bench's revisits face the way they faced before (a forward camera): none on the way back
    assert (res["revisit_frames"], res["recall"]) == (0, 0.0)


def test_rpe_by_hand():
    # the estimate runs 10 % long along a straight line of 1-m steps: over 1 m it is 0.1 m off
    ref = np.column_stack([np.arange(12.0), np.zeros(12), np.zeros(12)])
    est = ref * [1.1, 1.0, 1.0]
    r = rpe(est, ref, 1.0)
    assert r["pairs"] == 11 and r["mean_m"] == pytest.approx(0.1) and r["max_m"] == pytest.approx(0.1)
    r5 = rpe(est, ref, 5.0)  # pairs (0, 5), (5, 10): 0.5 m each
    assert rpe_pairs(ref[:, :2], 5.0) == [(0, 5), (5, 10)]
    assert r5["pairs"] == 2 and r5["mean_m"] == pytest.approx(0.5) and r5["rot_mean_deg"] == pytest.approx(0.0)
    # a heading error at the start turns the whole estimate: the motion seen from each pose is
    # the same, so RPE is 0 where APE before alignment would grow with the distance
    th = 0.3
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    turned = np.column_stack([ref[:, :2] @ R.T, np.full(12, th)])
    assert rpe(turned, ref, 1.0)["max_m"] == pytest.approx(0.0, abs=1e-12)
    # a frame turned by 10 degrees in place: the heading error over the pairs around it
    bent = ref.copy()
    bent[6:, 2] = math.radians(10)
    assert rpe(bent, ref, 1.0)["rot_mean_deg"] == pytest.approx(10 / 11)
    assert rpe(ref[:1], ref[:1], 1.0)["mean_m"] is None  # one pose: no pair
