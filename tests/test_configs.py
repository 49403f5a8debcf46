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


def test_another_source_kind_does_not_inherit_the_configs_source_params():
    # default.yaml's synthetic world has params (seed...) that a folder source does not take
    base = load_config("default")
    assert base.source.kind == "synthetic" and base.source.params
    cfg = load_config("default", {"source": {"kind": "folder", "params": {"path": "data/x"}}})
    assert cfg.source.kind == "folder" and cfg.source.params == {"path": "data/x"}
    # the same kind keeps its params and merges the new ones on top
    same = load_config("default", {"source": {"kind": "synthetic", "params": {"frames": 5}}})
    assert same.source.params == {**base.source.params, "frames": 5}


def test_unknown_source_kind_is_one_clear_error():
    with pytest.raises(ConfigError, match=r"unknown source kind 'foldr'.*folder"):
        load_config("default", {"source": {"kind": "foldr"}})
    # a user's own class by module path stays allowed
    assert load_config("default", {"source": {"kind": "mypkg.cam:Camera"}}).source.kind == "mypkg.cam:Camera"


def test_cli_unknown_source_prints_one_line_and_exits_2(capsys):
    from neoslam_stream.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["run", "--source", "foldr", "-p", "path=x"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "unknown source kind 'foldr'" in err and "Traceback" not in err and len(err.splitlines()) == 1
