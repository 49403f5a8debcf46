"""RatSLAM visual odometry: scanline profiles, the C++'s shift search order, scaling constants."""

import math

import numpy as np
import pytest

from neoslam_stream.algorithms.ratslam.visual_odometry import VisualOdometry, best_shift, profile
from neoslam_stream.runtime.messages import Message


def test_profile_is_column_mean_of_the_window_scaled_to_one():
    img = np.zeros((6, 5), dtype=np.uint8)
    img[2:4, 1] = 255  # rows 2-3 of column 1
    img[0, :] = 255  # row 0 is outside the window below
    np.testing.assert_allclose(profile(img, 0, -1, 1, 5), [0, 0.5, 0, 0, 0])  # 2 of 4 rows at 255


def test_colour_profile_sums_channels_like_the_cpp():
    img = np.zeros((2, 3, 3), dtype=np.uint8)
    img[:, 0] = (30, 60, 90)  # (30 + 60 + 90) / (3 * 255)
    assert profile(img, 0, -1, 0, -1)[0] == 180 / 765


def test_shift_sign_and_size():
    prof = np.sin(np.linspace(0, 12, 200))
    off, diff = best_shift(np.roll(prof, 5), prof)  # the scene moved 5 columns to the right
    assert off == 5 and diff < 0.05
    off, _ = best_shift(np.roll(prof, -7), prof)
    assert off == -7


def test_ties_go_to_the_negative_shift_first_as_in_the_cpp():
    prev = np.tile([0.0, 1.0], 50)
    cur = np.roll(prev, 1)  # matches prev exactly at shift +1 and at shift -1
    off, diff = best_shift(cur, prev)
    assert diff == 0.0 and off == -1  # the C++ scans 0..-39 before 0..+39, strict "<"


def test_rates_follow_openratslam_constants():
    # 200 px wide, 50 deg field of view, 10 Hz: 4 columns = 1 deg per frame = 10 deg/s
    img = np.tile((np.sin(np.linspace(0, 20, 200)) * 100 + 120)[None], (30, 1)).astype(np.uint8)
    vo = VisualOdometry(camera_fov_deg=50, camera_hz=10, vtrans_scaling=100)
    assert vo.on_image(img) is None  # the first frame has nothing to compare with
    vtrans, vrot = vo.on_image(np.roll(img, 4, axis=1))
    assert vrot == pytest.approx(math.radians(10.0))
    assert vtrans < 100 * 0.05  # the same texture, shifted: small "translation"



def test_translation_is_profile_difference_times_scaling():
    rng = np.random.default_rng(0)
    img = np.repeat(rng.integers(0, 200, (1, 120)), 2, axis=0).astype(np.uint8)  # rough texture
    vo = VisualOdometry(vtrans_scaling=10)
    vo.on_image(img)
    vtrans, vrot = vo.on_image(img + 51)  # unshifted, every column +51/255 = 0.2 brighter
    assert vtrans == pytest.approx(0.2 * 10) and vrot == 0.0


def test_vtrans_is_capped():
    vo = VisualOdometry(vtrans_scaling=1000, vtrans_max=20)
    vo.on_image(np.zeros((4, 50), dtype=np.uint8))
    vtrans, _ = vo.on_image(np.full((4, 50), 255, dtype=np.uint8))
    assert vtrans == 20


def test_real_frame_interval_fixes_rotation_after_a_dropped_frame():
    img = np.tile((np.sin(np.linspace(0, 20, 200)) * 100 + 120)[None], (30, 1)).astype(np.uint8)
    turned = np.roll(img, 4, axis=1)  # 1 deg between the two frames compared
    for compat, degrees in ((False, 1.0), (True, 2.0)):
        vo = VisualOdometry(camera_fov_deg=50, camera_hz=10, openratslam_compat=compat)
        vo.on_image(img)
        _, vrot = vo.on_image(turned, dt=0.2)  # one frame was dropped: 0.2 s between them
        # integrated by the consumer over dt: the real 1 deg, or the C++'s 10 deg/s * 0.2 s
        assert math.degrees(vrot * 0.2) == pytest.approx(degrees)


def test_stage_publishes_odometry_with_image_intervals():
    from neoslam_stream.nodes.ratslam import VisualOdometryNode

    st = VisualOdometryNode(camera_fov_deg=50, camera_hz=10)
    img = np.tile((np.sin(np.linspace(0, 20, 200)) * 100 + 120)[None], (30, 1)).astype(np.uint8)
    frames = [img, np.roll(img, 4, axis=1)]
    outs = [st.process("image", Message("image", i, 0.1 * i, {"image": f}))[0][1] for i, f in enumerate(frames)]
    assert [o.type for o in outs] == ["odom", "odom"]
    assert (outs[0]["vtrans"], outs[0]["vrot"]) == (0.0, 0.0)
    assert outs[1]["dt"] == pytest.approx(0.1) and outs[1]["vrot"] == pytest.approx(math.radians(10.0))
    with pytest.raises(ValueError):  # StageInputError: the window is outside a tiny frame
        VisualOdometryNode(vtrans_image_y_min=50).process("image", Message("image", 0, 0.0, {"image": img}))


