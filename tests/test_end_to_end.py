"""The real NeoSLAM pipeline end to end through real processes on the synthetic world."""

import pytest

from neoslam_stream.algorithms.features import FeatureConfig, VisualFeatureExtractor
from neoslam_stream.config import load_config
from neoslam_stream.evaluation import evaluate_run
from neoslam_stream.launch import run

pytestmark = pytest.mark.zenoh


def _cfg(topology: str, **source):
    params = {"seed": 0, **source}
    return load_config("default", {"run": {"topology": topology, "live": False},
                                   "source": {"kind": "synthetic", "params": params}})


def test_feature_batches_equal_single_frames():
    fx = VisualFeatureExtractor(**{**FeatureConfig().model_dump(), "backbone": "random_alexnet"})
    import numpy as np

    imgs = [np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8) for i in range(4)]
    np.testing.assert_array_equal(fx.extract_batch(imgs), np.stack([fx.extract(i) for i in imgs]))


@pytest.mark.slow
def test_map_beats_odometry_on_the_synthetic_world(tmp_path):
    # two laps: the second revisits every place of the first, loop closures must undo the drift
    # (the monolithic topology computes the same rows: tests/test_default_run.py)
    res = run(_cfg("pipeline", laps_cw=2, laps_ccw=0), tmp_path)
    assert res.report["loss"] == 0.0 and res.report["errors"] == 0
    ev = evaluate_run(tmp_path, plot=False)
    assert ev["loop_closures"]["closures"] > 0
    assert ev["trajectory_ape"]["mean_m"] < ev["odometry_ape"]["mean_m"], ev
