"""bench/day_back_end.py: a finished day's back end replayed from its templates.csv and the route's
recomputed odometry gives what the run's back end gave."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import day_back_end  # noqa: E402

from neoslam_stream.algorithms.backend import BackEnd  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402
from neoslam_stream.tum import write_tum  # noqa: E402

PARAMS = {"seed": 3, "speed": 3.0, "laps_cw": 1, "laps_ccw": 0, "width": 8, "height": 8, "loop": True}


def _fake_run(tmp_path: Path, laps: int) -> tuple[Path, np.ndarray]:
    """A run folder as a lossless run of the default's back end on a short synthetic route would
    leave it, with a perfect front end (a template per two frames of the route, the same on every
    lap): its config, templates.csv and trajectory.tum, the odometry taken from the source's own
    frames (what a run receives)."""
    cfg = load_config("default", {"source": {"params": PARAMS}})
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    src = SyntheticWorldSource(**PARAMS)
    be = BackEnd(cfg.back_end())
    rows, poses = ["frame,stamp,template_id,is_loop_closure,best_interval,best_score"], []
    for f in src:
        if f.frame == laps * src.route_len:
            break
        tid = (f.frame % src.route_len) // 2
        p = be.step(tid, 0.0, *f.odom, stamp=f.stamp)
        rows.append(f"{f.frame},{f.stamp:.6f},{tid},0,-1,0.0")
        poses.append((f.stamp, *p.pose[:3]))
    (run / "templates.csv").write_text("\n".join(rows) + "\n")
    write_tum(run / "trajectory.tum", np.array(poses))
    return run, np.array(poses)


def test_the_replay_gives_the_runs_poses_and_reads_each_lap(tmp_path):
    run, poses = _fake_run(tmp_path, laps=3)
    route = SyntheticWorldSource(**PARAMS).route_len
    res = day_back_end.replay(str(run), [], None)
    assert [r["lap"] for r in res["laps"]] == [1, 2, 3]
    np.testing.assert_allclose(res["first_lap_poses"][:, :2], poses[:route, 1:3], atol=1e-9)
    # the true bias of a lap: the source's odometry less the true yaw rate, by its definition
    # (odom_yaw_bias plus a random walk plus white noise), averaged over the lap
    _, odo, true_bias, gt, n_route, rate = day_back_end.route_input(run, None)
    assert n_route == route and rate == 10.0 and len(odo) == 3 * route
    src_cfg = SyntheticWorldSource(**PARAMS).config
    noise = np.random.default_rng(PARAMS["seed"] + 1).normal(0.0, 1.0, (len(odo), 3))
    walk = np.cumsum(noise[:, 0] * src_cfg.odom_noise * src_cfg.odom_walk)
    expected = src_cfg.odom_yaw_bias + walk + src_cfg.odom_noise * noise[:, 2]
    np.testing.assert_allclose(true_bias[1:], expected[1:], atol=1e-9)
    assert res["laps"][1]["bias_true_rad_s"] == pytest.approx(expected[route:2 * route].mean(), abs=1e-5)


def test_another_odometry_seed_keeps_the_templates_and_redraws_the_noise(tmp_path):
    run, _ = _fake_run(tmp_path, laps=2)
    tpl, odo, bias, *_ = day_back_end.route_input(run, None)
    tpl7, odo7, bias7, *_ = day_back_end.route_input(run, None, odom_seed=7)
    np.testing.assert_array_equal(tpl7, tpl)
    # the same true motion: the odometry differs by its noise only, drawn from seed 7
    noise = np.random.default_rng(7).normal(0.0, 1.0, (len(odo), 3))
    cfg = SyntheticWorldSource(**PARAMS).config
    walk = np.cumsum(noise[:, 0] * cfg.odom_noise * cfg.odom_walk)
    np.testing.assert_allclose(bias7[1:], (cfg.odom_yaw_bias + walk + cfg.odom_noise * noise[:, 2])[1:], atol=1e-9)
    assert not np.allclose(bias7[1:], bias[1:])
    # the run's own seed named explicitly is the run's odometry
    np.testing.assert_array_equal(day_back_end.route_input(run, None, odom_seed=PARAMS["seed"] + 1)[1], odo)


def test_a_setting_changes_only_the_replay_it_names(tmp_path):
    run, _ = _fake_run(tmp_path, laps=1)
    cfg = day_back_end.back_end_config(run, ["pose_cells.odometry_bias.reference=first",
                                             "experience_map.prune_m=0"])
    assert cfg["pose_cells"]["odometry_bias"]["reference"] == "first" and cfg["experience_map"]["prune_m"] == 0
    assert day_back_end.back_end_config(run, [])["experience_map"]["prune_m"] > 0


def test_targets_compare_every_lap_from_the_third_with_the_second():
    laps = [{"ape_online_m": 1.0, "ape_final_map_m": 1.0}, {"ape_online_m": 0.2, "ape_final_map_m": 0.1},
            {"ape_online_m": 0.21, "ape_final_map_m": 0.1}, {"ape_online_m": 0.23, "ape_final_map_m": 0.105}]
    t = day_back_end.targets(laps)
    assert t["ape_online_m_worst_vs_lap2"] == pytest.approx(1.15)
    assert t["ape_final_map_m_worst_vs_lap2"] == pytest.approx(1.05)
    assert t["reached"] == {"ape_online": False, "ape_final_map": True}


def test_a_run_that_lost_frames_or_is_not_synthetic_is_refused(tmp_path):
    run, _ = _fake_run(tmp_path, laps=1)
    lines = (run / "templates.csv").read_text().splitlines()
    (run / "templates.csv").write_text("\n".join(lines[:5] + lines[6:]) + "\n")
    with pytest.raises(SystemExit, match="misses frames"):
        day_back_end.route_input(run, None)
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    cfg["source"]["kind"] = "video"
    (run / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(SystemExit, match="synthetic route"):
        day_back_end.route_input(run, None)


def test_an_export_packs_the_runs_front_end_with_the_replayed_back_end(tmp_path):
    from neoslam_stream.nodes.ratslam import ExperienceMapNode, PoseCellsNode
    from neoslam_stream.runtime.checkpoint import load_map_file, save_state_file

    run, _ = _fake_run(tmp_path, laps=2)
    save_state_file(run / "state" / "D.state", {"places": np.arange(3)})
    save_state_file(run / "state" / "experience_map.state", {"stale": 1})  # replaced by the replay's
    res = day_back_end.replay(str(run), [], None, states=True)
    out = tmp_path / "day_x.neoslam"
    day_back_end.export_with(run, res["states"], 2 * SyntheticWorldSource(**PARAMS).route_len, out)
    stages = load_map_file(out)["stages"]
    assert sorted(stages) == ["D", "experience_map", "pose_cells"]
    np.testing.assert_array_equal(stages["D"]["places"], np.arange(3))
    sections = day_back_end.back_end_config(run, [])
    em = ExperienceMapNode(**sections["experience_map"])
    em.load_state_dict(stages["experience_map"])
    assert em.em.n_experiences == res["laps"][-1]["experiences"] > 0
    pc = PoseCellsNode(**sections["pose_cells"])
    pc.load_state_dict(stages["pose_cells"])
    assert pc.last_odom_frame == 2 * SyntheticWorldSource(**PARAMS).route_len - 1
    assert not out.with_suffix("").exists()  # the folder it was packed from is gone


def test_a_replayed_state_reproduces_a_saved_one_with_state_added_since():
    """reproduces_run_end: every value the run saved must be in the replayed state, exactly; keys the
    code has added to a state since (the bias's anchoring) are not the run's to match."""
    saved = {"pc": {"P": np.arange(4.0)}, "bias": {"scalars": [0.1, 2.0]}}
    replayed = {"pc": {"P": np.arange(4.0)}, "bias": {"scalars": [0.1, 2.0], "anchor": [0.1, 0.0, np.nan]}}
    assert day_back_end._same(saved, replayed)
    assert not day_back_end._same(replayed, saved)  # a value the replay lacks
    replayed["pc"]["P"] = np.arange(4.0) + 1e-12
    assert not day_back_end._same(saved, replayed)  # one value off
