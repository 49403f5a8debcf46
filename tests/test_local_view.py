"""Local-view cells on small constructed images; the pose-cell stage's event ordering."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.local_view import LocalViewCells
from neoslam_stream.runtime.messages import Message


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


def test_local_view_stage_flags_revisits():
    from neoslam_stream.nodes.ratslam import LocalViewNode

    st = LocalViewNode(template_x_size=8, template_y_size=4, vt_shift_match=1, vt_step_match=1)
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
    from neoslam_stream.nodes.ratslam import PoseCellsNode

    events = [("odom", _odom(f)) for f in range(6)] + [("visual_template", _tmpl(f, f // 2)) for f in range(6)]
    orders = [events, events[6:] + events[:6], [e for pair in zip(events[:6], events[6:], strict=True) for e in pair]]
    results = []
    for order in orders:
        st = PoseCellsNode()
        out = []
        for topic, m in order:
            out += st.process(topic, m)
        out += st.flush()
        results.append([(m.frame, m["action"], m["dst_id"]) for _, m in out])
    assert results[0] == results[1] == results[2]
    assert [r[0] for r in results[0]] == list(range(6))  # one action per odometry, in frame order


def _brute_force(lv, t):
    """Reference: every (template, shift) error by plain loops, first minimum wins."""
    c = lv.config
    X, Y, S = c.template_x_size, c.template_y_size, c.vt_shift_match
    best = (None, math.inf, 0)
    for i, tmpl in enumerate(lv.templates):
        if abs(tmpl.mean() - t.mean()) > c.vt_match_threshold + 0.005:
            continue
        if c.vt_panoramic:
            for off in range(0, X, c.vt_step_match):
                err = sum(abs(t[y, x] - tmpl[y, (x + off) % X]) for y in range(Y) for x in range(X)) / (X * Y)
                if err < best[1] - 1e-12:
                    best = (i, err, off)
        else:
            for off in range(0, 2 * S + 1, c.vt_step_match):
                err = sum(abs(t[y, S + k] - tmpl[y, off + k]) for y in range(Y) for k in range(X - 2 * S))
                err /= X * Y - 2 * S * Y
                if err < best[1] - 1e-12:
                    best = (i, err, off)
    return best


@pytest.mark.parametrize("panoramic", [False, True])
def test_compiled_match_equals_brute_force_including_ties(panoramic):
    rng = np.random.default_rng(3)
    lv = LocalViewCells(template_x_size=12, template_y_size=3, vt_shift_match=3, vt_step_match=1,
                        vt_match_threshold=0.2, vt_panoramic=panoramic)
    base = rng.random((3, 12))
    for _ in range(6):
        lv.add_template(np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1))
    lv.add_template(lv.templates[2].copy())  # an exact duplicate: the first copy must win
    lv.add_template(rng.random((3, 12)))
    for _ in range(20):
        q = np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1)
        ti, err, _rad = lv.compare(q)
        ref = _brute_force(lv, q)
        assert ti == ref[0] and err == pytest.approx(ref[1], abs=1e-12)
    ti, err, _ = lv.compare(lv.templates[2])
    assert (ti, err) == (2, 0.0)


@pytest.mark.parametrize("panoramic", [False, True])
def test_every_templates_error_agrees_with_the_best_match(panoramic):
    # errors(t) is compare's comparison for all templates (no mean pre-filter, no early stop): its
    # minimum is compare's best template with the same error and relative_rad
    rng = np.random.default_rng(5)
    lv = LocalViewCells(template_x_size=12, template_y_size=3, vt_shift_match=3, vt_step_match=1,
                        vt_match_threshold=10.0, vt_panoramic=panoramic)
    base = rng.random((3, 12))
    for _ in range(6):
        lv.add_template(np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1))
    for _ in range(10):
        q = np.roll(np.clip(base + rng.normal(0, 0.1, base.shape), 0, 1), int(rng.integers(0, 12)), axis=1)
        errs, rads = lv.errors(q)
        ti, err, rad = lv.compare(q)
        assert errs.shape == rads.shape == (6,)
        assert int(np.argmin(errs)) == ti and errs[ti] == pytest.approx(err, abs=1e-12)
        assert rads[ti] == pytest.approx(rad, abs=1e-12) and (panoramic or rad == 0.0)


def test_patch_normalisation_clamps_window_indices_like_the_cpp():
    lv = LocalViewCells(template_x_size=3, template_y_size=1, vt_shift_match=0, vt_step_match=1,
                        vt_patch_normalise=1)
    t = lv._patch_normalise(np.array([[0.0, 0.5, 1.0]]), 1)
    # cell 0: the 3x3 window's clamped columns are (0, 0, 1) in every row: values 0, 0, 0.5
    mu = 0.5 / 3
    sd = math.sqrt((2 * mu ** 2 + (0.5 - mu) ** 2) / 3)
    assert t[0, 0] == pytest.approx(((0 - mu) / sd + 3) / 6)
    assert t[0, 1] == pytest.approx(0.5)  # the centre cell sits at its window's mean
    assert t[0, 2] == pytest.approx(1 - t[0, 0])  # mirror image


def test_flat_patch_is_neutral_when_fixed_and_one_in_compat_mode():
    for compat, value in ((False, 0.5), (True, 1.0)):
        lv = LocalViewCells(template_x_size=4, template_y_size=2, vt_shift_match=0, vt_step_match=1,
                            vt_patch_normalise=1, openratslam_compat=compat)
        assert np.all(lv._patch_normalise(np.full((2, 4), 0.3), 1) == value)  # C++: min(1, 0/0) = 1


def test_colour_frames_average_channels_like_the_cpp():
    lv = LocalViewCells(template_x_size=2, template_y_size=1, vt_shift_match=0, vt_step_match=1)
    img = np.zeros((2, 4, 3), dtype=np.uint8)
    img[:, :2, 0] = 255  # red block: (255 + 0 + 0) / 3 / 255
    img[:, 2:] = 51
    np.testing.assert_allclose(lv.view_template(img), [[1 / 3, 0.2]], rtol=0, atol=1e-15)


def test_global_normalisation_scales_to_the_target_mean():
    lv = LocalViewCells(template_x_size=4, template_y_size=1, vt_shift_match=0, vt_step_match=1,
                        vt_normalisation=0.4)
    t = lv.view_template(np.array([[51, 51, 102, 204]], dtype=np.uint8))  # 0.2 0.2 0.4 0.8, mean 0.4
    np.testing.assert_allclose(t, [[0.2, 0.2, 0.4, 0.8]])


def test_bad_input_is_refused():
    lv = LocalViewCells(template_x_size=60, template_y_size=20, vt_shift_match=4, vt_step_match=1)
    with pytest.raises(ValueError):
        lv.view_template(np.zeros((10, 30)))  # smaller than the template
    with pytest.raises(ValueError):
        LocalViewCells(template_x_size=8, vt_shift_match=4)  # no columns left to compare


def test_state_round_trip_keeps_matching():
    rng = np.random.default_rng(4)
    lv = LocalViewCells(template_x_size=16, template_y_size=4, vt_shift_match=2, vt_step_match=1)
    imgs = [rng.integers(0, 256, (8, 32), dtype=np.uint8) for _ in range(3)]
    ids = [lv.on_image(im)[0] for im in imgs]
    twin = LocalViewCells(lv.config)
    twin.load_state_dict(lv.state_dict())
    assert [twin.on_image(im)[0] for im in imgs] == ids == [0, 1, 2]


def test_a_checkpoint_with_templates_of_another_size_is_refused():
    lv = LocalViewCells(template_x_size=16, template_y_size=4, vt_shift_match=2, vt_step_match=1)
    lv.on_image(np.random.default_rng(5).integers(0, 256, (8, 32), dtype=np.uint8))
    other = LocalViewCells(template_x_size=16, template_y_size=8, vt_shift_match=2, vt_step_match=1)
    with pytest.raises(ValueError, match="template_y_size: the checkpoint's is 4, the config's 8"):
        other.load_state_dict(lv.state_dict())
    assert len(other.templates) == 0
