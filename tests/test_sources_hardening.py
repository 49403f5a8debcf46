"""Hostile inputs at the sources: special files in an image folder, broken odometry
rows, images whose size header hides after 64 KB, valid but huge images, 16-bit and big-endian
ROS images, and a folder without odometry. Each is counted with its cause and skipped, or
converted, and the rest of the input is read normally."""

from __future__ import annotations

import errno
import json
import math
import os
import struct
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest

from neoslam_stream.runtime.imageinfo import MAX_PIXELS, image_dimensions, too_large
from neoslam_stream.sources import files as files_mod
from neoslam_stream.sources.files import ImageFolderSource
from neoslam_stream.tum import integrate_odometry, read_tum, read_tum_rows


def _png(value: int, size=(8, 10)) -> bytes:
    return cv2.imencode(".png", np.full((*size, 3), value, np.uint8))[1].tobytes()


def _frames(src, timeout: float = 30.0):
    """Every frame of ``src``, read in a thread: a source that blocks (opening a FIFO waits for
    a writer) fails the test instead of hanging it."""
    out: dict = {}

    def read():
        try:
            out["frames"] = list(src)
        except BaseException as exc:  # the test reports it
            out["error"] = exc

    th = threading.Thread(target=read, daemon=True)
    th.start()
    th.join(timeout)
    assert not th.is_alive(), "the source blocked (opened a FIFO?)"
    if "error" in out:
        raise out["error"]
    return out["frames"]


# --- 1. special files in an image folder --------------------------------------------------------

def test_special_files_in_an_image_folder_are_counted_and_skipped(tmp_path):
    img = tmp_path / "images"
    img.mkdir()
    for i in range(4):  # good frames 0000, 0002, 0004, 0006: brightness 10, 20, 30, 40
        (img / f"{2 * i:04d}.png").write_bytes(_png(10 * (i + 1)))
    os.symlink("0001_loop.png", img / "0001_loop.png")  # a symlink to itself: ELOOP
    os.symlink("nowhere.png", img / "0003_dangling.png")
    (img / "0005_x.jpg").mkdir()  # a directory with an image name
    os.mkfifo(img / "0007_y.jpg")  # opening it would wait for a writer forever
    src = ImageFolderSource(str(tmp_path))
    frames = _frames(src)
    # the rest of the folder is read normally, in order, numbered without gaps
    assert [int(f.image.mean()) for f in frames] == [10, 20, 30, 40]
    assert [f.frame for f in frames] == [0, 1, 2, 3]
    causes = src.errors
    assert sum(causes.values()) == 4, causes
    joined = " | ".join(causes)
    for name, reason in (("0001_loop.png", "symbolic links"), ("0003_dangling.png", "dangling"),
                         ("0005_x.jpg", "directory"), ("0007_y.jpg", "FIFO")):
        cause = [c for c in causes if name in c]
        assert len(cause) == 1 and reason in cause[0], (name, joined)
        assert str(img / name) in cause[0]  # the path, so the user finds it


def test_an_unreadable_image_file_is_counted_and_skipped(tmp_path, monkeypatch):
    (tmp_path / "a.png").write_bytes(_png(10))
    (tmp_path / "b.png").write_bytes(_png(20))
    (tmp_path / "c.png").write_bytes(_png(30))
    bad = str(tmp_path / "b.png")
    real_open = os.open

    def deny(path, flags, *args, **kwargs):  # chmod 000 does not stop root: simulate EACCES
        if os.fspath(path) == bad:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), bad)
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(files_mod.os, "open", deny)
    src = ImageFolderSource(str(tmp_path))
    frames = _frames(src)
    assert [int(f.image.mean()) for f in frames] == [10, 30]
    assert len(src.errors) == 1
    (cause,) = src.errors
    assert bad in cause and "Permission denied" in cause


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root reads chmod 000 files; covered by the monkeypatched EACCES test")
def test_a_chmod_000_image_file_is_counted_and_skipped(tmp_path):
    (tmp_path / "a.png").write_bytes(_png(10))
    (tmp_path / "b.png").write_bytes(_png(20))
    os.chmod(tmp_path / "b.png", 0)
    try:
        src = ImageFolderSource(str(tmp_path))
        frames = _frames(src)
    finally:
        os.chmod(tmp_path / "b.png", 0o644)
    assert [int(f.image.mean()) for f in frames] == [10]
    assert "Permission denied" in " ".join(src.errors)


