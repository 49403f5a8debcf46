"""Evaluation: hand-made trajectory pairs with known answers, and real ground truth moved rigidly."""

import math
from pathlib import Path

import numpy as np
import pytest

from neoslam_stream.evaluation import (
    ape,
    associate,
    evaluate_run,
    paper_metric,
    read_tum,
    umeyama_se2,
    write_tum,
)

GT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "trajectories_gt"


def test_paper_metric_hand_made():
    ref = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    est = np.array([[5.0, 5.0], [6.0, 5.0], [7.0, 6.0]])  # offset (removed), then 1 m off at the end
    m = paper_metric(est, ref)
    assert m["mean_m"] == pytest.approx(1 / 3) and m["max_m"] == pytest.approx(1.0)


def test_ape_removes_rotation_and_translation_exactly():
    rng = np.random.default_rng(0)
    ref = rng.random((50, 2)) * 10
    th = 0.7
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    est = ref @ R.T + [3.0, -2.0]
    assert ape(est, ref)["max_m"] < 1e-9
    Rf, t = umeyama_se2(est, ref)
    np.testing.assert_allclose(Rf, R.T, atol=1e-9)


def test_ape_of_a_known_residual():
    ref = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    est = ref.copy()
    est[:, 0] *= 1.0  # identical except one point displaced symmetrically twice
    est[0] += [0.1, 0.0]
    est[3] -= [0.1, 0.0]
    res = ape(est, ref)
    # best alignment keeps the centroid; the rotation that fits best leaves a residual below 0.1
    assert 0 < res["max_m"] <= 0.1 + 1e-12


def test_association_by_nearest_stamp():
    ie, ig = associate(np.array([0.0, 1.04, 5.0]), np.array([0.0, 1.0, 2.0]), max_dt=0.1)
    assert ie.tolist() == [0, 1] and ig.tolist() == [0, 1]


@pytest.mark.skipif(not (GT / "fr2_desk_groundtruth.txt").exists(), reason="trajectories_gt absent")
def test_real_ground_truth_against_itself_moved(tmp_path):
    gt = read_tum(GT / "fr2_desk_groundtruth.txt")
    gt = gt[np.unique(np.round(gt[:, 0], 6), return_index=True)[1]]  # the file repeats some stamps
    th = 0.4
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    moved = gt.copy()
    moved[:, 1:3] = gt[:, 1:3] @ R.T + [2.0, 1.0]
    assert ape(moved[:, 1:3], gt[:, 1:3])["max_m"] < 1e-6
    # the paper's metric subtracts the first points only: the rotation stays, error = rotated path
    pm = paper_metric(moved[:, 1:3], gt[:, 1:3])
    d = gt[:, 1:3] - gt[0, 1:3]
    expected = np.linalg.norm(d @ R.T - d, axis=1)  # |R d - d| = 2 sin(th/2) |d|
    assert pm["mean_m"] == pytest.approx(expected.mean(), rel=1e-9)
    np.testing.assert_allclose(expected, 2 * math.sin(th / 2) * np.linalg.norm(d, axis=1), rtol=1e-9)
    # a run folder with it: evaluation.json and map.png
    write_tum(tmp_path / "groundtruth.tum", gt)
    write_tum(tmp_path / "trajectory.tum", moved)
    res = evaluate_run(tmp_path)
    assert res["trajectory_ape"]["max_m"] < 1e-5
    assert (tmp_path / "map.png").stat().st_size > 1000 and (tmp_path / "evaluation.json").exists()
