"""Local-view cells and visual odometry on small constructed images."""

import math

import numpy as np
import pytest

from neoslam_stream.messages import Message
from stages.ratslam.adapters import LocalViewStage, PoseCellsStage
from stages.ratslam.local_view import LocalViewCells
from stages.ratslam.visual_odometry import VisualOdometry, best_shift


def test_template_is_block_means_ignoring_leftovers():
    lv = LocalViewCells(template_x_size=2, template_y_size=1, vt_shift_match=0, vt_step_match=1)
    img = np.zeros((2, 5))
    img[:, 0:2] = 51.0  # block 0: columns 0-1
    img[:, 2:4] = 102.0  # block 1: columns 2-3; column 4 is a leftover and ignored
    img[:, 4] = 255.0
    np.testing.assert_allclose(lv.view_template(img), [[0.2, 0.4]])


def test_same_view_matches_shifted_view_matches_new_view_creates():
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (20, 60)).astype(float)
    lv = LocalViewCells(template_x_size=60, template_y_size=20, vt_shift_match=4, vt_step_match=1,
                        vt_match_threshold=0.03)
    assert lv.on_image(base)[0] == 0
    assert lv.on_image(np.roll(base, 3, axis=1))[0] == 0  # within +-4 columns
    assert lv.last_error < 1e-12 or lv.last_error <= 0.03
    other = rng.integers(0, 256, (20, 60)).astype(float)
    assert lv.on_image(other)[0] == 1
    assert lv.on_image(base)[0] == 0


def test_panoramic_relative_rad():
    rng = np.random.default_rng(1)
    base = rng.integers(0, 256, (10, 60)).astype(float)
    lv = LocalViewCells(template_x_size=60, template_y_size=10, vt_panoramic=True, vt_step_match=5,
                        vt_match_threshold=0.03)
    lv.on_image(base)
    vt, rad = lv.on_image(np.roll(base, -15, axis=1))  # a quarter turn of a 60-column panorama
    assert vt == 0 and rad == pytest.approx(math.pi / 2)


def test_visual_odometry_shift_sign_and_scale():
    prof = np.sin(np.linspace(0, 12, 200))
    off, diff = best_shift(np.roll(prof, 5), prof)
    assert off == 5 and diff < 0.05
    vo = VisualOdometry(camera_fov_deg=50, camera_hz=10)
    img = np.tile((np.sin(np.linspace(0, 20, 200)) * 100 + 120)[None], (30, 1))
    assert vo.on_image(img) is None
    vtrans, vrot = vo.on_image(np.roll(img, 4, axis=1))
    assert vrot == pytest.approx(4 * 50 / 200 * 10 * math.pi / 180)


def test_local_view_stage_flags_revisits():
    st = LocalViewStage(template_x_size=8, template_y_size=4, vt_shift_match=1, vt_step_match=1)
    rng = np.random.default_rng(2)
    a, b = (rng.integers(0, 256, (16, 32, 3), dtype=np.uint8) for _ in range(2))
    outs = [st.process("image", Message("image", i, 0.0, {"image": im, "encoding": "rgb8"}))[0][1]
            for i, im in enumerate([a, b, a])]
    assert [m["id"] for m in outs] == [0, 1, 0]
    assert [m["is_loop_closure"] for m in outs] == [False, False, True]


def _odom(f):
    return Message("odom", f, f * 0.1, {"vtrans": 0.1, "vrot": 0.0, "dt": 0.1})


def _tmpl(f, vt):
    return Message("visual_template", f, f * 0.1, {"id": vt})


def test_pose_cells_stage_is_order_independent():
    events = [("odom", _odom(f)) for f in range(6)] + [("visual_template", _tmpl(f, f // 2)) for f in range(6)]
    orders = [events, events[6:] + events[:6], [e for pair in zip(events[:6], events[6:], strict=True) for e in pair]]
    results = []
    for order in orders:
        st = PoseCellsStage()
        out = []
        for topic, m in order:
            out += st.process(topic, m)
        out += st.flush()
        results.append([(m.frame, m["action"], m["dst_id"]) for _, m in out])
    assert results[0] == results[1] == results[2]
    assert [r[0] for r in results[0]] == list(range(6))  # one action per odometry, in frame order
