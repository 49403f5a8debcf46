"""studies/revisit_levels.py: the replayed decision's level and B's voted re-ranking, by hand."""

import math
from types import SimpleNamespace

import numpy as np
from revisit_levels import _voted, _with_frames, confidence_rule, heading_gated, visual_heading

from neoslam_stream.algorithms.calibration import CalibrationConfig, PlatformConfig, RunCalibration


def test_the_level_comes_from_the_view_a_moment_ago_or_the_lagged_one():
    r = {"z": 5.0, "s": 10.0, "mean": 4.0, "sd": 1.2, "recent": 11.0, "lags": {2.0: 6.0}}
    # a moment ago: level 4 + 0.9 (11 - 4) = 10.3, (10 - 10.3) / 1.2 = -0.25 below z's 1.5
    assert math.isclose(confidence_rule(3.5, 0.9, 0.0)(r), -0.25)
    # 2 m ago: level 4 + 0.9 (6 - 4) = 5.8, (10 - 5.8) / 1.2 = 3.5, so z - z_min = 1.5 decides
    assert math.isclose(confidence_rule(3.5, 0.9, 2.0)(r), 1.5)
    # no view that far back: the level is the unrelated places' mean, z decides
    assert math.isclose(confidence_rule(3.5, 0.9, 4.0)(r), 1.5)
    # a recent view below the mean raises nothing: (10 - 4) / 1.2 = 5 against z's 0.5
    assert math.isclose(confidence_rule(4.5, 0.9, 0.0)({**r, "recent": 3.0}), 0.5)


def test_the_vote_standardises_each_score_over_the_shortlist():
    coarse = np.array([[4.0, 3.0, 2.0, 1.0]])
    allowed = np.ones((1, 4), bool)
    fine1 = np.array([[0.0, 1.0, 2.0, 100.0]])  # over the 3: mean 1, sd sqrt(2/3)
    fine2 = np.array([[0.0, 0.0, 3.0, 100.0]])  # mean 1, sd sqrt(2)
    out = _voted(coarse, (fine1, fine2), allowed, 3)
    a, b = math.sqrt(1.5), 1 / math.sqrt(2)
    assert np.allclose(out[0, :3], [-a - b, -b, a + 2 * b])
    assert out[0, 3] == -np.inf  # outside the shortlist, whatever its scores
    allowed[0, 2] = False  # not allowed: the shortlist takes the next by coarse
    out = _voted(coarse, (fine1, fine2), allowed, 3)
    assert out[0, 2] == -np.inf and int(np.argmax(out[0])) == 3


def test_a_longer_stretch_only_for_the_replay():
    cal = RunCalibration(CalibrationConfig(enabled=True), PlatformConfig(speed_mps=1.4))
    assert cal.sequence_frames == 1  # 0.6 m at 1.4 m a frame
    longer = _with_frames(cal, 4)
    assert longer.sequence_frames == 4 and longer.config is cal.config
    assert RunCalibration(CalibrationConfig(enabled=True), PlatformConfig(speed_mps=1.4)).sequence_frames == 1


def test_the_heading_gate_refuses_a_winner_seen_facing_the_other_way():
    # frames 0-3 facing east, north, east and west (headings in the truth's third column)
    gt = np.array([[0, 0, 0.0], [0, 0, math.pi / 2], [0, 0, 2 * math.pi - 0.1], [0, 0, math.pi]])
    rows = {t: {"frame": t, "matched": 0} for t in (1, 2, 3)}
    gated = heading_gated(lambda r: 1.0, gt[:, 2])
    assert gated(rows[2]) == 1.0  # 2 pi - 0.1 from 0: 0.1 rad the other way round, the same facing
    assert gated(rows[3]) == -math.inf  # half a turn
    assert gated(rows[1]) == -math.inf  # exactly a quarter turn is not less than one


def test_the_visual_heading_integrates_the_turn_the_images_show():
    from neoslam_stream.config import load_config

    rng = np.random.default_rng(3)
    base = rng.integers(0, 255, (120, 160)).astype(np.float64)
    base = (base + np.roll(base, 1, 1) + np.roll(base, 2, 1)) / 3  # some texture across columns
    frames = [np.roll(base, 4 * i, axis=1) for i in range(3)]  # turning 4 columns a frame
    cfg = load_config("default")
    rec = {"stream": SimpleNamespace(pixels=lambda: iter(frames), stamps=np.array([0.0, 0.1, 0.2])), "config": cfg}
    heading = visual_heading(rec)
    focal = 160 / 2 / math.tan(math.radians(cfg.visual_odometry.camera_fov_deg) / 2)
    turn = math.atan2(4, focal)  # the pinhole angle of a 4-column shift at the image's centre
    assert heading[0] == 0.0
    assert math.isclose(abs(heading[1]), turn, rel_tol=0.05)
    assert math.isclose(heading[2], 2 * heading[1], rel_tol=0.05)
