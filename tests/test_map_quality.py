"""The default on a short synthetic run: its loop closures against ground truth, and its bytes.

1000 frames of the synthetic world (one lap and the first quarter of the second: the revisits
are frames ~790-1000) through the in-process cores with the shipped default config. A closure is
correct when the matched template's first frame lies within 1 m of the frame's true position
(``evaluation.loop_closure_quality``). The bars leave room for a different backbone build or BLAS
(measured values: docs/evaluation.md): precision >= 0.95 (the paper's rule fails it by far), at
least 150 closures and recall >= 0.6 (a filter that refused nearly everything would fail them).
The same run's templates and trajectory equal, byte for byte, those of ``neoslam run
--max-frames 1000`` (tests/data/default_profile_1000, README there): the cores in this process
compute what the pipeline's processes compute.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neoslam_stream import NeoSLAM, load_config
from neoslam_stream.evaluation import loop_closure_quality
from neoslam_stream.sources.synthetic import SyntheticWorldSource

FRAMES = 1000

#: 1000 frames rendered and stepped through the whole chain in-process: tens of seconds
pytestmark = pytest.mark.slow


def test_default_closures_are_precise_on_a_short_synthetic_run(tmp_path):
    cfg = load_config("default")
    slam = NeoSLAM(cfg, run_dir=tmp_path)
    gt = []
    for f in SyntheticWorldSource(**{**cfg.source.params, "frames": FRAMES}):
        slam.step(f.image, odometry=f.odom, stamp=f.stamp)
        gt.append((f.stamp, *f.groundtruth))
    slam.finish()
    q = loop_closure_quality(tmp_path / "templates.csv", np.array(gt), radius=1.0)
    assert q["closures"] >= 150, q
    assert q["precision"] >= 0.95, q
    assert q["recall"] >= 0.6, q
    from test_default_run import FILES, _same

    ref = Path(__file__).resolve().parent / "data" / "default_profile_1000"
    assert _same(tmp_path, ref) == dict.fromkeys(FILES, True)
