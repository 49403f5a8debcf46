"""Every shipped config validates, and the dataset values are the research notes' values."""

from pathlib import Path

import pytest

from neoslam_stream.config import ConfigError, load_config, packaged_configs

# the YAML files in the source tree: every one of them must ship (and validate)
CONFIGS = sorted((Path(__file__).resolve().parents[1] / "neoslam_stream" / "configs").glob("*.yaml"))


def test_every_config_file_ships():
    assert len(CONFIGS) >= 6
    assert packaged_configs() == [p.stem for p in CONFIGS]


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_config_validates(path):
    load_config(path)
    load_config(path.stem)  # by name, through importlib.resources


def test_unknown_config_name_lists_the_shipped_ones():
    with pytest.raises(ConfigError, match="irat2011"):
        load_config("no_such_config")


def test_dataset_values():
    irat = load_config("irat2011")
    assert (irat.pose_cells.pc_dim_xy, irat.pose_cells.pc_cell_x_size, irat.pose_cells.pc_vt_inject_energy) == (
        11, 0.015, 0.1)
    assert (irat.experience_map.exp_loops, irat.experience_map.exp_initial_em_deg) == (20, 140)
    lake = load_config("fiu_lake")
    assert (lake.spatial_view.theta_sigma, lake.spatial_view.exclude_recent_intervals) == (410, 20)
    rob = load_config("robotarium")
    assert (rob.spatial_view.theta_rho, rob.spatial_view.theta_sigma, rob.experience_map.exp_loops) == (6, 485, 1)
    stl = load_config("stlucia")
    assert stl.odometry == "visual" and stl.visual_odometry.vtrans_scaling == 1000
