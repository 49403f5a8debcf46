"""`neoslam compare`: NeoSLAM (the config and the paper's profile) and RatSLAM in one run, the image
topic fanned out."""

import json

import numpy as np
import pytest
import yaml

from neoslam_stream.cli import main
from neoslam_stream.config import packaged_config_text

pytestmark = pytest.mark.zenoh


def test_compare_runs_every_pipeline_on_the_same_frames_and_shares_common_stages(tmp_path, capsys):
    """One run of `neoslam compare` (its outputs for each pipeline, the table, the figure), with a
    config that differs from the paper's profile in D only, so that A, B and C run once for both."""
    cfg = yaml.safe_load(packaged_config_text("paper"))
    cfg["spatial_view"]["theta_sigma"] = 300
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    assert main(["compare", "-c", str(path), "--max-frames", "60", "--no-live", "--out", str(out),
                 "--radius", "0.5"]) == 0
    stages = set(json.loads((out / "report.json").read_text())["stages"])
    assert {"A", "D", "rs_local_view", "rs_pose_cells", "rs_experience_map"} <= stages
    assert {"pp_D", "pp_pose_cells", "pp_experience_map"} <= stages
    assert not {"pp_A", "pp_B", "pp_C"} & stages
    table = json.loads((out / "compare.json").read_text())
    assert [table[k]["frames_processed"] for k in ("neoslam", "neoslam_paper", "ratslam")] == [60, 60, 60]
    assert table["neoslam_paper"]["same_as_default"] is False
    assert all(table[k]["loop_radius_m"] == 0.5 for k in ("neoslam", "neoslam_paper", "ratslam"))
    for name in ("trajectory.tum", "map.json", "templates.csv", "closures.csv"):
        assert (out / "paper" / name).exists()
    for sub in (out, out / "ratslam"):
        assert (sub / "trajectory.tum").exists() and (sub / "map.json").exists()
    assert (out / "compare.png").exists()
    # both Ds saw the same SDRs (C's one output): intervals depend on theta_alpha and theta_rho only
    # and scores not on theta_sigma, so the best scores agree frame by frame, and every frame
    # closed at theta_sigma 470 is closed at 300
    mine = np.loadtxt(out / "templates.csv", delimiter=",", skiprows=1)
    paper = np.loadtxt(out / "paper" / "templates.csv", delimiter=",", skiprows=1)
    assert np.array_equal(mine[:, 0], paper[:, 0]) and np.array_equal(mine[:, 5], paper[:, 5])
    assert np.all(mine[:, 3] >= paper[:, 3])
    # 60 frames (1.8 m of travel) revisit nothing: every match is a re-recognition, none a loop closure
    assert (out / "compare_pr.png").exists()
    assert table["neoslam"]["loop_closures"] == table["neoslam_paper"]["loop_closures"] == 0
    assert table["neoslam"]["loop_re_recognitions"] == int(mine[:, 3].sum()) > 0
    assert table["neoslam_paper"]["loop_re_recognitions"] == int(paper[:, 3].sum())
    printed = capsys.readouterr().out
    # a column per pipeline, its name over two lines: "NeoSLAM" above "(paper)"
    assert "(paper)" in printed and "RatSLAM" in printed and "within 0.5 m" in printed
    assert (f"re-recognitions of a place just passed (not loop closures): NeoSLAM (default) "
            f"{int(mine[:, 3].sum())}, NeoSLAM (paper) {int(paper[:, 3].sum())}, RatSLAM") in printed
