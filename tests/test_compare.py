"""`neoslam compare`: both pipelines in one run, the image topic fanned out."""

import json

import pytest

from neoslam_stream.cli import main

pytestmark = pytest.mark.zenoh


def test_compare_runs_both_pipelines_on_the_same_frames(tmp_path):
    rc = main(["compare", "--max-frames", "60", "--no-live", "--out", str(tmp_path)])
    assert rc == 0
    table = json.loads((tmp_path / "compare.json").read_text())
    assert table["neoslam"]["frames_processed"] == table["ratslam"]["frames_processed"] == 60
    for sub in (tmp_path, tmp_path / "ratslam"):
        assert (sub / "trajectory.tum").exists() and (sub / "map.json").exists()
    assert (tmp_path / "compare.png").exists()
    report = json.loads((tmp_path / "report.json").read_text())
    assert {"A", "D", "rs_local_view", "rs_pose_cells", "rs_experience_map"} <= set(report["stages"])
