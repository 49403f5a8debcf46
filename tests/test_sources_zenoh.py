"""Live zenoh sources through real zenoh sessions, and the CDR parser against rosbags' deserialiser."""

import threading
import time

import cv2
import numpy as np
import pytest

from neoslam_stream.runtime.bus import open_session, wait_for_peers
from neoslam_stream.runtime.messages import Message, encode
from neoslam_stream.runtime.ports import free_port
from neoslam_stream.sources import cdr
from neoslam_stream.sources.zenoh_camera import ZenohImageSource, ZenohRos2CameraSource

pytestmark = pytest.mark.zenoh


def _ts():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _header(ts, t):
    T = ts.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9))),
                                    frame_id="camera")


def _collect(src):
    got = []
    th = threading.Thread(target=lambda: got.extend(src), daemon=True)
    th.start()
    return got, th


def _publisher(ep):
    pub = open_session(connect=[ep])
    assert wait_for_peers(pub, 1, 10.0), "the publisher did not reach the source's session"
    time.sleep(0.5)  # let the subscriber's declaration reach the publisher
    return pub


def test_bridged_compressed_images_on_the_topic_key():
    ts = _ts()
    ep = f"tcp/127.0.0.1:{free_port()}"
    # as the iRat 2011 config names it; the bridge drops the leading slash
    src = ZenohRos2CameraSource("/irat_red/camera/image/compressed", image_type="sensor_msgs/msg/CompressedImage",
                                listen=[ep], timeout_s=3.0, capacity=16)
    assert src.keys == {"image": "irat_red/camera/image/compressed"}
    got, th = _collect(src)
    pub = _publisher(ep)
    rng = np.random.default_rng(4)
    jpegs = [cv2.imencode(".jpg", rng.integers(0, 256, (12, 16, 3), dtype=np.uint8))[1].tobytes() for _ in range(3)]
    for i, jp in enumerate(jpegs):
        m = ts.types["sensor_msgs/msg/CompressedImage"](header=_header(ts, 100.0 + 0.1 * i), format="rgb8; jpeg compressed bgr8",
                                                        data=np.frombuffer(jp, np.uint8))
        pub.put("irat_red/camera/image/compressed", cdr.serialize(m, "sensor_msgs/msg/CompressedImage"))
        time.sleep(0.05)
    # a raw Image on the CompressedImage key: decodes to garbage or fails, never kills the source
    pub.put("irat_red/camera/image/compressed", b"\x00\x01\x00\x00\x01")
    time.sleep(0.3)
    src.close()
    th.join(10)
    pub.close()
    assert [f.frame for f in got] == [0, 1, 2]
    assert [f.compressed for f in got] == jpegs and {f.format for f in got} == {"jpeg"}
    assert got[2].stamp == pytest.approx(100.2)
    assert got[0].odom is None  # no odometry topic configured
    assert sum(src.errors.values()) == 1


def test_native_zenoh_image_source_and_close_ends_a_live_stream():
    ep = f"tcp/127.0.0.1:{free_port()}"
    src = ZenohImageSource("robots/cam0/image", listen=[ep], capacity=16)  # no timeout: stops on close()
    assert src.length is None
    got, th = _collect(src)
    pub = _publisher(ep)
    imgs = [np.full((4, 5, 3), 10 * i, np.uint8) for i in range(3)]
    for i, im in enumerate(imgs):
        pub.put("robots/cam0/image", encode(Message("image", 40 + i, 5.0 + i, {"image": im, "encoding": "rgb8"})))
        time.sleep(0.05)
    pub.put("robots/cam0/image", b"not msgpack")
    time.sleep(0.5)
    assert th.is_alive()  # a live source waits for more
    src.close()
    th.join(10)
    pub.close()
    assert not th.is_alive()
    # our own frame numbers from 0 (the publisher's are its own), the publisher's stamps
    assert [f.frame for f in got] == [0, 1, 2] and [f.stamp for f in got] == [5.0, 6.0, 7.0]
    for f, im in zip(got, imgs, strict=True):
        np.testing.assert_array_equal(f.image, im)
    assert sum(src.errors.values()) == 1


def test_image_parser_is_zero_copy_and_drops_row_padding():
    ts = _ts()
    padded = np.random.default_rng(5).integers(0, 256, (5, 16), dtype=np.uint8)
    m = ts.types["sensor_msgs/msg/Image"](header=_header(ts, 3.5), height=5, width=13, encoding="mono8",
                                          is_bigendian=0, step=16, data=padded.reshape(-1))
    raw = bytearray(cdr.serialize(m, "sensor_msgs/msg/Image"))
    ours = cdr.parse_image(raw)
    ref = ts.deserialize_cdr(bytes(raw), "sensor_msgs/msg/Image")
    np.testing.assert_array_equal(ours["image"], ref.data.reshape(5, 16)[:, :13])
    assert (ours["width"], ours["height"], ours["step"], ours["encoding"]) == (13, 5, 16, "mono8")
    assert ours["frame_id"] == ref.header.frame_id == "camera" and ours["stamp"] == pytest.approx(3.5)
    assert np.shares_memory(ours["image"], np.frombuffer(raw, np.uint8))  # a view, not a copy
    bad = cdr.serialize(ts.types["sensor_msgs/msg/Image"](header=_header(ts, 0.0), height=1, width=1,
                                                          encoding="yuv422", is_bigendian=0, step=2,
                                                          data=np.zeros(2, np.uint8)), "sensor_msgs/msg/Image")
    with pytest.raises(cdr.CdrError, match="yuv422"):
        cdr.parse_image(bad)
    with pytest.raises(cdr.CdrError, match="shorter than its 4-byte header"):
        cdr.parse_image(b"\x00")
    with pytest.raises(cdr.CdrError, match="representation"):
        cdr.parse_image(b"\x00\x07\x00\x00" + bytes(raw[4:]))  # XCDR2, not plain CDR


