"""Image folder and video sources on files the test writes: time matching, errors, limits."""

import math

import cv2
import numpy as np
import pytest

from neoslam_stream.evaluation import write_tum
from neoslam_stream.sources.files import ImageFolderSource, VideoSource


def _images(folder, n, size=(8, 10)):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((*size, 3), 20 * i, np.uint8))


def test_ground_truth_at_another_rate_is_interpolated_at_the_frame_stamps(tmp_path):
    _images(tmp_path, 5)  # no images/ subfolder: the folder itself
    # images at 2 Hz (stamps from the odometry file, one row per image), driving 1 m/s along x
    write_tum(tmp_path / "odometry.tum", [(0.5 * i, 0.5 * i, 0.0, 0.0) for i in range(5)])
    # ground truth at 3 Hz, turning at 0.3 rad/s through +-pi (the heading wraps)
    gt = [(k / 3, k / 3, 1.0, math.remainder(3.0 + 0.3 * k / 3, 2 * math.pi)) for k in range(8)]
    write_tum(tmp_path / "gt.tum", gt)
    frames = list(ImageFolderSource(str(tmp_path), groundtruth=str(tmp_path / "gt.tum")))
    assert [f.stamp for f in frames] == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    for f in frames[:4]:  # inside the ground truth's span (0 .. 7/3 s)
        x, y, th = f.groundtruth
        assert (x, y) == pytest.approx((f.stamp, 1.0), abs=1e-6)
        assert math.remainder(th - (3.0 + 0.3 * f.stamp), 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    assert frames[1].odom == pytest.approx((1.0, 0.0, 0.5))
    assert int(frames[3].image.mean()) == 60


def test_ground_truth_far_outside_its_span_is_none_and_bad_files_pass_through(tmp_path):
    _images(tmp_path / "images", 3)
    (tmp_path / "images" / "0003.png").write_bytes(b"not a png")  # the stage will report it
    write_tum(tmp_path / "groundtruth.tum", [(100.0, 1.0, 2.0, 0.0), (101.0, 2.0, 2.0, 0.0)])
    src = ImageFolderSource(str(tmp_path), rate_hz=4.0)
    frames = list(src)
    assert src.length == 4 and [f.stamp for f in frames] == [0.0, 0.25, 0.5, 0.75]
    assert all(f.groundtruth is None for f in frames)  # 99 s before the first sample
    assert frames[3].image is None and frames[3].compressed == b"not a png"
    # no odometry file: no odometry, and the source says so before it is built (the run then
    # measures visual odometry: test_source_params.py)
    assert all(f.odom is None for f in frames)
    assert not ImageFolderSource.gives_odometry(path=str(tmp_path))
    assert len(list(ImageFolderSource(str(tmp_path), max_frames=2))) == 2
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no images"):
        ImageFolderSource(str(tmp_path / "empty"))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        ImageFolderSource(str(tmp_path / "nowhere"))


def test_video_limits_and_errors(tmp_path):
    path = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 8.0, (16, 12))
    for i in range(10):
        vw.write(np.full((12, 16, 3), (i * 20, 0, 255 - i * 20), np.uint8))  # BGR
    vw.release()
    src = VideoSource(str(path), max_frames=4)
    frames = list(src)
    assert src.length == 4 and len(frames) == 4 and src.rate_hz == pytest.approx(8.0)
    b, _, r = frames[2].image.reshape(-1, 3).mean(0)[::-1]  # frames are RGB: reverse to read B, G, R
    assert abs(b - 40) < 6 and abs(r - 215) < 6
    assert VideoSource(str(path), rate_hz=2.0).rate_hz == 2.0
    (tmp_path / "x.avi").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="cannot open"):
        VideoSource(str(tmp_path / "x.avi"))
    with pytest.raises(FileNotFoundError):
        VideoSource(str(tmp_path / "none.avi"))


def test_an_odometry_row_with_the_previous_stamp_is_refused_with_its_cause(tmp_path, caplog):
    """Two rows with one stamp would mean motion in no time (dt = 0): the second is refused,
    counted once and logged once with its cause; its image is still published, without motion."""
    _images(tmp_path / "images", 4)
    (tmp_path / "odometry.tum").write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n"
                                           "0.2 2 0 0 0 0 0 1\n")
    with caplog.at_level("WARNING"):
        src = ImageFolderSource(str(tmp_path))
        frames = list(src)
    assert len(frames) == 4
    assert [f.odom is None for f in frames] == [False, False, True, False]
    assert all(f.odom[2] > 0 for f in frames[1:] if f.odom is not None)  # no motion in zero time
    assert frames[3].odom == pytest.approx((10.0, 0.0, 0.1))  # from row 1 to row 3
    assert list(src.errors.values()) == [1]
    cause = next(iter(src.errors))
    assert "odometry row 2" in cause and "is not after the previous" in cause
    assert sum(cause in r.getMessage() for r in caplog.records) == 1


def test_images_beyond_a_short_odometry_file_are_counted(tmp_path):
    """An odometry file with fewer rows than images: the images beyond it have no motion, said
    once with its cause and counted per image (they used to pass silently)."""
    _images(tmp_path / "images", 5)
    (tmp_path / "odometry.tum").write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.2 2 0 0 0 0 0 1\n")
    src = ImageFolderSource(str(tmp_path))
    frames = list(src)
    assert [f.odom is None for f in frames] == [False, False, False, True, True]
    assert list(src.errors.values()) == [2] and "3 rows for 5 images" in next(iter(src.errors))