def test_a_skipped_file_keeps_the_odometry_of_its_neighbours(tmp_path):
    """Row i of odometry.tum belongs to file i; a skipped file's motion goes to the next frame."""
    for i in range(4):
        (tmp_path / f"{i}.png").write_bytes(_png(10 * (i + 1)))
    (tmp_path / "1.png").unlink()
    (tmp_path / "1.png").mkdir()
    with open(tmp_path / "odometry.tum", "w") as fh:  # 1 m per row along x, 1 row per second
        for i in range(4):
            fh.write(f"{i}.0 {i}.0 0 0 0 0 0 1\n")
    frames = _frames(ImageFolderSource(str(tmp_path)))
    assert [f.stamp for f in frames] == [0.0, 2.0, 3.0]
    assert frames[1].odom == pytest.approx((1.0, 0.0, 2.0))  # 2 m in 2 s
    assert frames[2].odom == pytest.approx((1.0, 0.0, 1.0))


# --- 2. a folder without odometry ----------------------------------------------------------------

def test_a_folder_without_odometry_gives_none_and_says_so_before_it_is_built(tmp_path):
    for i in range(3):
        (tmp_path / f"{i}.png").write_bytes(_png(10 * (i + 1)))
    # the run learns it before the source is built (and measures visual odometry: test_source_params.py)
    assert ImageFolderSource.gives_odometry(path=str(tmp_path)) is False
    src = ImageFolderSource(str(tmp_path), rate_hz=4.0)
    frames = _frames(src)
    assert [f.odom for f in frames] == [None, None, None] and [f.stamp for f in frames] == [0.0, 0.25, 0.5]
    assert src.info()["odometry"] is False and src.errors == {}


