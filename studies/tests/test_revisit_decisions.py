"""studies/revisit_decisions.py: where a revisiting frame's decision stopped, by the decision's steps."""

from types import SimpleNamespace

import numpy as np
from revisit_decisions import STEPS, recorded, step_of

Z_MIN = 3.5


def _row(z, confidence, closed, ref=10):
    return {"ref": ref, "confidence": confidence, "closed": closed, "z": z}


def test_each_step_by_hand():
    assert step_of(None, False, Z_MIN) == "no assessment"
    assert step_of(_row(None, float("-inf"), False, -1), False, Z_MIN) == "no assessment"
    assert step_of(_row(6.0, 1.0, True), True, Z_MIN) == "closed, right"
    assert step_of(_row(6.0, 1.0, True), False, Z_MIN) == "closed, wrong"
    assert step_of(_row(6.0, 1.0, False), False, Z_MIN) == "winner elsewhere"
    # confidence = min(z - z_min, (s - level) / sd): z 3.0 fails z_min whatever the level
    assert step_of(_row(3.0, -0.5, False), True, Z_MIN) == "z below z_min"
    # z 5 passes (z - z_min = 1.5), so a negative confidence is the level's
    assert step_of(_row(5.0, -0.2, False), True, Z_MIN) == "below the recent view's level"
    # both passed on this frame, yet no closure: the stretch's evidence refused it
    assert step_of(_row(5.0, 0.4, False), True, Z_MIN) == "stretch refused"
    assert len(set(STEPS)) == 7


def test_recorded_passes_every_verdict_through_and_keeps_it_by_frame():
    calls = []

    class Calibration:
        def assess(self, scores, times, recent, best=None):
            calls.append("assess")
            return SimpleNamespace(z=float(scores.max() if best is None else scores[best]))

        def accept(self, t, ref, confidence):
            calls.append("accept")
            return confidence >= 0

    fe = SimpleNamespace(spatial_view=SimpleNamespace(calibration=Calibration()))
    rows = recorded(fe)
    cal = fe.spatial_view.calibration
    assert cal.assess(np.array([1.0, 7.0]), np.array([0.0, 1.0]), None).z == 7.0
    assert cal.assess(np.array([1.0, 7.0]), np.array([0.0, 1.0]), None, 0).z == 1.0  # a re-ranked winner
    assert cal.accept(4, 2, 0.5) is True
    assert cal.accept(5, -1, -1.0) is False  # no assessment on this frame
    assert calls == ["assess", "assess", "accept", "accept"]
    # the verdict keeps the frame's latest assessment (the re-ranked winner's z)
    assert rows == {4: {"ref": 2, "confidence": 0.5, "closed": True, "z": 1.0},
                    5: {"ref": -1, "confidence": -1.0, "closed": False, "z": None}}


def test_recorded_wraps_the_real_calibration_as_spatial_view_calls_it():
    """D calls assess with the re-ranked winner (spatial_view._calibrated): the wrapper must take
    every argument the real RunCalibration.assess takes and pass it on."""
    from neoslam_stream.algorithms.calibration import CalibrationConfig, PlatformConfig, RunCalibration

    cal = RunCalibration(CalibrationConfig(enabled=True, min_candidates=3), PlatformConfig(speed_mps=1.0))
    fe = SimpleNamespace(spatial_view=SimpleNamespace(calibration=cal))
    rows = recorded(fe)
    scores = np.array([0.1, 0.2, 0.15, 0.9, 0.12, 0.18, 0.11])
    times = np.arange(7) * 10.0  # 10 s apart: every other candidate lies outside the neighbourhood
    a = cal.assess(scores, times, None, 1)  # the winner chosen by a re-ranking, not the highest score
    rest = np.delete(scores, 1)
    assert a.best == 1 and a.z == (0.2 - rest.mean()) / (rest.std() + 1e-9)
    cal.accept(0, 1, a.confidence)
    assert rows[0]["z"] == a.z
