"""Loop closures decided from the run's own statistics (algorithms/calibration.py), in D and in
RatSLAM's local view: hand-worked statistics, the consistency of the evidence, and whole streams
with and without a revisit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.calibration import CalibrationConfig, PlatformConfig, RunCalibration
from neoslam_stream.algorithms.frontend import LocalViewFrontEnd
from neoslam_stream.algorithms.spatial_view import SpatialViewCells, SpatialViewConfig


def test_the_platform_gives_the_earliest_revisit():
    # a 30 m loop driven at up to twice 0.5 m/s takes 30 s
    assert PlatformConfig(speed_mps=0.5, shortest_loop_m=30.0).min_revisit_s() == pytest.approx(30.0)


def _cal(**over) -> RunCalibration:
    cfg = CalibrationConfig(enabled=True, **{"min_candidates": 5, **over})
    return RunCalibration(cfg, PlatformConfig(speed_mps=1.0, shortest_loop_m=10.0))


def test_assess_works_out_z_and_the_level_by_hand():
    cal = _cal(z_min=2.0, rho=0.5, neighbourhood_m=1.5)
    # candidates 1 s apart; the winner (index 5, score 20) and index 6 (1 s away: within 1.5 m at
    # 1 m/s) are the same place and left out of the statistics
    scores = np.array([10, 12, 10, 12, 10, 20, 19, 10, 12, 10], dtype=float)
    times = np.arange(10, dtype=float)
    a = cal.assess(scores, times, recent=26.0)
    rest = np.array([10, 12, 10, 12, 10, 12, 10], dtype=float)  # indices 4, 5, 6 (within 1.5 s) out
    mean, sd = rest.mean(), rest.std()
    assert a.best == 5 and a.score == 20
    assert a.mean == pytest.approx(mean) and a.sd == pytest.approx(sd, rel=1e-6)
    z = (20 - mean) / sd
    level = mean + 0.5 * (26 - mean)  # half way to the view a moment ago
    assert a.z == pytest.approx(z, rel=1e-6)
    assert a.confidence == pytest.approx(min(z - 2.0, (20 - level) / sd), rel=1e-6)
    assert a.second in (1, 3, 8) and a.second_score == 12  # the runner-up is another place


def test_too_few_candidates_give_no_verdict():
    cal = _cal(min_candidates=20)
    assert cal.assess(np.arange(10, dtype=float), np.arange(10, dtype=float) * 10, None) is None
    assert cal.report()["ready_from_frame"] == -1


def test_a_closure_needs_consistent_evidence_over_the_stretch_of_travel():
    cal = _cal(sequence_m=2.5)  # 1 m/s, frames 1 s apart: 2.5 s of travel, L = 3 frames before
    for t in range(6):
        cal.on_stamp(float(t))
    assert cal.frame_s == 1.0 and cal.sequence_frames == 3
    # references advancing with the queries, mean confidence 0.5 >= 0: a closure at the 4th frame
    decided = [cal.accept(t, 100 + t, c) for t, c in zip(range(10, 14), (1.0, -0.5, 1.0, 0.5), strict=True)]
    assert decided == [False, False, False, True]
    # the closure keeps the confidence it was decided on: the stretch's mean, (1 - 0.5 + 1 + 0.5) / 4
    assert cal.evidence == pytest.approx(0.5)
    # a jump of the reference by 40 frames is no consistent sequence: no evidence
    assert cal.accept(14, 160, 5.0) is False
    assert cal.evidence == -math.inf
    # a run of weak evidence (mean < 0) is refused even when consistent
    cal2 = _cal(sequence_m=2.5)
    for t in range(6):
        cal2.on_stamp(float(t))
    assert [cal2.accept(t, 50 + t, -0.1) for t in range(4)] == [False] * 4


def test_the_sequence_length_follows_the_measured_frame_rate():
    cal = _cal(sequence_m=0.6)
    for t in range(30):
        cal.on_stamp(t * 0.1)  # 10 Hz at 1 m/s: 0.1 m per frame, 6 frames for 0.6 m
    assert cal.sequence_frames == 6
    slow = _cal(sequence_m=0.6)
    for t in range(30):
        slow.on_stamp(t * 5.0)  # 5 m per frame: one frame before is the least
    assert slow.sequence_frames == 1


# ------------------------------------------------------------------------------ whole streams
#: winner cells as the Temporal Memory gives them with NeoSLAM's parameters: cell 0 of 512 of the
#: 2048 columns, so two unrelated frames share ~128 cells (as real ones do), not ~4
COLUMNS, CELLS = 2048, 32


def _places(n_places: int, rng: np.random.Generator) -> list[np.ndarray]:
    return [rng.choice(COLUMNS, 512, replace=False) for _ in range(n_places)]


def _noisy(cols: np.ndarray, rng: np.random.Generator, keep: float) -> np.ndarray:
    """A visit of a place: a fraction ``keep`` of its columns, the rest random, as winner cells."""
    k = int(round(keep * cols.size))
    kept = rng.choice(cols, k, replace=False)
    others = np.setdiff1d(np.arange(COLUMNS), kept)
    return np.sort(np.concatenate([kept, rng.choice(others, cols.size - k, replace=False)])) * CELLS


def _d(**platform) -> SpatialViewCells:
    return SpatialViewCells(SpatialViewConfig(calibration={"enabled": True}),
                            platform=PlatformConfig(**{"speed_mps": 1.0, "shortest_loop_m": 20.0, **platform}))


def test_d_closes_the_loop_of_a_second_traversal_and_nothing_else():
    """Two traversals of 80 places, one frame per place and second (1 m apart at 1 m/s): the second
    traversal shares 60 % of each place's cells with the first. The revisits are found, onto the
    right place, with no absolute threshold; the first traversal closes nothing."""
    rng = np.random.default_rng(1)
    places = _places(80, rng)
    d = _d()
    first = [d.compute(_noisy(p, rng, 0.9), stamp=float(i)) for i, p in enumerate(places)]
    second = [d.compute(_noisy(p, rng, 0.6), stamp=80.0 + i) for i, p in enumerate(places)]
    assert not any(r["is_loop_closure"] for r in first)
    closures = [(i, r) for i, r in enumerate(second) if r["is_loop_closure"]]
    assert len(closures) >= 60  # most revisits found
    # each closure carries the confidence it was decided on (>= 0: accepted); other frames none
    assert all(r["confidence"] >= 0 for _, r in closures)
    assert not any("confidence" in r for r in first)
    starts = d.interval_start
    assert all(starts[r["best_interval"]] == i for i, r in closures)  # each onto its own place
    rep = d.calibration.report()
    assert rep["revisit_seen"] and rep["closures"] == len(closures) and rep["ready_from_frame"] >= 0
    assert rep["score_needed"] > rep["unrelated_mean"]


def test_a_place_visited_twice_before_closes_whichever_visit_wins():
    """A third traversal whose frames are each a copy of the first or of the second visit of the
    place, alternately: the winner flips between two earlier intervals from frame to frame. They
    are one place (the second visit closed onto the first's template), so the evidence is
    consistent and the third traversal closes as well as the second, onto the first visit's place."""
    rng = np.random.default_rng(5)
    places = _places(80, rng)
    d = _d()
    visits = [[_noisy(p, rng, 0.9) for p in places] for _ in range(2)]
    for i, v in enumerate(visits[0] + visits[1]):
        d.compute(v, stamp=float(i))
    second_closed = sum(d.interval_template[80 + i] == d.interval_template[i] for i in range(80))
    assert second_closed >= 60
    third = [d.compute(visits[i % 2][i], stamp=160.0 + i) for i in range(80)]
    closed = [i for i, r in enumerate(third) if r["is_loop_closure"]]
    assert len(closed) >= second_closed - 5
    won = [d.interval_start[third[i]["best_interval"]] for i in closed]
    assert sum(w >= 80 for w in won) >= 20  # the second visit's intervals do win half the time
    first_frame = {d.interval_template[i]: i for i in range(79, -1, -1)}
    assert all(first_frame[third[i]["id"]] == i for i in closed)


def test_templates_made_while_a_revisit_was_confirmed_become_that_place():
    """At 0.2 m/s and one frame a second the evidence needs L = 3 frames (0.6 m), so the second
    traversal's first frames of the revisit are refused and make new templates. Once the evidence
    confirms the revisit, every template made in the L frames before the closure is the place its
    frame matched: its interval takes the first traversal's template of that place. The state
    carries the templates still on probation through a checkpoint."""
    rng = np.random.default_rng(6)
    places = _places(80, rng)
    frames = [_noisy(p, rng, 0.9) for p in places] + [_noisy(p, rng, 0.6) for p in places]
    d = _d(speed_mps=0.2)
    out = [d.compute(f, stamp=float(i)) for i, f in enumerate(frames)]
    L = d.calibration.sequence_frames
    assert L == 3
    made = [i for i in range(80, 160) if out[i]["id"] >= 80 and not out[i]["is_loop_closure"]]
    closed = {i for i in range(80, 160) if out[i]["is_loop_closure"]}
    confirmed = [i for i in made if any(i + j in closed for j in range(1, L + 1))]
    assert 80 in confirmed  # the revisit's first frame, refused for want of evidence
    for i in confirmed:  # each place's intervals: the first traversal's i - 80, the second's i
        assert d.interval_template[i] == d.interval_template[i - 80], i
    unconfirmed = [i for i in made if i not in confirmed]
    assert all(d.interval_template[i] == out[i]["id"] for i in unconfirmed)
    assert d.calibration.report()["templates_merged"] == len(confirmed)
    # the probation list through a checkpoint: resumed on the frame after the first refusal
    first = _d(speed_mps=0.2)
    for i, f in enumerate(frames[:81]):
        first.compute(f, stamp=float(i))
    assert first.calibration.pending
    resumed = _d(speed_mps=0.2)
    resumed.load_state_dict(first.state_dict())
    assert [resumed.compute(f, stamp=float(81 + i)) for i, f in enumerate(frames[81:])] == out[81:]
    assert resumed.interval_template == d.interval_template


def test_a_run_without_revisit_closes_nothing_and_says_so():
    rng = np.random.default_rng(2)
    d = _d()
    out = [d.compute(_noisy(p, rng, 0.9), stamp=float(i)) for i, p in enumerate(_places(200, rng))]
    assert not any(r["is_loop_closure"] for r in out)
    rep = d.calibration.report()
    assert rep["revisit_seen"] is False and rep["closures"] == 0 and rep["ready_from_frame"] >= 0


def test_d_finds_no_loop_before_a_shortest_loop_has_passed():
    """A place seen again 10 s later, when the shortest loop takes 60 s at twice the speed: no
    candidate yet (the robot cannot have come back)."""
    rng = np.random.default_rng(3)
    places = _places(40, rng)
    d = _d(shortest_loop_m=120.0)
    out = [d.compute(_noisy(places[i % 10], rng, 0.8), stamp=float(i)) for i in range(40)]
    assert not any(r["is_loop_closure"] for r in out)


@pytest.mark.parametrize("cut", [70, 90])
def test_the_calibrated_state_survives_a_checkpoint(cut):
    """Frames 0.25 s apart, so the measured interval differs from the one a fresh run assumes
    (1 s) and the stretch of evidence is 3 frames, not 1: a restored run must measure it from the
    saved intervals before it restores the evidence, or it keeps only one frame of it. Cut 90
    falls among the second traversal's closures."""
    rng = np.random.default_rng(4)
    places = _places(60, rng)
    frames = [_noisy(p, rng, 0.9) for p in places] + [_noisy(p, rng, 0.6) for p in places]
    whole = _d()
    ref = [whole.compute(f, stamp=0.25 * i) for i, f in enumerate(frames)]
    assert whole.calibration.sequence_frames == 3 and any(r["is_loop_closure"] for r in ref[cut:])
    first = _d()
    for i, f in enumerate(frames[:cut]):
        first.compute(f, stamp=0.25 * i)
    resumed = _d()
    resumed.load_state_dict(first.state_dict())
    rest = [resumed.compute(f, stamp=0.25 * (cut + i)) for i, f in enumerate(frames[cut:])]
    assert rest == ref[cut:]


def test_revisits_stay_out_of_the_index_and_later_drives_still_close():
    """``index_revisits: false``: four drives of 80 places. An interval enters the index when it
    closes, unless every frame of it closed onto an older place: after the drives the index holds
    exactly the other intervals, so it grows with new places, not with frames. The third and fourth
    drives, which can only match what the index kept, close as well as the second, each onto its
    own place's template; a checkpoint taken mid-drive resumes with the same decisions."""
    rng = np.random.default_rng(7)
    places = _places(80, rng)
    frames = [_noisy(p, rng, 0.9) for p in places] + [_noisy(p, rng, 0.6) for _ in range(3) for p in places]

    def make() -> SpatialViewCells:
        return SpatialViewCells(SpatialViewConfig(calibration={"enabled": True}, index_revisits=False),
                                platform=PlatformConfig(speed_mps=1.0, shortest_loop_m=20.0))

    d = make()
    out = [d.compute(f, stamp=float(i)) for i, f in enumerate(frames)]
    closed = [r["is_loop_closure"] for r in out]
    complete = range(d.n_intervals - 1)  # the newest interval is still open
    kept = [k for k in complete
            if not all(closed[d.interval_start[k]:d.interval_end[k] + 1])]
    assert d.indexed.tolist() == kept and len(kept) < 0.5 * d.n_intervals
    first_frame = {}
    for k in range(d.n_intervals):
        first_frame.setdefault(d.interval_template[k], d.interval_start[k])
    drives = [[i for i in range(80) if closed[80 * n + i]] for n in range(4)]
    assert not drives[0] and len(drives[1]) >= 60
    for n in (2, 3):
        assert len(drives[n]) >= len(drives[1]) - 5
        assert all(first_frame[out[80 * n + i]["id"]] == i for i in drives[n])
    half = make()
    for i, f in enumerate(frames[:200]):
        half.compute(f, stamp=float(i))
    resumed = make()
    resumed.load_state_dict(half.state_dict())
    assert [resumed.compute(f, stamp=float(200 + i)) for i, f in enumerate(frames[200:])] == out[200:]
    with pytest.raises(ValueError, match="index_revisits"):
        SpatialViewConfig(index_revisits=False)


def _corridor(seed: int, speed_mps: float):
    """RatSLAM's calibrated local view and a corridor of random texture, 70 frames long:
    frame(i, noise) is the i-th view (each overlaps the previous one, as a camera's do)."""
    rng = np.random.default_rng(seed)
    strip = rng.integers(0, 256, (24, 64 + 16 * 70), dtype=np.uint8)
    lv = LocalViewFrontEnd({"template_x_size": 16, "template_y_size": 6, "vt_shift_match": 1,
                            "calibration": {"enabled": True}},
                           PlatformConfig(speed_mps=speed_mps, shortest_loop_m=20.0))

    def frame(i: int, noise: float) -> np.ndarray:
        view = strip[:, 16 * i:16 * i + 64].astype(float)
        return np.clip(view + rng.normal(0, noise, view.shape), 0, 255).astype(np.uint8)

    return lv, frame


def test_the_local_view_recognises_old_templates_only_when_they_stand_out():
    """RatSLAM's local view with the same decision: a corridor of random texture driven twice at
    one frame per second (each frame overlaps the previous one, as a camera's do); the second
    drive, noisier, is recognised onto the first drive's templates, and the first closes nothing."""
    lv, frame = _corridor(5, speed_mps=1.0)
    first = [lv.template(frame(i, 5), stamp=float(i)) for i in range(70)]
    ids = [r["id"] for r in first]
    assert not any(r["is_loop_closure"] for r in first)
    second = [lv.template(frame(i, 25), stamp=70.0 + i) for i in range(70)]
    closures = [(i, r["id"]) for i, r in enumerate(second) if r["is_loop_closure"]]
    assert len(closures) >= 35
    assert all(tid == ids[i] for i, tid in closures)
    rep = lv.calibration.report()
    assert rep["revisit_seen"] and math.isfinite(rep["unrelated_sd"])


def test_the_local_view_keeps_one_template_per_place_over_repeated_drives():
    """The corridor driven three times at 0.2 m/s (L = 3 frames of evidence): the second drive's
    first frames of the revisit make templates before the evidence confirms it; they then become
    the place their frames matched, a first-drive template (+-1 frame), and every closure of the
    third drive reports a first-drive template, never one of those duplicates."""
    lv, frame = _corridor(7, speed_mps=0.2)
    first = [lv.template(frame(i, 5), stamp=float(i))["id"] for i in range(70)]
    n_first = len(lv.cells.templates)
    second = [lv.template(frame(i, 25), stamp=70.0 + i) for i in range(70)]
    L = lv.calibration.sequence_frames
    assert L == 3
    closed = {i for i, r in enumerate(second) if r["is_loop_closure"]}
    dups = [(i, r["id"]) for i, r in enumerate(second)
            if r["id"] >= n_first and any(i + j in closed for j in range(1, L + 1))]
    assert dups  # the revisit's first frames, refused for want of evidence
    for i, tid in dups:
        assert lv.place[tid] in first[max(0, i - 1):i + 2], (i, tid)
    third = [lv.template(frame(i, 25), stamp=140.0 + i) for i in range(70)]
    closures = [r["id"] for r in third if r["is_loop_closure"]]
    assert len(closures) >= 35 and all(tid < n_first for tid in closures)


def test_the_run_summary_says_what_was_calibrated_and_whether_a_revisit_was_seen():
    from neoslam_stream.cli.report import calibration_line

    rng = np.random.default_rng(6)
    d = _d()
    for i, p in enumerate(_places(120, rng)):
        d.compute(_noisy(p, rng, 0.9), stamp=float(i))
    rep = d.calibration.report()
    line = calibration_line("D", rep)
    assert f"calibrated from frame {rep['ready_from_frame']}" in line and "no revisit seen in this run" in line
    assert str(rep["score_needed"]) in line
    early = _d()
    early.compute(_noisy(_places(1, rng)[0], rng, 0.9), stamp=0.0)
    assert "not calibrated" in calibration_line("D", early.calibration.report())
