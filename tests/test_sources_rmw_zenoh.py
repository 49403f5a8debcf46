"""The rmw-zenoh source against a real zenoh publisher that behaves like an rmw_zenoh node: keys
``<domain>/<topic>/<DDS type>/<hash>`` and attachments made with zenoh's own serializer
(zenoh.ext.z_serialize), on loopback."""

import logging
import threading
import time

import numpy as np
import pytest
import zenoh
from zenoh.ext import Int64, z_serialize

from neoslam_stream.runtime.bus import open_session, wait_for_peers
from neoslam_stream.runtime.ports import free_port
from neoslam_stream.sources import cdr, source_factory
from neoslam_stream.sources.rmw_zenoh import (
    Attachment,
    RmwZenohCameraSource,
    SequenceCounter,
    dds_type_name,
    parse_attachment,
    ros_type_name,
    topic_key,
)
from neoslam_stream.sources.zenoh_camera import ZenohRos2CameraSource

pytestmark = pytest.mark.zenoh

#: from rmw_zenoh's design document (docs/design.md, "Topic and Service name mapping"): the key of
#: demo_nodes_cpp's talker on Jazzy
TALKER_KEY = "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def _ts():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _compact(seq, stamp, gid):
    """An attachment as current rmw_zenoh writes it, built with zenoh's serializer."""
    return z_serialize((Int64(seq), Int64(stamp), bytes(gid))).to_bytes()


def _keyvalue(seq, stamp, gid):
    """The key/value attachment of rmw_zenoh's first zenoh-1.0 releases."""
    return z_serialize(("sequence_number", Int64(seq), "source_timestamp", Int64(stamp),
                        "source_gid", bytes(gid))).to_bytes()


def test_keys_and_type_names_as_rmw_zenoh_writes_them():
    ts = _ts()
    key = topic_key(0, "/chatter", dds_type_name("std_msgs/msg/String"), ts.hash_rihs01("std_msgs/msg/String"))
    assert key == TALKER_KEY
    assert topic_key(2, "/robot1/chatter") == "2/robot1/chatter/*/*"
    assert ros_type_name("sensor_msgs::msg::dds_::CompressedImage_") == "sensor_msgs/msg/CompressedImage"
    assert zenoh.KeyExpr(topic_key(0, "/camera/image_raw")).intersects(
        zenoh.KeyExpr("0/camera/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"))
    # the wildcard takes one chunk each: another domain or a deeper topic does not match
    assert not zenoh.KeyExpr(topic_key(0, "/camera")).intersects(
        zenoh.KeyExpr("0/camera/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"))
    assert not zenoh.KeyExpr(topic_key(0, "/camera/image_raw")).intersects(
        zenoh.KeyExpr("1/camera/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"))
    with pytest.raises(ValueError):
        topic_key(0, "/")


def test_attachments_in_both_layouts_and_ours_equals_zenohs():
    gid = bytes(range(100, 116))
    for raw in (_compact(41, 1_700_000_000_123_456_789, gid), _keyvalue(41, 1_700_000_000_123_456_789, gid)):
        att = parse_attachment(raw)
        assert (att.sequence_number, att.source_timestamp, att.gid) == (41, 1_700_000_000_123_456_789, gid)
    assert Attachment(41, 7, gid).encode() == _compact(41, 7, gid)
    for bad in (b"", b"\x01" * 10, _compact(1, 2, gid)[:-3], z_serialize((Int64(1), Int64(2), b"abc")).to_bytes()):
        with pytest.raises(ValueError):
            parse_attachment(bad)


def test_sequence_counter_counts_gaps_per_publisher():
    c = SequenceCounter()
    a, b = b"a" * 16, b"b" * 16
    for seq in (1, 2, 5, 6):  # 3 and 4 lost
        c.add(Attachment(seq, 0, a))
    for seq in (10, 12):  # 11 lost; another publisher's numbers are its own
        c.add(Attachment(seq, 0, b))
    c.add(Attachment(1, 0, a))  # the publisher restarted: no loss, counting starts again
    c.add(Attachment(3, 0, a))  # 2 lost after the restart
    assert c.lost == {a: 3, b: 1} and c.total_lost == 4 and c.restarts == 1


def _image(ts, t, value, w=6, h=4):
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9))),
                                   frame_id="cam")
    px = np.full((h, w, 3), value, np.uint8)
    return T["sensor_msgs/msg/Image"](header=hdr, height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3,
                                      data=px.reshape(-1)), px


def _odom(ts, t, v, w):
    T = ts.types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9))),
                                   frame_id="odom")
    V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    pose = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                         orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)), covariance=np.zeros(36))
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=V3(x=v, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=w)),
        covariance=np.zeros(36))
    return T["nav_msgs/msg/Odometry"](header=hdr, child_frame_id="base", pose=pose, twist=twist)


