"""The synthetic world: determinism, loop structure, odometry model, renderer geometry, dataset CLI."""

import math

import numpy as np
import pytest

from neoslam_stream.cli import main
from neoslam_stream.sources.files import ImageFolderSource
from neoslam_stream.sources.synthetic import (
    CAMERA_HEIGHT,
    TEX_PX_PER_M,
    TEX_ROWS,
    WALL_HEIGHT,
    SyntheticWorld,
    SyntheticWorldSource,
)

SMALL = {"width": 64, "height": 48}


def _dead_reckon(odo, start):
    x, y, th = start
    out = []
    for v, w, dt in odo:
        th += w * dt
        x += v * dt * math.cos(th)
        y += v * dt * math.sin(th)
        out.append((x, y))
    return np.array(out)


def _wrap(a):
    return np.remainder(np.asarray(a) + math.pi, 2 * math.pi) - math.pi


def test_same_seed_same_stream_other_seed_other_textures():
    a = list(SyntheticWorldSource(frames=15, seed=3, **SMALL))
    b = list(SyntheticWorldSource(frames=15, seed=3, **SMALL))
    c = list(SyntheticWorldSource(frames=15, seed=4, **SMALL))
    for fa, fb in zip(a, b, strict=True):
        np.testing.assert_array_equal(fa.image, fb.image)
        assert fa.odom == fb.odom and fa.groundtruth == fb.groundtruth
    assert [f.frame for f in a] == list(range(15))
    assert not np.array_equal(a[-1].image, c[-1].image)  # textures come from the seed
    assert a[-1].groundtruth == c[-1].groundtruth  # the floor plan and the route do not


def test_three_laps_revisit_places_in_both_directions():
    src = SyntheticWorldSource(seed=0)
    gt = src.gt
    assert [d for _, _, d in src.laps] == ["cw", "cw", "ccw"]
    (a0, a1, _), (b0, b1, _), (c0, c1, _) = src.laps
    lap1 = gt[a0:a1]
    # the second lap drives exactly the first lap's poses, one lap (> 60 s) later
    np.testing.assert_allclose(gt[b0:b1], lap1 + [0, 0, 2 * math.pi], atol=1e-9)
    assert (b0 - a0) / src.rate_hz > 60
    # the third lap passes every place of the first, facing the other way
    for k in range(c0, c1, 37):
        d = np.linalg.norm(lap1[:, :2] - gt[k, :2], axis=1)
        j = int(np.argmin(d))
        assert d[j] < 0.02
        assert abs(_wrap(gt[k, 2] - lap1[j, 2])) > math.pi - 0.05
    # a 10 m x 8 m world, and the route stays inside it, clear of every wall
    xmin, ymin, xmax, ymax = SyntheticWorld.bounds()
    assert (xmax - xmin, ymax - ymin) == (10.0, 8.0)
    w = SyntheticWorld(**SMALL)
    p = gt[::5, :2]
    for (x0, y0), (x1, y1) in w.segments:
        e = np.array([x1 - x0, y1 - y0])
        t = np.clip(((p - [x0, y0]) @ e) / (e @ e), 0, 1)
        assert np.min(np.linalg.norm(p - ([x0, y0] + t[:, None] * e), axis=1)) > 0.15


def test_route_is_closed_and_smooth_so_it_loops_seamlessly():
    src = SyntheticWorldSource(seed=0)
    gt = src.gt
    closed = np.vstack([gt, gt[:1]])
    step = np.linalg.norm(np.diff(closed[:, :2], axis=0), axis=1)
    turn = np.abs(_wrap(np.diff(closed[:, 2])))
    assert step.max() <= 0.3 / 10 + 1e-9  # speed / rate
    assert turn.max() <= 0.8 / 10 + 1e-9  # the turn rate, also at the U-turns
    assert (step < 1e-12).sum() > 20  # turning on the spot where the direction changes
    # frames beyond one route repeat it
    long = SyntheticWorldSource(frames=src.route_len + 3, **SMALL)
    fr = list(long)
    assert fr[src.route_len].groundtruth == pytest.approx(fr[0].groundtruth)
    endless = SyntheticWorldSource(loop=True, **SMALL)
    assert endless.length is None
    with pytest.raises(ValueError, match="at least one lap"):
        SyntheticWorldSource(laps_cw=0, laps_ccw=0)
    with pytest.raises(ValueError):
        SyntheticWorldSource(lapz=3)


def test_noiseless_odometry_reproduces_ground_truth_and_noise_makes_drift():
    clean = SyntheticWorldSource(odom_scale_bias=1.0, odom_yaw_bias=0.0, odom_noise=0.0, **SMALL)
    n = 2 * clean.route_len  # across the wrap-around too
    path = _dead_reckon(clean.odometry(n), clean.gt[0])
    truth = clean.gt[np.arange(n) % clean.route_len, :2]
    assert np.max(np.linalg.norm(path - truth, axis=1)) < 0.05
    noisy = SyntheticWorldSource(**SMALL)
    odo = noisy.odometry(noisy.route_len)
    moving = clean.odometry(noisy.route_len)[:, 0] > 0.1
    # the speed scale bias (1.03) is there on average, and the yaw drift leaves metres of error
    assert np.mean(odo[moving, 0] / clean.odometry(noisy.route_len)[moving, 0]) == pytest.approx(1.03, abs=0.005)
    drift = np.linalg.norm(_dead_reckon(odo, noisy.gt[0]) - noisy.gt[:, :2], axis=1)
    assert drift[-1] > 1.0
    # the stream's odometry is that model, frame for frame
    fr = list(SyntheticWorldSource(frames=5, **SMALL))
    np.testing.assert_allclose([f.odom for f in fr], odo[:5])
    assert fr[0].odom[2] == 0.0 and fr[1].odom[2] == pytest.approx(0.1)


