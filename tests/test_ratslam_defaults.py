"""Every RatSLAM config model builds, with its own defaults, an object that processes an input."""

import numpy as np

from neoslam_stream.algorithms.ratslam.actions import CREATE_NODE
from neoslam_stream.algorithms.ratslam.experience_map import ExperienceMap, ExperienceMapConfig
from neoslam_stream.algorithms.ratslam.local_view import LocalViewCells, LocalViewConfig
from neoslam_stream.algorithms.ratslam.odometry_bias import OdometryBiasConfig, YawBiasEstimator
from neoslam_stream.algorithms.ratslam.odometry_gate import OdometryGate, OdometryGateConfig
from neoslam_stream.algorithms.ratslam.pose_cells import PoseCellConfig, PoseCellNetwork
from neoslam_stream.algorithms.ratslam.visual_odometry import VisualOdometry, VisualOdometryConfig


def test_pose_cells_with_default_config_make_an_experience():
    pc = PoseCellNetwork(PoseCellConfig())
    pc.on_view_template(0)
    pc.on_odo(0.1, 0.0, 1.0)
    assert pc.get_action()[0] == CREATE_NODE


def test_experience_map_with_default_config_places_a_node():
    em = ExperienceMap(ExperienceMapConfig())
    em.on_odo(1.0, 0.0, 1.0)
    em.on_action(CREATE_NODE, 0, 0, 0.0)
    assert em.n_experiences == 1


def test_local_view_with_default_config_matches_a_repeated_image():
    lv = LocalViewCells(LocalViewConfig())
    img = np.random.default_rng(0).integers(0, 256, (120, 240), dtype=np.uint8)
    assert lv.on_image(img) == (0, 0.0)
    assert lv.on_image(img) == (0, 0.0)
    assert lv.templates.shape == (1, 20, 60)


def test_visual_odometry_with_default_config_gives_rates_from_the_second_frame():
    vo = VisualOdometry(VisualOdometryConfig())
    img = np.random.default_rng(1).integers(0, 256, (60, 100), dtype=np.uint8)
    assert vo.on_image(img) is None
    assert vo.on_image(img) == (0.0, 0.0)


def test_yaw_bias_estimator_and_gate_with_default_configs_pass_everything_through():
    bias, gate = YawBiasEstimator(OdometryBiasConfig()), OdometryGate(OdometryGateConfig())
    assert bias.correct(0.25, 0.1) == 0.25 and not bias.enabled
    gate.on_odo(1.0, 0.0, 1.0)
    assert gate.check(0) and not gate.enabled
