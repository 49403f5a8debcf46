"""Evaluation: hand-made trajectory pairs with known answers, and real ground truth moved rigidly."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from neoslam_stream.cli import main
from neoslam_stream.evaluation import (
    ape,
    associate,
    evaluate_run,
    loop_closure_quality,
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
    # a square and the same square 10 % larger about its centre: by symmetry the best rigid fit is
    # the identity, leaving every corner 0.1 * sqrt(2) m off
    ref = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    res = ape(ref * 1.1 + [4.0, 2.0], ref)
    for k in ("mean_m", "rmse_m", "max_m"):
        assert res[k] == pytest.approx(0.1 * math.sqrt(2), abs=1e-12)


def test_loop_closure_precision_and_recall_hand_made(tmp_path):
    # 1 Hz along x = t mod 50: from t = 50 on, every frame revisits the place of 50 s before
    t = np.arange(100.0)
    gt = np.column_stack([t, t % 50, np.zeros(100), np.zeros(100)])
    rows = []
    for k in range(100):
        tid, loop = (k, 0) if k < 50 else (100 + k, 0)
        if k == 60:
            tid, loop = 10, 1  # template made at x = 10, robot at x = 10: correct
        if k == 70:
            tid, loop = 40, 1  # made at x = 40, robot at x = 20: false
        if k == 80:
            tid, loop = 30, 1  # made at x = 30, robot at x = 30: correct
        rows.append(f"{k},{t[k]:.6f},{tid},{loop},-1,0")
    rows.append("100,500.0,7,1,-1,0")  # no ground truth near t = 500 s: left out
    (tmp_path / "templates.csv").write_text("frame,stamp,template_id,is_loop_closure,best_interval,best_score\n"
                                            + "\n".join(rows) + "\n")
    q = loop_closure_quality(tmp_path / "templates.csv", gt, radius=1.0)
    assert (q["closures"], q["correct"], q["revisit_frames"]) == (3, 2, 50)
    assert q["precision"] == pytest.approx(2 / 3) and q["recall"] == pytest.approx(2 / 50)
    # a radius of 25 m accepts the false one too (left after 5 m still: the default, 5 radii, is
    # 125 m); with a 60 s gap nothing counts as a revisit
    assert loop_closure_quality(tmp_path / "templates.csv", gt, radius=25.0, left_m=5.0)["correct"] == 3
    assert loop_closure_quality(tmp_path / "templates.csv", gt, min_gap_s=60.0)["recall"] is None


def test_evaluate_run_folder_and_cli(tmp_path, capsys):
    t = np.arange(20) * 0.5
    gt = np.column_stack([t, t, np.zeros(20), np.zeros(20)])  # 1 m/s along x
    write_tum(tmp_path / "groundtruth.tum", gt)
    est = gt.copy()
    est[:, 1:3] += [3.0, -1.0]  # the estimate in its own frame: a pure shift
    write_tum(tmp_path / "trajectory.tum", est)
    odo = gt.copy()
    odo[:, 2] = 0.1 * np.arange(20)  # odometry drifting sideways 0.1 m per sample
    write_tum(tmp_path / "odometry.tum", odo)
    nodes = [{"id": i, "x": 3.0 + i, "y": -1.0, "theta": 0.0, "stamp": float(i)} for i in range(5)]
    nodes[4]["y"] = 0.0  # the last node 1 m off
    (tmp_path / "map.json").write_text(json.dumps({"nodes": nodes,
                                                   "links": [{"from": i, "to": i + 1} for i in range(4)]}))
    res = evaluate_run(tmp_path)
    assert res["trajectory_ape"]["max_m"] < 1e-6 and res["trajectory_paper"]["max_m"] < 1e-6
    assert res["map_nodes"] == 5
    assert res["map_paper"]["mean_m"] == pytest.approx(1 / 5, abs=1e-6)
    assert res["map_paper"]["max_m"] == pytest.approx(1.0, abs=1e-6)
    assert res["odometry_paper"]["max_m"] == pytest.approx(1.9, abs=1e-6)
    assert json.loads((tmp_path / "evaluation.json").read_text()) == res
    # the command recomputes the same from the files; without ground truth it says so
    (tmp_path / "evaluation.json").unlink()
    assert main(["evaluate", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "evaluation.json").read_text()) == res
    (tmp_path / "groundtruth.tum").rename(tmp_path / "gt_elsewhere.tum")
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "no ground truth" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path), "--gt", str(tmp_path / "gt_elsewhere.tum")]) == 0


@pytest.mark.skipif(not (GT / "KITTI_00_gt.txt").exists(), reason="trajectories_gt absent")
def test_kitti_ground_truth_shifted_gives_the_shift_before_and_zero_after_alignment():
    poses = np.loadtxt(GT / "KITTI_00_gt.txt").reshape(-1, 3, 4)
    xy = poses[:, [0, 2], 3]  # camera frame: x right, z forward -> the ground plane
    assert np.ptp(xy[:, 0]) > 400  # a city-block drive, not a toy
    moved = xy + [30.0, -40.0]
    raw = np.linalg.norm(moved - xy, axis=1)
    np.testing.assert_allclose(raw, 50.0)  # the known offset before alignment
    assert ape(moved, xy)["max_m"] < 1e-6
    assert paper_metric(moved, xy)["max_m"] < 1e-9  # the first point's subtraction removes a shift
    th = -1.2
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    assert ape(xy @ R.T + [5.0, 5.0], xy)["max_m"] < 1e-6


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


def test_online_floor_is_odometry_until_the_first_return_then_exact():
    from neoslam_stream.evaluation import ape, online_floor

    # out and back along x: x = 0..9, then 9..0, one frame per second; odometry doubles every
    # distance and reports its poses in its own frame: rotated by 90 degrees and shifted
    t = np.arange(20.0)
    x = np.r_[np.arange(10.0), np.arange(9.0, -1.0, -1.0)]
    gt = np.c_[t, x, np.zeros(20), np.zeros(20)]
    odo = np.c_[t, np.full(20, 5.0), 2 * x - 3.0, np.full(20, np.pi / 2)]
    r = online_floor(gt, odo, radius=0.5, min_gap_s=5.0)
    # frame 12 (x = 7) is the first within 0.5 m of a frame at least 5 s older (frame 7); frames 10
    # and 11 (x = 9, 8) only have their own positions 1-3 s back
    assert (r["first_return_frame"], r["first_return_s"], r["frames_before_first_return"]) == (12, 12.0, 0.6)
    # the floor trajectory: odometry (2x from the true start, after the rigid start alignment)
    # before frame 12, the truth from there on
    est = np.c_[np.where(np.arange(20) < 12, np.r_[2 * np.arange(10.0), 18.0, 16.0, np.zeros(8)], x), np.zeros(20)]
    assert r["ape_mean_m"] == pytest.approx(ape(est, gt[:, 1:3])["mean_m"])
    # exact odometry: no floor at all; no return within the run: the whole run is dead reckoning
    assert online_floor(gt, gt, radius=0.5, min_gap_s=5.0)["ape_mean_m"] == pytest.approx(0.0, abs=1e-12)
    never = online_floor(gt, odo, radius=0.5, min_gap_s=50.0)
    assert never["first_return_frame"] == 20 and never["first_return_s"] is None


def _epoch_run(tmp_path: Path) -> tuple[Path, Path, float]:
    """A run folder whose stamps are epoch seconds (a 2011 bag) and a ground truth of the same path
    from 0 s, moved rigidly; returns the folder, the ground-truth file and the clocks' difference."""
    start = 1322463452.25
    t = np.arange(40) * 0.25
    xy = np.column_stack([np.cos(t), np.sin(2 * t)])
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.tum", np.column_stack([start + t, xy, np.zeros(40)]))
    th = 0.5
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    gt = tmp_path / "gt.tum"
    write_tum(gt, np.column_stack([t, xy @ R.T + [4.0, 1.0], np.zeros(40)]))
    return run, gt, start