def test_frames_odometry_and_loss_from_an_rmw_zenoh_publisher():
    ts = _ts()
    ep = f"tcp/127.0.0.1:{free_port()}"
    src = RmwZenohCameraSource(image_topic="/camera/image_raw", odom_topic="/odom", domain_id=3, listen=[ep],
                               timeout_s=3.0, capacity=32)
    assert src.keys["image"] == "3/camera/image_raw/*/*"
    got = []
    th = threading.Thread(target=lambda: got.extend(src), daemon=True)
    th.start()
    pub = open_session(connect=[ep])
    assert wait_for_peers(pub, 1, 10.0)
    time.sleep(0.5)
    img_key = topic_key(3, "/camera/image_raw", dds_type_name("sensor_msgs/msg/Image"),
                        ts.hash_rihs01("sensor_msgs/msg/Image"))
    odom_key = topic_key(3, "/odom", dds_type_name("nav_msgs/msg/Odometry"), ts.hash_rihs01("nav_msgs/msg/Odometry"))
    gid_cam, gid_odom = bytes(range(16)), bytes(range(16, 32))
    sent = []
    # the camera's sequence numbers 1..8 with 4 and 5 lost on the way (never put), at 10 Hz;
    # odometry at 20 Hz, 0.5 m/s and 0.2 rad/s, from before the first frame
    oseq = 0
    for k in range(-1, 15):
        t = 100.0 + 0.05 * k
        oseq += 1
        pub.put(odom_key, cdr.serialize(_odom(ts, t, 0.5, 0.2), "nav_msgs/msg/Odometry"),
                attachment=_compact(oseq, int(t * 1e9), gid_odom))
        if k >= 0 and k % 2 == 0:
            seq = k // 2 + 1
            if seq in (4, 5):
                continue
            msg, px = _image(ts, t, 10 * seq)
            sent.append((seq, t, px))
            pub.put(img_key, cdr.serialize(msg, "sensor_msgs/msg/Image"),
                    attachment=_keyvalue(seq, int(t * 1e9), gid_cam) if seq == 8 else _compact(seq, int(t * 1e9), gid_cam))
        time.sleep(0.02)
    # the same topic in another domain, and a Humble publisher without type hashes in ours
    pub.put(topic_key(0, "/camera/image_raw", dds_type_name("sensor_msgs/msg/Image"), "RIHS01_" + "0" * 64),
            cdr.serialize(_image(ts, 200.0, 1)[0], "sensor_msgs/msg/Image"), attachment=_compact(1, 0, gid_cam))
    humble_gid = bytes(range(32, 48))
    msg, px = _image(ts, 101.0, 99)
    pub.put(topic_key(3, "/camera/image_raw", dds_type_name("sensor_msgs/msg/Image"), "TypeHashNotSupported"),
            cdr.serialize(msg, "sensor_msgs/msg/Image"), attachment=_compact(1, 0, humble_gid))
    sent.append((1, 101.0, px))
    # a type that is no image on the image topic: counted and skipped
    pub.put(topic_key(3, "/camera/image_raw", "std_msgs::msg::dds_::String_", "RIHS01_" + "1" * 64), b"\x00\x01\x00\x00")
    time.sleep(0.5)
    src.close()
    th.join(10)
    pub.close()
    assert [f.frame for f in got] == list(range(len(sent))) == list(range(7))
    for f, (_, t, px) in zip(got, sent, strict=True):
        assert f.stamp == pytest.approx(t) and np.array_equal(f.image, px)
    info = src.info()
    assert info["lost_before_source"] == 2  # sequence numbers 4 and 5
    assert info["publishers"][gid_cam.hex()] == {"received": 6, "lost": 2, "last_sequence_number": 8}
    assert info["publishers"][humble_gid.hex()]["lost"] == 0
    assert info["odom_lost_before_source"] == 0
    assert info["type_hashes"]["sensor_msgs/msg/Image"] == "TypeHashNotSupported"  # the last one seen
    assert sum(src.errors.values()) == 1 and "std_msgs" in next(iter(src.errors))
    # odometry integrated over each camera interval: frames 0 and 1 are 0.1 s apart
    v, w, dt = got[1].odom
    assert dt == pytest.approx(0.1) and v == pytest.approx(0.5) and w == pytest.approx(0.2)
    v, w, dt = got[3].odom  # after the two lost frames: 0.3 s, and the whole motion of it
    assert dt == pytest.approx(0.3) and v * dt == pytest.approx(0.15) and w * dt == pytest.approx(0.06)


def test_silence_is_warned_with_the_key_expressions(caplog):
    caplog.set_level(logging.WARNING, logger="neoslam.sources.rmw_zenoh")
    # timeout_s counts from the first frame: before it, only close() ends the stream
    src = RmwZenohCameraSource(image_topic="/cam", odom_topic="/odom", domain_id=7, warn_after_s=0.3, timeout_s=0.2)
    got = []
    th = threading.Thread(target=lambda: got.extend(src), daemon=True)
    th.start()
    time.sleep(1.0)
    assert th.is_alive()
    src.close()
    th.join(5)
    assert not th.is_alive() and got == []
    text = " ".join(r.getMessage() for r in caplog.records)
    assert "7/cam/*/*" in text and "7/odom/nav_msgs::msg::dds_::Odometry_/*" in text and "7447" in text


def test_bad_parameters_give_one_clear_error():
    with pytest.raises(ValueError, match="namespace") as e:
        RmwZenohCameraSource(image_topic="/cam", namespace=1)
    assert "domain_id" in str(e.value)  # the message lists the parameters there are
    with pytest.raises(ValueError, match="domain_id"):
        RmwZenohCameraSource(image_topic="/cam", domain_id=-1)
    # the bridge source: a number is no namespace (it raised AttributeError before)
    with pytest.raises(ValueError, match="rmw-zenoh"):
        ZenohRos2CameraSource("/cam", namespace=1)
    assert source_factory("rmw-zenoh").endswith(":RmwZenohCameraSource")


def test_the_run_summary_says_how_many_frames_were_lost_before_the_source(capsys):
    from neoslam_stream.cli import print_summary

    print_summary({"run": "r", "stages": {}, "source": {"kind": "rmw-zenoh", "lost_before_source": 2}})
    assert "lost before the source: 2 frames" in capsys.readouterr().out
    print_summary({"run": "r", "stages": {}, "source": {"kind": "synthetic"}})
    assert "lost before the source" not in capsys.readouterr().out