# ---------------------------------------------------------------------------- calibrated scale, pinhole rotation
def test_the_typical_speed_scale_maps_the_median_raw_speed_so_far_to_the_platforms_speed():
    from neoslam_stream.algorithms.ratslam.visual_odometry import TypicalSpeedScale

    s = TypicalSpeedScale(0.3)
    # raw 2: median 2 -> 0.3; raw 4: median of (2, 4) 3 -> 0.4; raw 6: median 4 -> 0.45; raw 0 -> 0;
    # raw 3: median of (0, 2, 3, 4, 6) 3 -> 0.3
    assert [s(r) for r in (2.0, 4.0, 6.0, 0.0, 3.0)] == pytest.approx([0.3, 0.4, 0.45, 0.0, 0.3])
    assert TypicalSpeedScale(0.3)(0.0) == 0.0  # nothing has moved yet: no scale, no motion


def test_scale_platform_reads_the_first_motion_as_the_typical_speed():
    img = np.full((2, 120), 20, dtype=np.uint8)  # flat: every shift differs alike, shift 0 is tried first
    vo = VisualOdometry(scale="platform", speed_mps=0.5)
    vo.on_image(img, 0.1)
    # 51/255 = 0.2 brighter, then 102/255 = 0.4 more: raw speeds 2 and 4 per second, medians 2 and 3
    v1, _ = vo.on_image(img + 51, 0.1)
    v2, _ = vo.on_image(img + 153, 0.1)
    assert (v1, v2) == pytest.approx((0.5, 0.5 * 4 / 3))
    with pytest.raises(ValueError, match="speed_mps"):
        VisualOdometry(scale="platform")


def _pinhole_view(heading: float, width: int = 200, focal: float = 100.0) -> np.ndarray:
    """A pinhole camera's view of a world whose brightness depends on the direction only: column u
    (from the centre, + to the right) looks at heading - atan(u / f)."""
    u = np.arange(width) + 0.5 - width / 2
    row = 120 + 100 * np.sin(7 * (heading - np.arctan(u / focal)))
    return np.tile(row[None], (20, 1)).astype(np.uint8)


def test_pinhole_centre_reads_a_rotation_as_the_angle_of_the_centres_shift_and_no_translation():
    from neoslam_stream.algorithms.ratslam.visual_odometry import rotated_difference

    # 200 columns at 90 degrees: f = 100 px; a left turn of 0.05 rad moves the centre by
    # f tan(0.05) = 5.004 columns: the best shift is 5, read as atan(5 / 100) rad in 0.1 s
    before, after = _pinhole_view(0.0), _pinhole_view(0.05)
    vo = VisualOdometry(camera_fov_deg=90, rotation="pinhole_centre")
    vo.on_image(before, 0.1)
    vtrans, vrot = vo.on_image(after, 0.1)
    assert vrot == pytest.approx(math.atan(5 / 100) / 0.1)
    # undone, the rotation leaves only the views' rounding to 8 bits (at most a level between the
    # two); one shift for every column, as OpenRatSLAM's translation reads it, leaves more than that
    # rounding could
    p0, p1 = profile(before, 0, -1, 0, -1), profile(after, 0, -1, 0, -1)
    undone = rotated_difference(p1, p0, 0, 200, 100.0, math.atan2(5, 100))
    assert undone <= 1 / 255 < 2 / 255 < best_shift(p1, p0)[1]
    assert vtrans == pytest.approx(undone * 100 / (10 * 0.1))  # vtrans_scaling 100, camera_hz 10


def test_state_keeps_the_profiles_and_the_raw_speeds():
    img = np.full((2, 120), 20, dtype=np.uint8)
    vo = VisualOdometry(scale="platform", speed_mps=0.5)
    vo.on_image(img, 0.1)
    vo.on_image(img + 51, 0.1)
    again = VisualOdometry(scale="platform", speed_mps=0.5)
    again.load_state_dict(vo.state_dict())
    assert again.on_image(img + 153, 0.1) == vo.on_image(img + 153, 0.1)


def test_subpixel_reads_a_turn_of_a_fraction_of_a_column_closer_than_the_whole_columns():
    # 200 columns at 90 degrees (f = 100 px): a turn of 0.024 rad moves the centre by f tan(0.024)
    # = 2.4 columns; whole columns read 2, the refined shift lies between 2 and 2.5 and nearer 2.4
    before, after = _pinhole_view(0.0), _pinhole_view(0.024)
    rates = {}
    for sub in (False, True):
        vo = VisualOdometry(camera_fov_deg=90, rotation="pinhole_centre", subpixel=sub)
        vo.on_image(before, 0.1)
        rates[sub] = vo.on_image(after, 0.1)[1] * 0.1
    assert rates[False] == pytest.approx(math.atan(2 / 100))
    shift = 100 * math.tan(rates[True])
    assert 2.0 < shift <= 2.5 and abs(shift - 2.4) < abs(2.0 - 2.4)


