"""Bag reader: bags the test writes (ROS 1 .bag, ROS 2 MCAP) with known odometry integrals, and
clear errors on the shared sample bags."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from neoslam_stream.sources.bag import BagSource

BAGS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "rosbag_samples"
needs_bags = pytest.mark.skipif(not BAGS.is_dir(), reason="../shared/data/rosbag_samples absent")

ODOM_T = 1.0 + 0.05 * np.arange(60)  # 20 Hz for 3 s
ODOM_V = 0.1 + 0.01 * np.arange(60)  # accelerating
ODOM_W = 0.3 - 0.01 * np.arange(60)  # turning less and less, then the other way
FRAME_T = 1.013 + 0.2 * np.arange(12)  # 5 Hz, between odometry stamps
GT_T = 1.0 + 0.1 * np.arange(30)  # 10 Hz


def _zoh_integral(a: float, b: float, values: np.ndarray) -> float:
    """Integral over [a, b] of the odometry's piecewise-constant rate (each twist holds until the
    next message): the definition the reader must implement."""
    ends = np.append(ODOM_T[1:], np.inf)
    overlap = np.clip(np.minimum(ends, b) - np.maximum(ODOM_T, a), 0, None)
    return float(overlap @ values)


def _types(store):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(getattr(Stores, store))


def _header(ts, t, **extra):
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id="base", **extra)


def _odom(ts, t, v, w, **hx):
    T = ts.types
    vec = T["geometry_msgs/msg/Vector3"]
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    return T["nav_msgs/msg/Odometry"](
        header=_header(ts, t, **hx), child_frame_id="base",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=vec(x=v, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=w)),
            covariance=np.zeros(36)))


def _pose(ts, t, x, yaw, **hx):
    T = ts.types
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=float(np.sin(yaw / 2)), w=float(np.cos(yaw / 2)))
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=-x, z=0.0), orientation=q)
    return T["geometry_msgs/msg/PoseStamped"](header=_header(ts, t, **hx), pose=pose)


def _check_odometry(frames):
    assert frames[0].odom == (0.0, 0.0, 0.0)
    for i in range(1, len(frames)):
        vtrans, vrot, dt = frames[i].odom
        a, b = FRAME_T[i - 1], FRAME_T[i]
        assert dt == pytest.approx(b - a, abs=1e-9)
        assert vtrans * dt == pytest.approx(_zoh_integral(a, b, ODOM_V), abs=1e-9)
        assert vrot * dt == pytest.approx(_zoh_integral(a, b, ODOM_W), abs=1e-9)
    # summed over frames: the odometry path between the first and the last frame
    total = sum(f.odom[0] * f.odom[2] for f in frames)
    assert total == pytest.approx(_zoh_integral(FRAME_T[0], FRAME_T[-1], ODOM_V), abs=1e-9)


def test_ros1_bag_compressed_images_odometry_and_pose(tmp_path):
    from rosbags.rosbag1 import Writer

    ts = _types("ROS1_NOETIC")
    T = ts.types
    rng = np.random.default_rng(0)
    jpegs = [cv2.imencode(".jpg", rng.integers(0, 256, (16, 20, 3), dtype=np.uint8))[1].tobytes()
             for _ in FRAME_T]
    path = tmp_path / "run.bag"
    msgs = []
    for t, v, w in zip(ODOM_T, ODOM_V, ODOM_W, strict=True):
        msgs.append((t, "/odom", "nav_msgs/msg/Odometry", _odom(ts, t, v, w, seq=0)))
    for j, t in enumerate(GT_T):
        msgs.append((t, "/overhead/pose", "geometry_msgs/msg/PoseStamped", _pose(ts, t, float(j), 0.1 * j, seq=0)))
    for i, t in enumerate(FRAME_T):
        img = T["sensor_msgs/msg/CompressedImage"](header=_header(ts, t, seq=i), format="jpeg",
                                                   data=np.frombuffer(jpegs[i], np.uint8))
        msgs.append((t, "/cam/image/compressed", "sensor_msgs/msg/CompressedImage", img))
    with Writer(path) as w:
        conns = {}
        for topic, typ in {(m[1], m[2]) for m in msgs}:
            conns[topic] = w.add_connection(topic, typ, typestore=ts)
        for t, topic, typ, m in sorted(msgs, key=lambda m: m[0]):
            w.write(conns[topic], int(round(t * 1e9)), ts.serialize_ros1(m, typ))
    src = BagSource(str(path), image_topic="/cam/image/compressed", odom_topic="/odom",
                    groundtruth_topic="/overhead/pose")
    frames = list(src)
    assert src.length == len(frames) == len(FRAME_T)
    assert [f.frame for f in frames] == list(range(len(FRAME_T)))
    assert frames[3].compressed == jpegs[3] and frames[3].format == "jpeg" and frames[3].image is None
    assert frames[5].stamp == pytest.approx(FRAME_T[5])
    _check_odometry(frames)
    # ground truth interpolated at the frame's stamp: pose j at 1 + 0.1 j is (j, -j, 0.1 j), so the
    # frame at 1.013 + 0.2 i sits at j = 2 i + 0.13
    for i in (0, 4, 11):
        j = 2 * i + 0.13
        assert frames[i].groundtruth == pytest.approx((j, -j, 0.1 * j))


def test_mcap_raw_images_with_row_padding(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _types("ROS2_HUMBLE")
    T = ts.types
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 256, (6, 10), dtype=np.uint8) for _ in FRAME_T]
    path = tmp_path / "run_mcap"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        ci = w.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        msgs = [(t, co, _odom(ts, t, v, wz), "nav_msgs/msg/Odometry")
                for t, v, wz in zip(ODOM_T, ODOM_V, ODOM_W, strict=True)]
        for t, im in zip(FRAME_T, imgs, strict=True):
            padded = np.zeros((6, 12), np.uint8)  # step 12 > width 10: the reader must drop the padding
            padded[:, :10] = im
            msgs.append((t, ci, T["sensor_msgs/msg/Image"](header=_header(ts, t), height=6, width=10,
                                                          encoding="mono8", is_bigendian=0, step=12,
                                                          data=padded.reshape(-1)), "sensor_msgs/msg/Image"))
        for t, c, m, typ in sorted(msgs, key=lambda m: m[0]):
            w.write(c, int(round(t * 1e9)), ts.serialize_cdr(m, typ))
    mcap = next(path.glob("*.mcap"))
    frames = list(BagSource(str(mcap), image_topic="/camera/image_raw", odom_topic="/odom"))
    assert len(frames) == len(FRAME_T)
    for f, im in zip(frames, imgs, strict=True):
        assert f.encoding == "mono8"
        np.testing.assert_array_equal(f.image, im)
    _check_odometry(frames)
    # max_frames stops early
    assert len(list(BagSource(str(mcap), image_topic="/camera/image_raw", max_frames=4))) == 4


def test_unsupported_image_encoding_is_a_counted_error(tmp_path):
    from rosbags.rosbag2 import Writer

    ts = _types("ROS2_HUMBLE")
    path = tmp_path / "float_depth"
    with Writer(path, version=8) as w:
        c = w.add_connection("/depth", "sensor_msgs/msg/Image", typestore=ts)
        m = ts.types["sensor_msgs/msg/Image"](header=_header(ts, 1.0), height=2, width=2, encoding="32FC1",
                                              is_bigendian=0, step=8, data=np.zeros(16, np.uint8))
        w.write(c, 10**9, ts.serialize_cdr(m, "sensor_msgs/msg/Image"))
    src = BagSource(str(path), image_topic="/depth")
    assert list(src) == []  # skipped, not fatal (16-bit encodings are converted: test_sources_hardening)
    (cause,) = src.errors
    assert "32FC1" in cause and "not supported" in cause


@needs_bags
def test_wrong_topics_and_types_are_clear_errors():
    with pytest.raises(ValueError, match=r"image topic .*TFMessage.*must be one of"):
        BagSource(str(BAGS / "tf_example_ros2"), image_topic="/tf")
    with pytest.raises(ValueError, match=r"odom topic '/odometry' not in .*'/amcl_pose'"):
        BagSource(str(BAGS / "nav2_turtlebot.mcap"), odom_topic="/odometry")
    with pytest.raises(ValueError, match="name at least one"):
        BagSource(str(BAGS / "nav2_turtlebot.mcap"))
    with pytest.raises(FileNotFoundError):
        BagSource(str(BAGS / "missing.bag"), image_topic="/x")


@needs_bags
def test_ros2_bag_pose_frames_with_gps_ground_truth():
    # OpenRatSLAM2's recorded lake run: experience-map poses as frames, GPS as ground truth
    src = BagSource(str(BAGS / "surveyor_lake_ratslam_output_ros2"),
                    image_topic=None, odom_topic=None, groundtruth_topic="/surveyor/gps_fix", max_frames=50)
    frames = list(src)
    assert len(frames) == 50 and src.length == 50
    stamps = np.array([f.stamp for f in frames])
    assert np.all(np.diff(stamps) >= 0)
    gt = np.array([f.groundtruth for f in frames if f.groundtruth is not None])
    # the lake GPS at ~1 Hz: consecutive fixes of a boat a few metres apart, never a 0/0 jump
    assert np.max(np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1)) < 50


def test_a_ground_truth_topic_the_bag_lacks_is_a_warning_not_a_failure(tmp_path, caplog):
    """A user's own bag with the irat2011 topics but no /overhead/pose: the frames come without
    ground truth, and the source says so once (log and info(), which report.json keeps)."""
    from rosbags.rosbag1 import Writer

    ts = _types("ROS1_NOETIC")
    T = ts.types
    path = tmp_path / "mine.bag"
    with Writer(path) as w:
        co = w.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        ci = w.add_connection("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        msgs = [(t, co, _odom(ts, t, v, wz, seq=0), "nav_msgs/msg/Odometry")
                for t, v, wz in zip(ODOM_T, ODOM_V, ODOM_W, strict=True)]
        jpeg = cv2.imencode(".jpg", np.full((16, 20, 3), 128, np.uint8))[1].ravel()
        msgs += [(t, ci, T["sensor_msgs/msg/CompressedImage"](header=_header(ts, t, seq=0), format="jpeg", data=jpeg),
                  "sensor_msgs/msg/CompressedImage") for t in FRAME_T]
        for t, c, m, typ in sorted(msgs, key=lambda m: m[0]):
            w.write(c, int(round(t * 1e9)), ts.serialize_ros1(m, typ))
    with caplog.at_level("WARNING"):
        src = BagSource(str(path), image_topic="/cam/image/compressed", odom_topic="/odom",
                        groundtruth_topic="/overhead/pose")
        frames = list(src)
    assert len(frames) == len(FRAME_T) and all(f.groundtruth is None for f in frames)
    _check_odometry(frames)  # the rest of the bag is read as before
    (note,) = src.info()["warnings"]
    assert "'/overhead/pose'" in note and "without ground truth" in note and "groundtruth_topic=null" in note
    assert [r.getMessage() for r in caplog.records if "/overhead/pose" in r.getMessage()] == [note]
    assert src.errors == {}  # a warning, not an error
    # named as null on purpose: no warning at all
    quiet = BagSource(str(path), image_topic="/cam/image/compressed", odom_topic="/odom", groundtruth_topic=None)
    assert quiet.info()["warnings"] == [] and len(list(quiet)) == len(FRAME_T)
    # the ground-truth topic as the only one (frames from it) is still an error: nothing to run on
    with pytest.raises(ValueError, match="groundtruth topic '/overhead/pose' not in"):
        BagSource(str(path), groundtruth_topic="/overhead/pose")