def test_evaluate_names_both_time_ranges_when_the_stamps_do_not_overlap(tmp_path, capsys):
    run, gt, start = _epoch_run(tmp_path)
    assert main(["evaluate", str(run), "--gt", str(gt)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"{start:.3f} .. {start + 39 * 0.25:.3f} s" in err  # the run's range
    assert f"0.000 .. {39 * 0.25:.3f} s" in err  # the ground truth's
    assert "--gt-offset SECONDS" in err and "--gt-align-start" in err
    assert f"--gt-offset {start:.3f}" in err  # the difference of the first stamps, offered
    assert not (run / "evaluation.json").exists()


def test_gt_offset_and_align_start_shift_the_ground_truth(tmp_path, capsys):
    run, gt, start = _epoch_run(tmp_path)
    by_offset = evaluate_run(run, gt, plot=False, gt_offset=start)
    assert by_offset["ground_truth_offset_s"] == start
    assert by_offset["trajectory_ape"]["max_m"] < 1e-5  # the same path, moved rigidly: every pose paired
    aligned = evaluate_run(run, gt, plot=False, gt_align_start=True)
    assert aligned["ground_truth_offset_s"] == pytest.approx(start, abs=1e-6)
    assert aligned["trajectory_ape"]["max_m"] < 1e-5
    # an offset that still leaves the clocks apart is the same clear error, naming the shift
    from neoslam_stream.evaluation import StampMismatch

    with pytest.raises(StampMismatch, match="shifted by 100.000 s"):
        evaluate_run(run, gt, plot=False, gt_offset=100.0)
    assert main(["evaluate", str(run), "--gt", str(gt), "--gt-align-start"]) == 0
    assert "shifted by" in capsys.readouterr().out
    # the two ways exclude each other
    with pytest.raises(SystemExit):
        main(["evaluate", str(run), "--gt", str(gt), "--gt-align-start", "--gt-offset", "3"])


def test_evaluate_says_what_each_metric_measures(capsys):
    from neoslam_stream.cli import print_evaluation
    from neoslam_stream.evaluation import METRICS

    ev = {"trajectory_ape": {"mean_m": 0.159, "rmse_m": 0.2, "max_m": 0.41},
          "odometry_ape": {"mean_m": 5.09, "rmse_m": 6.0, "max_m": 13.0},
          "map_paper": {"mean_m": 7.48, "max_m": 12.5}, "map_nodes": 154}
    print_evaluation(ev)
    lines = capsys.readouterr().out.splitlines()
    ape_line = next(line for line in lines if "0.159 m" in line)
    paper_line = next(line for line in lines if "7.480 m" in line)
    assert "SE(2)-aligned" in ape_line and "paper metric" in paper_line and "154" in paper_line
    # each figure is followed by the line that says what it measures and whether to quote it
    assert lines[lines.index(ape_line) + 1].strip() == METRICS["ape"]
    assert lines[lines.index(paper_line) + 1].strip() == METRICS["paper"]
    assert "NeoSLAM" in METRICS["paper"] and "no rotation" in METRICS["paper"]
    assert "quote" in METRICS["ape"] and "quote" in METRICS["paper"]
    # docs/evaluation.md explains both and says which to quote
    doc = (Path(__file__).resolve().parents[1] / "docs" / "evaluation.md").read_text()
    assert "Which figure to quote" in doc