def test_ray_cast_and_wall_projection_hand_worked():
    w = SyntheticWorld(width=416, height=240)
    # at (1.5, 1.25) looking west: the west wall (x = 0) is 1.5 m ahead on the centre columns
    dist, tid, along = w.cast(1.5, 1.25, math.pi)
    c = [207, 208]
    np.testing.assert_allclose(dist[c], 1.5, atol=1e-9)
    assert set(tid[c].tolist()) == {7}
    np.testing.assert_allclose(along[c], 4 - 1.25, atol=0.01)  # that wall runs from y=4 down to y=0
    # edge columns: rays at +-atan(207.5/208) from the heading. The right one still meets the west
    # wall (at y = 1.25 + 1.5 tan a < 4): perpendicular distance 1.5. The left one turns south and
    # meets the south wall (y = 0) first: perpendicular distance 1.25 / tan a = 1.25 * 208 / 207.5.
    np.testing.assert_allclose(dist[415], 1.5, atol=1e-9)
    np.testing.assert_allclose(dist[0], 1.25 * 208 / 207.5, atol=1e-9)
    assert (tid[415], tid[0]) == (7, 0)
    img = w.render(1.5, 1.25, math.pi)
    f = 208.0  # (width / 2) / tan(45 deg)
    top = 120 - f * (WALL_HEIGHT - CAMERA_HEIGHT) / 1.5  # 36.8
    bottom = 120 + f * CAMERA_HEIGHT / 1.5  # 203.2
    col = img[:, 208].astype(int)
    bg = w.background[:, 0].astype(np.uint8).astype(int)
    np.testing.assert_array_equal(col[: math.floor(top) - 1], bg[: math.floor(top) - 1])
    np.testing.assert_array_equal(col[math.ceil(bottom) + 1:], bg[math.ceil(bottom) + 1:])
    inside = col[math.ceil(top) + 1: math.floor(bottom) - 1]
    assert (np.abs(inside - bg[math.ceil(top) + 1: math.floor(bottom) - 1]).sum(1) > 0).mean() > 0.9


def test_a_repeated_texture_makes_two_places_look_alike():
    w = SyntheticWorld(width=416, height=240)
    # the west wall and the central block's west face share texture 7; seen from 1.5 m at the same
    # position along each wall they look the same (mirrored: the walls run in opposite senses)
    a = w.render(1.5, 2.0, math.pi)
    b = w.render(1.5, 3.5, 0.0)
    other = w.render(8.5, 2.0, 0.0)  # the east wall, another texture, also 1.5 m away
    cols = slice(208 - 100, 208 + 100)
    same = np.mean(a[:, cols] == b[:, cols][:, ::-1])
    diff = np.mean(a[:, cols] == other[:, cols][:, ::-1])
    assert same > 0.9 > 0.5 > diff


def test_dataset_cli_writes_what_the_folder_source_reads_back(tmp_path):
    out = tmp_path / "syn"
    assert main(["dataset", "synthetic", "--out", str(out), "--frames", "12", "--width", "64",
                 "--height", "48", "--seed", "2"]) == 0
    ref = list(SyntheticWorldSource(frames=12, seed=2, **SMALL))
    back = list(ImageFolderSource(str(out)))
    assert len(back) == 12
    for r, b in zip(ref, back, strict=True):
        np.testing.assert_array_equal(r.image, b.image)  # PNG is lossless
        assert b.groundtruth == pytest.approx(r.groundtruth, abs=1e-5)
        assert b.stamp == pytest.approx(r.stamp)
        assert b.odom == pytest.approx(r.odom, abs=1e-4)


def _render_by_definition(w, x: float, y: float, th: float) -> np.ndarray:
    """The frame as the renderer defines it, in whole-array numpy: the wall a column hits spans
    rows top..bottom, its texel times the distance shade there, floor and ceiling elsewhere."""
    dist, _tid, along = w.cast_walls(x, y, th)
    seg = w._hit_wall
    dist = np.maximum(dist, 0.05)
    h2 = w.height / 2
    top = h2 - w.focal * (WALL_HEIGHT - CAMERA_HEIGHT) / dist
    bottom = h2 + w.focal * CAMERA_HEIGHT / dist
    v = (w.rows - top[None]) / (bottom - top)[None]
    inside = (v >= 0) & (v < 1)
    vi = np.clip((v * TEX_ROWS).astype(np.int32), 0, TEX_ROWS - 1)
    ui = np.minimum((along * TEX_PX_PER_M).astype(np.int32), w.atlas.shape[2] - 1)
    cols = w.atlas[seg[None, :], vi, ui[None, :]]
    shade = (1.0 / (1.0 + 0.15 * dist)).astype(np.float32)[None, :, None]
    return np.where(inside[..., None], cols * shade, w.background).astype(np.uint8)


def test_the_compiled_renderer_gives_the_definition_bit_for_bit():
    src = SyntheticWorldSource(seed=3)
    w = src.world
    for i in range(0, src.route_len, 97):  # poses all round the route, near walls and far
        x, y, th = src.gt[i]
        frame = w.render(x, y, th)
        assert frame.dtype == np.uint8 and frame.shape == (w.height, w.width, 3)
        assert np.array_equal(frame, _render_by_definition(w, x, y, th)), i
