"""evo (an outside tool: GPL-3.0, never imported by the package) reads our TUM files and gives our
APE and RPE: the commands of docs/evaluation.md, run on a run folder's files. Skipped where
``evo_ape`` / ``evo_rpe`` are not on PATH (``pip install evo`` puts them there)."""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess

import numpy as np
import pytest

from neoslam_stream.evaluation import ape, rpe, write_tum

EVO = shutil.which("evo_ape"), shutil.which("evo_rpe")
pytestmark = pytest.mark.skipif(not all(EVO), reason="evo is not installed (evo_ape / evo_rpe not on PATH; "
                                                     "pip install evo, a GPL tool kept outside the package)")


def _evo(args: list[str], cwd, home) -> dict[str, float]:
    """The statistics evo prints (max, mean, median, min, rmse, sse, std)."""
    r = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-2000:]
    return {k: float(v) for k, v in re.findall(r"^\s*(max|mean|median|min|rmse|sse|std)\s+([-\d.e+]+)\s*$",
                                               r.stdout, re.M)}


def test_evo_reads_our_tum_files_and_agrees(tmp_path):
    # a loop with a drifting estimate, stamps as a run folder has them (source time, 10 Hz)
    t = np.arange(400) * 0.1
    a = t * 0.08
    gt = np.column_stack([t, 6 * np.cos(a), 4 * np.sin(a), a + math.pi / 2])
    est = gt.copy()
    est[:, 1:3] = (gt[:, 1:3] * 1.03 + [2.0, -1.0]) @ np.array([[math.cos(0.2), math.sin(0.2)],
                                                                 [-math.sin(0.2), math.cos(0.2)]])
    est[:, 3] += 0.2 + 0.002 * np.arange(400)
    write_tum(tmp_path / "groundtruth.tum", gt)
    write_tum(tmp_path / "trajectory.tum", est)
    home = tmp_path / "home"
    home.mkdir()
    ours = ape(est[:, 1:3], gt[:, 1:3])
    got = _evo(["evo_ape", "tum", "groundtruth.tum", "trajectory.tum", "--align", "--t_max_diff", "0.5"], tmp_path, home)
    assert got["mean"] == pytest.approx(ours["mean_m"], abs=1e-5)
    assert got["rmse"] == pytest.approx(ours["rmse_m"], abs=1e-5) and got["max"] == pytest.approx(ours["max_m"], abs=1e-5)
    for delta in (1, 5):
        mine = rpe(est[:, 1:], gt[:, 1:], float(delta))
        got = _evo(["evo_rpe", "tum", "groundtruth.tum", "trajectory.tum", "--delta", str(delta), "--delta_unit", "m",
                    "--pairs_from_reference", "--t_max_diff", "0.5"], tmp_path, home)
        assert got["mean"] == pytest.approx(mine["mean_m"], abs=1e-5), delta
        assert got["max"] == pytest.approx(mine["max_m"], abs=1e-5), delta
        got = _evo(["evo_rpe", "tum", "groundtruth.tum", "trajectory.tum", "--delta", str(delta), "--delta_unit", "m",
                    "--pairs_from_reference", "--t_max_diff", "0.5", "--pose_relation", "angle_deg"], tmp_path, home)
        assert got["mean"] == pytest.approx(mine["rot_mean_deg"], abs=1e-4), delta