def test_a_run_on_a_folder_without_odometry_completes(tmp_path):
    """The back end waited for odometry that never came: the run stalled 60 s per frame."""
    data = tmp_path / "data"
    data.mkdir()
    rng = np.random.default_rng(0)
    n = 12
    for i in range(n):
        cv2.imwrite(str(data / f"{i:03d}.png"), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    run_dir = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run([sys.executable, "-m", "neoslam_stream.cli", "run", "--pipeline", "ratslam",
                           "--source", "folder", "-p", f"path={data}", "--no-live", "--out", str(run_dir)],
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = (run_dir / "trajectory.tum").read_text().splitlines()
    assert len(rows) == n  # one pose per frame: none waited for odometry
    rep = json.loads((run_dir / "report.json").read_text())
    assert rep["frames_out"] == n


# --- 3. odometry file rows -------------------------------------------------------------------------

def test_dead_reckoning_turns_before_it_advances():
    # hand-worked: 1 m east, then a quarter turn left with 2 m (taken along the new heading, north),
    # then a quarter turn back with 0.5 m east (0.25 m/s for 2 s)
    rows = integrate_odometry([0.0, 1.0, 2.0], [(1.0, 0.0, 1.0), (2.0, math.pi / 2, 1.0), (0.25, -math.pi / 4, 2.0)])
    np.testing.assert_allclose(rows, [[0, 1, 0, 0], [1, 1, 2, math.pi / 2], [2, 1.5, 2, 0]], atol=1e-12)


def test_tum_rows_bom_indented_comments_and_bad_rows_with_line_numbers(tmp_path):
    path = tmp_path / "odometry.tum"
    lines = ["# t x y z qx qy qz qw",
             "0.0 0 0 0 0 0 0 1",
             "   # an indented comment",
             "1.0 1 0 0 0 0 0 1",
             "2.0 2 0 0 0 0",  # a missing column (line 5)
             "3.0 3 0 zero 0 0 0 1",  # not a number (line 6)
             "4.0 4 0 0 0 0 inf 1",  # qz = inf (line 7)
             "5.0 5 nan 0 0 0 0 1",  # NaN (line 8)
             "",
             "6.0 6 0 0 0 0 0 1"]
    path.write_bytes(b"\xef\xbb\xbf" + "\n".join(lines).encode() + b"\n")  # UTF-8 BOM first
    rows, errors = read_tum_rows(path)
    # one row per data line (bad ones as NaN, so that row i still belongs to image i)
    assert rows.shape == (7, 4)
    assert np.isfinite(rows[[0, 1, 6]]).all() and np.isnan(rows[2:6]).all()
    np.testing.assert_allclose(rows[[0, 1, 6], :2], [[0, 0], [1, 1], [6, 6]])
    assert [i for i, _ in errors] == [2, 3, 4, 5]
    for (_, cause), line in zip(errors, (5, 6, 7, 8), strict=True):
        assert f"odometry.tum line {line}" in cause
    assert "8 values" in errors[0][1] and "not a number" in errors[1][1]
    assert "infinite" in errors[2][1] and "NaN" in errors[3][1]
    # read_tum (evaluation, ground truth): the good rows only, nothing raised
    np.testing.assert_allclose(read_tum(path)[:, 0], [0, 1, 6])


def test_bad_odometry_rows_are_source_errors_and_the_run_goes_on(tmp_path):
    for i in range(4):
        (tmp_path / f"{i}.png").write_bytes(_png(10 * (i + 1)))
    (tmp_path / "odometry.tum").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 inf 1\n2 2 0 0 0 0 0 1\n3 3 0\n")
    (tmp_path / "groundtruth.tum").write_text("\ufeff0 0 0 0 0 0 0 1\n  # comment\n1 1 0 0 0 0 0 1\n1.5 x\n"
                                              "3 3 0 0 0 0 0 1\n")
    src = ImageFolderSource(str(tmp_path))
    frames = _frames(src)
    assert len(frames) == 4  # every image is published
    assert [f.odom is not None for f in frames] == [True, False, True, False]
    assert frames[2].odom == pytest.approx((1.0, 0.0, 2.0))  # from row 0 to row 2
    causes = " | ".join(src.errors)
    assert sum(src.errors.values()) == 3, causes
    assert "odometry.tum line 2" in causes and "odometry.tum line 4" in causes
    assert "groundtruth.tum line 4" in causes
    # ground truth interpolated between the good rows around the stamp (the bad row skipped)
    assert frames[2].stamp == 2.0 and frames[2].groundtruth == pytest.approx((2.0, 0.0, 0.0))


# --- 4. image sizes and huge images ------------------------------------------------------------

def _app_segment(n: int) -> bytes:
    return b"\xff\xe1" + struct.pack(">H", n + 2) + bytes(n)


def test_jpeg_size_header_after_64_kb_is_found():
    jpg = cv2.imencode(".jpg", np.zeros((16, 24, 3), np.uint8))[1].tobytes()
    # two 40 KB APP1 segments in front of the frame header: the SOF sits beyond 80 KB
    padded = jpg[:2] + _app_segment(40000) + _app_segment(40000) + jpg[2:]
    assert image_dimensions(padded) == (24, 16)
    assert cv2.imdecode(np.frombuffer(padded, np.uint8), cv2.IMREAD_COLOR).shape == (16, 24, 3)
    # a bomb hiding its header the same way is refused before decoding
    sof = padded.index(b"\xff\xc0")
    bomb = bytearray(padded)
    bomb[sof + 5:sof + 9] = struct.pack(">HH", 60000, 60000)
    assert too_large(bytes(bomb)) == (60000, 60000)
    # garbage bytes between segments (libjpeg skips them) do not hide it either
    sneaky = jpg[:2] + b"\x00\x11garbage" + bytes(bomb[2:])
    assert too_large(sneaky) == (60000, 60000)


def test_other_formats_give_their_size():
    assert image_dimensions(cv2.imencode(".bmp", np.zeros((5, 7, 3), np.uint8))[1].tobytes()) == (7, 5)
    assert image_dimensions(b"P6\n# comment\n7 5\n255\n" + bytes(105)) == (7, 5)
    assert image_dimensions(cv2.imencode(".png", np.zeros((5, 7), np.uint8))[1].tobytes()) == (7, 5)


def _big_scene(w: int, h: int) -> np.ndarray:
    """A cheap synthetic scene: smooth gradients and large blocks (compresses well, resizes
    without aliasing)."""
    x = np.linspace(0, 255, w, dtype=np.float32)
    y = np.linspace(0, 255, h, dtype=np.float32)
    img = np.empty((h, w, 3), np.uint8)
    img[:, :, 0] = x[None, :].astype(np.uint8)
    img[:, :, 1] = y[:, None].astype(np.uint8)
    img[:, :, 2] = 60
    img[h // 4: h // 2, w // 4: w // 2] = (250, 30, 200)
    return img


def test_a_valid_8000x6000_jpeg_is_resized_at_the_source(tmp_path, monkeypatch):
    big = _big_scene(8000, 6000)
    ok, jpg = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    (tmp_path / "0.jpg").write_bytes(jpg.tobytes())
    (tmp_path / "1.png").write_bytes(cv2.imencode(".png", big[:3000, :4000])[1].tobytes())
    flags = []
    real = cv2.imdecode

    def spy(buf, flag):
        flags.append(flag)
        return real(buf, flag)

    monkeypatch.setattr(files_mod.cv2, "imdecode", spy)
    src = ImageFolderSource(str(tmp_path), max_side=1000)
    frames = _frames(src)
    assert src.errors == {}
    # the JPEG was decoded at a reduced scale (never whole), the PNG has no such option
    assert flags[0] == cv2.IMREAD_REDUCED_COLOR_8  # 8000 / 8 = 1000 px: the largest that still fits
    for f, (w, h), ref in ((frames[0], (1000, 750), big), (frames[1], (1000, 750), big[:3000, :4000])):
        assert f.image is not None and f.image.shape == (h, w, 3)
        want = cv2.resize(ref, (w, h), interpolation=cv2.INTER_AREA)[:, :, ::-1]  # RGB
        assert np.abs(f.image.astype(int) - want.astype(int)).mean() < 4.0
    # the default limit is 1920 px on the long side
    assert max(_frames(ImageFolderSource(str(tmp_path)))[0].image.shape) == 1920


def test_decompression_bombs_stay_refused_with_their_cause(tmp_path):
    ihdr = struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0)
    import zlib

    png = (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr
           + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr)) + b"IEND")
    (tmp_path / "0.png").write_bytes(png)
    (tmp_path / "1.png").write_bytes(_png(50))
    frames = _frames(ImageFolderSource(str(tmp_path)))
    # passed on undecoded: stage A refuses it with "beyond the limit" (tests/test_reliability.py)
    assert frames[0].image is None and frames[0].compressed == png
    assert too_large(png) == (60000, 60000) and 60000 * 60000 > MAX_PIXELS
    assert int(frames[1].image.mean()) == 50