def test_odometry_and_compressed_image_decode_like_rosbags_and_fail_clearly():
    ts = _ts()
    T = ts.types
    vec = T["geometry_msgs/msg/Vector3"]
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=vec(x=0.25, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=-0.5)),
        covariance=np.arange(36, dtype=np.float64))
    pose = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
        covariance=np.zeros(36))
    odom = T["nav_msgs/msg/Odometry"](header=_header(ts, 7.25), child_frame_id="base", pose=pose, twist=twist)
    raw = cdr.serialize(odom, "nav_msgs/msg/Odometry")
    assert raw[:4] == b"\x00\x01\x00\x00"  # little-endian plain CDR, as the bridge forwards it
    got = cdr.decode(raw, "nav_msgs/msg/Odometry")
    assert (got.twist.twist.linear.x, got.twist.twist.angular.z) == (0.25, -0.5)
    assert got.header.stamp.sec == 7 and got.header.stamp.nanosec == 250_000_000
    np.testing.assert_array_equal(got.twist.covariance, np.arange(36))
    with pytest.raises(cdr.CdrError, match="big-endian"):
        cdr.decode(b"\x00\x00" + raw[2:], "nav_msgs/msg/Odometry")
    with pytest.raises(cdr.CdrError, match="cannot decode nav_msgs/msg/Odometry"):
        cdr.decode(raw[:40], "nav_msgs/msg/Odometry")
    with pytest.raises(cdr.CdrError, match="not supported"):
        cdr.decode(raw, "sensor_msgs/msg/Imu")
    with pytest.raises(ValueError, match="image_type"):
        ZenohRos2CameraSource("/cam", image_type="sensor_msgs/msg/Imu")


def test_bridged_odometry_is_integrated_up_to_each_frame():
    ts = _ts()
    T = ts.types
    vec = T["geometry_msgs/msg/Vector3"]

    def odom(t, v, w):
        return T["nav_msgs/msg/Odometry"](
            header=_header(ts, t), child_frame_id="base",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                                 orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                               w=1.0)),
                covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=vec(x=v, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=w)),
                covariance=np.zeros(36)))

    odom_t = 10.0 + 0.05 * np.arange(24)
    odom_v = 0.2 + 0.02 * np.arange(24)
    frame_t = 10.03 + 0.2 * np.arange(6)
    ep = f"tcp/127.0.0.1:{free_port()}"
    src = ZenohRos2CameraSource("/cam", odom_topic="/odom", listen=[ep], timeout_s=3.0, capacity=16)
    got, th = _collect(src)
    pub = _publisher(ep)
    img = np.zeros((2, 3, 3), np.uint8)
    events = [(t, "odom", v) for t, v in zip(odom_t, odom_v, strict=True)] + [(t, "cam", None) for t in frame_t]
    for t, key, v in sorted(events, key=lambda e: e[0]):
        if key == "odom":
            pub.put("odom", cdr.serialize(odom(t, v, -v), "nav_msgs/msg/Odometry"))
        else:
            m = T["sensor_msgs/msg/Image"](header=_header(ts, t), height=2, width=3, encoding="rgb8",
                                           is_bigendian=0, step=9, data=img.reshape(-1))
            pub.put("cam", cdr.serialize(m, "sensor_msgs/msg/Image"))
        time.sleep(0.01)  # keep the two keys' callbacks in publication order
    time.sleep(0.3)
    src.close()
    th.join(10)
    pub.close()
    assert len(got) == len(frame_t)
    ends = np.append(odom_t[1:], np.inf)
    for i in range(1, len(got)):
        a, b = frame_t[i - 1], frame_t[i]
        # each twist holds until the next message: the integral over the frame interval
        expected = float(np.clip(np.minimum(ends, b) - np.maximum(odom_t, a), 0, None) @ odom_v)
        vtrans, vrot, dt = got[i].odom
        assert dt == pytest.approx(0.2, abs=1e-6)
        assert vtrans * dt == pytest.approx(expected, abs=1e-6) and vrot * dt == pytest.approx(-expected, abs=1e-6)


def test_frames_dropped_by_a_slow_consumer_keep_their_odometry():
    ep = f"tcp/127.0.0.1:{free_port()}"
    src = ZenohImageSource("cam", odom_key="odom", listen=[ep], capacity=2, timeout_s=5.0)
    pub = _publisher(ep)
    img = np.zeros((2, 2, 3), np.uint8)

    def image(k):
        pub.put("cam", encode(Message("image", k, float(k), {"image": img})))
        time.sleep(0.1)

    def odom(v):
        pub.put("odom", encode(Message("odom", 0, 0.0, {"vtrans": v, "vrot": -v, "dt": 1.0})))
        time.sleep(0.1)

    it = iter(src)
    image(0)
    first = next(it)
    assert (first.stamp, first.odom) == (0.0, (0.0, 0.0, 0.0))
    # 1 m, 1 m, 2 m between four images while nobody reads: the ring of 2 drops image 1
    odom(1.0)
    image(1)
    odom(1.0)
    image(2)
    odom(2.0)
    image(3)
    time.sleep(0.3)
    rest = [next(it), next(it)]
    src.close()
    pub.close()
    assert [f.stamp for f in rest] == [2.0, 3.0] and src.dropped == 1
    assert rest[0].odom == pytest.approx((1.0, -1.0, 2.0))  # image 1's metre is not lost
    assert rest[1].odom == pytest.approx((2.0, -2.0, 1.0))
    assert sum(f.odom[0] * f.odom[2] for f in [first, *rest]) == pytest.approx(4.0)