def test_refined_shift_stays_within_half_a_column_and_keeps_the_edge_of_the_search():
    from neoslam_stream.algorithms.ratslam.visual_odometry import refined_shift

    # a V-shaped difference (a ramp shifted by 2.4 columns): the parabola through 1.4, 0.4, 0.6
    # (times the slope) has its vertex at 2 + 0.5 * (1.4 - 0.6) / 1.2 = 2.333
    prev = np.linspace(0.0, 1.0, 101)[:-10]
    cur = np.interp(np.arange(prev.size) - 2.4, np.arange(prev.size), prev)
    assert refined_shift(cur[5:], prev[5:], 2) == pytest.approx(2 + 0.5 * 0.8 / 1.2, abs=1e-6)
    assert refined_shift(cur, prev, 39) == 39.0  # the last offset tried has no neighbour beyond it


def _centre_moved(width: int = 210, shift: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Two frames whose sides are the same and whose middle third moved by ``shift`` columns: what
    driving at a wall of repeated texture looks like to the centre (it matches a period away)."""
    rng = np.random.default_rng(3)
    row = rng.integers(30, 220, width + 2 * shift).astype(np.uint8)
    a = row[shift:shift + width].copy()
    b = a.copy()
    third = width // 3
    b[third:2 * third] = row[third:2 * third]  # the centre's content, shifted by `shift` columns
    return np.tile(a[None], (10, 1)), np.tile(b[None], (10, 1))


def test_rotation_check_refuses_a_centre_shift_the_whole_window_does_not_bear_out():
    before, after = _centre_moved()
    reads = {}
    for check in (False, True):
        vo = VisualOdometry(camera_fov_deg=90, rotation="pinhole_centre", rotation_check=check)
        vo.on_image(before, 0.1)
        reads[check] = vo.on_image(after, 0.1)[1]
    focal = 105 / math.tan(math.radians(45))  # 210 columns at 90 degrees
    assert reads[False] == pytest.approx(math.atan(10 / focal) / 0.1)  # the centre alone: a turn
    assert reads[True] == 0.0  # the sides stayed put: no turn
    # a real turn moves every column: the check keeps it
    vo = VisualOdometry(camera_fov_deg=90, rotation="pinhole_centre", rotation_check=True)
    vo.on_image(_pinhole_view(0.0), 0.1)
    assert vo.on_image(_pinhole_view(0.05), 0.1)[1] == pytest.approx(math.atan(5 / 100) / 0.1)


def test_normal_flow_is_the_difference_over_the_profiles_contrast():
    # a textured row, then every column 25 levels brighter: no turn explains it, the difference is
    # 25/255, the flow that over the mean absolute gradient of the two profiles (alike: the same
    # texture), times vtrans_scaling 10 over camera_hz 10 * dt 0.1
    row = np.random.default_rng(5).integers(0, 200, 90).astype(np.uint8)
    prev = np.tile(row[None], (4, 1))
    contrast = np.abs(np.diff(row / 255.0)).mean()
    reads = {}
    for translation in ("difference", "normal_flow"):
        vo = VisualOdometry(camera_fov_deg=90, rotation="pinhole_centre", translation=translation,
                            vtrans_scaling=10.0)
        vo.on_image(prev, 0.1)
        reads[translation] = vo.on_image(prev + 25, 0.1)[0]
    assert reads["difference"] == pytest.approx(25 / 255 * 10 / (10 * 0.1))
    assert reads["normal_flow"] == pytest.approx(25 / 255 / contrast * 10 / (10 * 0.1))
    # a flat image has no contrast to read motion from: no speed rather than a division by zero
    vo = VisualOdometry(translation="normal_flow")
    vo.on_image(np.full((4, 60), 20, np.uint8), 0.1)
    assert vo.on_image(np.full((4, 60), 40, np.uint8), 0.1)[0] == 0.0


def test_the_typical_speed_keeps_a_fixed_memory_beyond_its_exact_samples(monkeypatch):
    from neoslam_stream.algorithms.ratslam.visual_odometry import TypicalSpeedScale

    monkeypatch.setattr(TypicalSpeedScale, "EXACT", 100)
    raws = np.random.default_rng(4).uniform(1.0, 3.0, 1000)
    s = TypicalSpeedScale(0.3)
    for r in raws[:100]:
        s(r)
    assert s.median == pytest.approx(np.median(raws[:100]))  # exact while few
    out = [s(r) for r in raws[100:]]
    assert s.samples == [] and len(s.histogram) == 1000  # the histogram holds them all
    width = 10 ** (1 / 1000)
    assert np.percentile(raws, 50, method="lower") / width <= s.median <= np.percentile(raws, 50, method="higher") * width
    assert out[-1] == pytest.approx(0.3 * raws[-1] / s.median)
    # the state carries the histogram
    vo = VisualOdometry(scale="platform", speed_mps=0.3)
    vo.speed_scale = s
    again = VisualOdometry(scale="platform", speed_mps=0.3)
    again.load_state_dict(vo.state_dict())
    assert again.speed_scale.median == s.median and len(again.speed_scale.histogram) == 1000