# --- 5. 16-bit and big-endian ROS images ----------------------------------------------------------

def _stretch(v: np.ndarray) -> np.ndarray:
    """The documented conversion: the frame's own range [min, max] mapped linearly onto 0..255."""
    lo, hi = float(v.min()), float(v.max())
    if hi <= lo:
        return np.zeros(v.shape, np.uint8)
    return np.round((v.astype(np.float64) - lo) * 255.0 / (hi - lo)).astype(np.uint8)


#: encoding, channels, the 8-bit encoding it becomes (alpha is dropped, channel order kept)
CASES = [("mono16", 1, "mono8"), ("16UC1", 1, "mono8"), ("rgb16", 3, "rgb8"), ("bgr16", 3, "bgr8"),
         ("rgba16", 4, "rgb8"), ("bgra16", 4, "bgr8")]


def _sixteen(rng, h, w, ch):
    v = rng.integers(1000, 5000, (h, w, ch) if ch > 1 else (h, w)).astype(np.uint16)  # a 12-bit sensor
    return v


def _expected(v, ch, enc8):
    return _stretch(v if ch == 1 else v[:, :, :3]), enc8


def _image_msg(ts, t, v, enc, big_endian, pad=4):
    T = ts.types
    h, w = v.shape[:2]
    ch = 1 if v.ndim == 2 else v.shape[2]
    row = v.reshape(h, w * ch).astype(">u2" if big_endian else "<u2").view(np.uint8)
    step = w * ch * 2 + pad
    data = np.zeros((h, step), np.uint8)
    data[:, : w * ch * 2] = row
    stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=0)
    return T["sensor_msgs/msg/Image"](header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam"),
                                      height=h, width=w, encoding=enc, is_bigendian=int(big_endian),
                                      step=step, data=data.reshape(-1))


def test_16_bit_and_big_endian_images_in_a_bag_are_converted(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from neoslam_stream.sources.bag import BagSource

    ts = get_typestore(Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(3)
    path = tmp_path / "bag16"
    expected = []
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as wr:
        c = wr.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        k = 0
        for enc, ch, enc8 in CASES:
            for big in (False, True):
                v = _sixteen(rng, 5, 6, ch)
                wr.write(c, (k + 1) * 10**9, ts.serialize_cdr(_image_msg(ts, k + 1, v, enc, big),
                                                             "sensor_msgs/msg/Image"))
                expected.append(_expected(v, ch, enc8))
                k += 1
        # one unsupported encoding among them: counted and skipped, the replay goes on
        bad = ts.types["sensor_msgs/msg/Image"](
            header=ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=k + 1,
                                                                                                nanosec=0),
                                                   frame_id="cam"),
            height=2, width=2, encoding="yuv422", is_bigendian=0, step=4, data=np.zeros(8, np.uint8))
        wr.write(c, (k + 1) * 10**9, ts.serialize_cdr(bad, "sensor_msgs/msg/Image"))
        v = _sixteen(rng, 5, 6, 1)
        wr.write(c, (k + 2) * 10**9, ts.serialize_cdr(_image_msg(ts, k + 2, v, "mono16", False),
                                                      "sensor_msgs/msg/Image"))
        expected.append(_expected(v, 1, "mono8"))
    src = BagSource(str(next(path.glob("*.mcap"))), image_topic="/cam")
    frames = _frames(src)
    assert len(frames) == len(expected)
    assert [f.frame for f in frames] == list(range(len(expected)))
    for f, (img, enc) in zip(frames, expected, strict=True):
        assert f.encoding == enc and f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, img)
    (cause,) = src.errors
    assert "yuv422" in cause and "not supported" in cause


