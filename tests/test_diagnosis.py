"""The diagnosis tools of a map's quality: D's runner-up, the oracle front end, closures.csv, closure
precision/recall at a stated radius, omega >= 1, and the paper's profile. Expected values are
worked by hand from the definitions (docs/evaluation.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from neoslam_stream.algorithms.oracle import OracleTemplates
from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig
from neoslam_stream.cli import main
from neoslam_stream.config import ConfigError, load_config
from neoslam_stream.nodes.recorder import RecorderNode
from neoslam_stream.nodes.run_rows import CLOSURES_HEADER
from neoslam_stream.nodes.topics import GROUNDTRUTH, VISUAL_TEMPLATE
from neoslam_stream.runtime.messages import Message


# ------------------------------------------------------------------ 1d. omega = 0 is refused
def test_exclude_recent_intervals_zero_is_refused_with_the_reason():
    with pytest.raises(ValidationError, match="exclude_recent_intervals must be >= 1"):
        SpatialViewConfig(exclude_recent_intervals=0)
    with pytest.raises(ConfigError, match="exclude_recent_intervals"):
        load_config("default", {"spatial_view": {"exclude_recent_intervals": 0}})
    assert SpatialViewConfig(exclude_recent_intervals=1).exclude_recent_intervals == 1


# ------------------------------------------------------------------ 1b. D's runner-up
def test_spatial_view_reports_the_runner_up():
    # theta_rho 0: every frame opens its own interval; omega 1: all but the current are candidates
    d = SpatialViewCells(theta_alpha=3, theta_rho=0, theta_sigma=4, exclude_recent_intervals=1, sdr_size=256)
    d.compute(np.array([0, 1, 2, 3, 4, 5], np.uint32))      # interval 0
    d.compute(np.array([10, 11, 12, 13, 14, 15], np.uint32))  # interval 1
    d.compute(np.array([0, 1, 2, 3, 20, 21], np.uint32))    # interval 2: overlap 4 with 0, not > 4
    r = d.compute(np.array([0, 1, 2, 3, 4, 30], np.uint32))
    # scores: interval 0 -> 5 (0..4), interval 1 -> 0, interval 2 -> 4 (0..3); 5 > theta_sigma 4
    assert r["is_loop_closure"] and (r["best_interval"], r["best_score"]) == (0, 5)
    assert (r["second_interval"], r["second_score"]) == (2, 4)
    assert r["confidence"] == 5 - 4  # the paper's rule: the score less theta_sigma
    # a single candidate has no runner-up
    d = SpatialViewCells(theta_alpha=3, theta_rho=0, theta_sigma=4, exclude_recent_intervals=1, sdr_size=256)
    d.compute(np.array([0, 1, 2, 3, 4, 5], np.uint32))
    r = d.compute(np.array([0, 1, 2, 3, 4, 5], np.uint32))
    assert r["is_loop_closure"] and (r["second_interval"], r["second_score"]) == (-1, 0)


# ------------------------------------------------------------------ 1a. the oracle
def test_oracle_templates_by_hand():
    o = OracleTemplates(radius_m=1.0, heading_tolerance_deg=45)
    seq = [((0.0, 0.0, 0.0), 0, False, 0.0, None),    # first place: template 0
           ((0.5, 0.0, 0.0), 0, False, 0.5, None),    # within 1 m of 0, still its first visit
           ((1.5, 0.0, 0.0), 1, False, 0.0, None),    # 1.5 m from 0: new template 1
           ((0.2, 0.0, 0.0), 0, True, 0.2, None),     # back at 0 (1 is 1.3 m away): a return
           ((0.2, 0.0, math.pi), 2, False, 0.0, None),  # same place facing the other way: new
           ((1.0, 0.0, 0.1), 1, True, 0.5, 1.0)]      # 0 at 1.0 m and 1 at 0.5 m: 1, runner-up 0
    for pose, tid, loop, score, second in seq:
        r = o.compute(pose)
        assert (r["id"], r["is_loop_closure"]) == (tid, loop), pose
        assert r["best_score"] == pytest.approx(score)
        assert (r["second_score"] is None) if second is None else r["second_score"] == pytest.approx(second)
    assert o.n_templates == 3
    with pytest.raises(ValueError, match="3 finite numbers"):
        o.compute((0.0, float("nan"), 0.0))


def _vt(frame, tid, loop=False, best=-1, score=0, second=None, interval=None):
    data = {"id": tid, "is_loop_closure": loop, "best_interval": best, "best_score": score,
            "relative_rad": 0.0}
    if second is not None:
        data["second_score"] = second
    if interval is not None:
        data["interval"] = interval
    return Message(VISUAL_TEMPLATE, frame, 0.1 * frame, data)


def _gt(frame, x, y):
    return Message(GROUNDTRUTH, frame, 0.1 * frame, {"pose": np.array([x, y, 0.0])})


def test_closures_csv_rows_by_hand(tmp_path):
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    # frames 0..5 along x, 1 m apart; D opens interval 0 at frame 0, 1 at 2, 2 at 4
    for f in range(6):
        rec.process(GROUNDTRUTH, _gt(f, float(f), 0.0))
        interval = f // 2
        if f == 5:  # matches interval 1 (opened at frame 2) with overlap 480, runner-up 470
            rec.process(VISUAL_TEMPLATE, _vt(f, 1, True, best=1, score=480, second=470, interval=interval))
        else:
            rec.process(VISUAL_TEMPLATE, _vt(f, interval, interval=interval))
    # written as it came, before the end of the run
    rows = (tmp_path / "closures.csv").read_text()
    assert rows == CLOSURES_HEADER + "5,0.500000,1,2,3.000,480,470,10,\n"
    # a closure's confidence is its last column
    rec.process(GROUNDTRUTH, _gt(6, 2.5, 0.0))
    vt = _vt(6, 1, True, best=1, score=470, second=400, interval=3)
    vt.data["confidence"] = 1.25
    rec.process(VISUAL_TEMPLATE, vt)
    assert (tmp_path / "closures.csv").read_text().endswith("6,0.600000,1,2,0.500,470,400,70,1.25\n")
    rec.flush()
    rec.close()


def _feed_line(rec, frames):
    """Frames along x (1 m apart), one template each, a return to template 0 from frame 3 on."""
    for f in frames:
        rec.process(GROUNDTRUTH, _gt(f, float(f % 3), 0.0))
        rec.process(VISUAL_TEMPLATE, _vt(f, f if f < 3 else 0, f >= 3, score=0.5 * f))


def test_a_restarted_recorder_neither_loses_nor_doubles_closure_rows(tmp_path):
    first = RecorderNode()
    first.run_dir, first.run_id = str(tmp_path), "run-1"
    _feed_line(first, range(6))  # then killed: no flush, no close
    second = RecorderNode()
    second.run_dir, second.run_id = str(tmp_path), "run-1"
    _feed_line(second, range(4, 8))  # upstream replays 4 and 5 before new frames
    second.flush()
    second.close()
    # closures at frames 3..7, each matched to frame 0 (template 0's first frame, which the second
    # recorder reads back from templates.csv), x = f % 3; the true position of frame 0 died with the
    # first recorder (no checkpoint), so the new rows' distances are unknown, not wrong
    want = "".join(f"{f},{0.1 * f:.6f},0,0,{f % 3:.3f},{0.5 * f:g},,,\n" for f in range(3, 6))
    want += "".join(f"{f},{0.1 * f:.6f},0,0,,{0.5 * f:g},,,\n" for f in range(6, 8))
    assert (tmp_path / "closures.csv").read_text() == CLOSURES_HEADER + want


def test_a_recorder_restored_from_a_checkpoint_keeps_the_places(tmp_path):
    first = RecorderNode()
    first.run_dir, first.run_id = str(tmp_path), "run-1"
    _feed_line(first, range(5))
    state = first.state_dict()  # the checkpoint, then killed
    second = RecorderNode()
    second.run_dir, second.run_id = str(tmp_path), "run-1"
    second.load_state_dict(state)
    _feed_line(second, range(5, 8))
    second.flush()
    second.close()
    want = "".join(f"{f},{0.1 * f:.6f},0,0,{f % 3:.3f},{0.5 * f:g},,,\n" for f in range(3, 8))
    assert (tmp_path / "closures.csv").read_text() == CLOSURES_HEADER + want


def test_closure_rows_without_ground_truth_have_an_empty_distance(tmp_path):
    rec = RecorderNode()
    rec.run_dir = str(tmp_path)
    rec.process(VISUAL_TEMPLATE, _vt(0, 0))
    rec.process(VISUAL_TEMPLATE, _vt(1, 1))
    rec.process(VISUAL_TEMPLATE, _vt(2, 0, True, score=0.25))  # a local view: a template, no interval
    rec.flush()
    rec.close()
    assert (tmp_path / "closures.csv").read_text() == CLOSURES_HEADER + "2,0.200000,0,0,,0.25,,,\n"


@pytest.mark.zenoh
def test_oracle_run_closes_only_within_its_radius_and_beats_odometry(tmp_path, capsys):
    from neoslam_stream.evaluation import read_tum

    r = 0.5  # the default: exp_delta_pc_threshold 2 x pc_cell_x_size 0.25 m
    # 0.9 m/s: a lap of the ring in ~26 s, so 700 frames hold two and a half laps
    assert main(["run", "--oracle-templates", "-p", "speed=0.9", "--max-frames", "700", "--no-live",
                 "--out", str(tmp_path)]) == 0
    gt = read_tum(tmp_path / "groundtruth.tum")
    tpl = np.loadtxt(tmp_path / "templates.csv", delimiter=",", skiprows=1, ndmin=2)
    assert len(tpl) == len(gt) == 700
    pos = {int(f): gt[i, 1:3] for i, f in enumerate(tpl[:, 0])}  # frame i has gt row i (one per frame)
    first: dict[int, int] = {}
    for f, tid in zip(tpl[:, 0].astype(int), tpl[:, 2].astype(int), strict=True):
        first.setdefault(tid, f)
    loops = tpl[tpl[:, 3] > 0]
    assert len(loops) > 100
    dist = [np.linalg.norm(pos[int(f)] - pos[first[int(t)]]) for f, t in loops[:, [0, 2]]]
    assert max(dist) <= r + 1e-6
    # closures.csv: one row per closure, the matched frame the template's first frame, same distance
    lines = (tmp_path / "closures.csv").read_text().splitlines()[1:]
    assert len(lines) == len(loops)
    for line, f, t, dd in zip(lines, loops[:, 0], loops[:, 2], dist, strict=True):
        cols = line.split(",")
        assert (int(cols[0]), int(cols[2]), int(cols[3])) == (int(f), int(t), first[int(t)])
        assert float(cols[4]) == pytest.approx(dd, abs=1e-3)
    out = capsys.readouterr().out
    assert "closures: precision 1.00" in out and f"at 1.0 m ({len(loops)} of {len(loops)} correct)" in out
    import json

    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert ev["trajectory_ape"]["mean_m"] <= ev["odometry_ape"]["mean_m"]
    assert ev["loop_closures"]["precision"] == 1.0 and ev["loop_closures"]["radius_m"] == 1.0
    # --radius states another radius; below r some closures are farther than it
    assert main(["evaluate", str(tmp_path), "--radius", "0.1"]) == 0
    out = capsys.readouterr().out
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    n_within = sum(d <= 0.1 for d in dist)
    assert ev["loop_closures"]["radius_m"] == 0.1 and ev["loop_closures"]["correct"] == n_within < len(loops)
    assert f"at 0.1 m ({n_within} of {len(loops)} correct)" in out


def test_oracle_needs_ground_truth_and_a_neoslam_pipeline(capsys):
    assert main(["run", "--oracle-templates", "--pipeline", "ratslam", "--max-frames", "5"]) == 2
    assert "--oracle-templates" in capsys.readouterr().err


# ------------------------------------------------------------------ 2. the paper's profile
def test_the_paper_profile_ships_with_the_papers_values(capsys):
    assert main(["config", "list"]) == 0
    assert "paper" in capsys.readouterr().out.split()
    assert main(["config", "show", "paper"]) == 0
    assert "theta_sigma: 470" in capsys.readouterr().out
    cfg = load_config("paper")
    sv = cfg.spatial_view
    # the paper's theta_alpha, theta_rho, theta_sigma and omega; raw features (no centring)
    assert (sv.theta_alpha, sv.theta_rho, sv.theta_sigma, sv.exclude_recent_intervals) == (384, 3, 470, 3)
    assert cfg.projector.centre_window == 0 and cfg.run.pipeline == "neoslam"
