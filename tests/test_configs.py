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


# ---------------------------------------------------------------------------- a config on top of its base
def test_a_short_config_of_ones_own_runs_the_default_on_its_source(tmp_path):
    own = tmp_path / "my.yaml"
    own.write_text("source:\n  kind: folder\n  params: {path: data/run1}\nodometry: visual\n")
    cfg = load_config(own)
    # applied on top of the shipped default: the same as the default with these values on top
    expected = load_config("default", {"source": {"kind": "folder", "params": {"path": "data/run1"}},
                                       "odometry": "visual"})
    assert cfg.model_dump() == expected.model_dump()
    assert cfg.run.pipeline == "neoslam" and cfg.source.params == {"path": "data/run1"}  # no synthetic seed
    assert cfg.platform == load_config("default").platform


def test_base_none_starts_from_the_models_defaults_and_shipped_configs_are_complete(tmp_path):
    from neoslam_stream.config import FullRunConfig, packaged_config_text

    bare = tmp_path / "bare.yaml"
    bare.write_text("base: none\nodometry: visual\n")
    assert load_config(bare).model_dump() == FullRunConfig(odometry="visual").model_dump()
    for name in packaged_configs():  # each says base: none, so it means what it says
        text = packaged_config_text(name)
        assert "\nbase: none" in "\n" + text, name
        assert load_config(name).model_dump() == load_config(_written(tmp_path, name, text)).model_dump()


def _written(tmp_path, name, text):
    path = tmp_path / f"copy_of_{name}.yaml"  # `neoslam config show NAME > copy.yaml`: the same config
    path.write_text(text)
    return path


def test_a_base_can_be_a_shipped_config_or_a_file_and_faults_are_one_line(tmp_path):
    (tmp_path / "lab.yaml").write_text("platform: {speed_mps: 0.8}\n")
    (tmp_path / "robot.yaml").write_text("base: lab.yaml\nplatform: {area_m: 25}\n")
    cfg = load_config(tmp_path / "robot.yaml")  # robot on lab on the default
    assert (cfg.platform.speed_mps, cfg.platform.area_m, cfg.run.pipeline) == (0.8, 25, "neoslam")
    (tmp_path / "irat.yaml").write_text("base: irat2011\nsource: {params: {path: x.bag}}\n")
    irat = load_config(tmp_path / "irat.yaml")
    assert irat.pose_cells.pc_dim_xy == 11 and irat.source.params["image_topic"].startswith("/irat_red")
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(ConfigError, match="comes back to itself"):
        load_config(tmp_path / "a.yaml")
    (tmp_path / "c.yaml").write_text("base: defualt\n")
    with pytest.raises(ConfigError, match="no shipped config"):
        load_config(tmp_path / "c.yaml")


def test_config_show_prints_a_file_merged_onto_its_base(tmp_path, capsys, monkeypatch):
    import yaml

    from neoslam_stream.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "my.yaml").write_text("source:\n  kind: video\n  params: {path: robot.mp4}\n")
    assert main(["config", "show", "my.yaml"]) == 0
    shown = capsys.readouterr().out
    assert shown.startswith("# my.yaml on default")
    (tmp_path / "shown.yaml").write_text(shown)
    assert yaml.safe_load(shown)["run"]["pipeline"] == "neoslam"
    assert load_config(tmp_path / "shown.yaml").model_dump() == load_config(tmp_path / "my.yaml").model_dump()