def test_16_bit_and_big_endian_images_through_the_cdr_parser():
    from rosbags.typesys import Stores, get_typestore

    from neoslam_stream.sources.cdr import parse_image

    ts = get_typestore(Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(4)
    for enc, ch, enc8 in CASES:
        for big in (False, True):
            v = _sixteen(rng, 4, 7, ch)
            payload = bytes(ts.serialize_cdr(_image_msg(ts, 1, v, enc, big), "sensor_msgs/msg/Image"))
            m = parse_image(payload)
            img, want_enc = _expected(v, ch, enc8)
            assert m["encoding"] == want_enc, enc
            np.testing.assert_array_equal(m["image"], img)
    # a constant frame has no range: black, not a division by zero
    flat = np.full((3, 3), 777, np.uint16)
    m = parse_image(bytes(ts.serialize_cdr(_image_msg(ts, 1, flat, "mono16", False), "sensor_msgs/msg/Image")))
    assert m["image"].max() == 0
    assert math.isfinite(float(m["image"].mean()))


def test_large_raw_and_compressed_frames_in_a_bag_are_resized(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from neoslam_stream.sources.bag import BagSource

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    wide = _big_scene(4000, 300)
    small = _big_scene(64, 48)
    path = tmp_path / "big"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as wr:
        ci = wr.add_connection("/cam/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        for k, img in enumerate((wide, small)):
            hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=k + 1, nanosec=0),
                                           frame_id="cam")
            jpg = cv2.imencode(".jpg", img)[1].reshape(-1)
            wr.write(ci, (k + 1) * 10**9, ts.serialize_cdr(
                T["sensor_msgs/msg/CompressedImage"](header=hdr, format="jpeg", data=jpg),
                "sensor_msgs/msg/CompressedImage"))
    frames = _frames(BagSource(str(next(path.glob("*.mcap"))), image_topic="/cam/compressed", max_side=1000))
    # the large one decoded (at 1/4 scale) and resized at the source, the small one passed on as it is
    assert frames[0].image is not None and frames[0].image.shape == (75, 1000, 3)
    want = cv2.resize(wide, (1000, 75), interpolation=cv2.INTER_AREA)[:, :, ::-1]
    assert np.abs(frames[0].image.astype(int) - want.astype(int)).mean() < 4.0
    assert frames[1].image is None and frames[1].compressed[:2] == b"\xff\xd8"
    # a raw frame: resized the same way
    raw = np.ascontiguousarray(wide[:, :, 0])
    path2 = tmp_path / "raw"
    with Writer(path2, version=8, storage_plugin=StoragePlugin.MCAP) as wr:
        c = wr.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
        wr.write(c, 10**9, ts.serialize_cdr(T["sensor_msgs/msg/Image"](
            header=hdr, height=300, width=4000, encoding="mono8", is_bigendian=0, step=4000,
            data=raw.reshape(-1)), "sensor_msgs/msg/Image"))
    (f,) = _frames(BagSource(str(next(path2.glob("*.mcap"))), image_topic="/cam", max_side=1000))
    np.testing.assert_array_equal(f.image, cv2.resize(raw, (1000, 75), interpolation=cv2.INTER_AREA))


def test_visual_odometry_pipelines_do_not_take_the_source_odometry():
    """With ``odometry: visual`` the pipeline makes its own odometry: the source's (a folder's
    zero motion, a bag's odometry topic) is not published, or each frame would have two."""
    from neoslam_stream.config import FullRunConfig
    from neoslam_stream.nodes.pipelines import build_ratslam

    assert build_ratslam(FullRunConfig()).consumed_source_topics == ["image", "odom"]
    assert build_ratslam(FullRunConfig(odometry="visual")).consumed_source_topics == ["image"]
