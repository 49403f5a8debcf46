"""ROS 2 output: our outputs as ROS 2 messages, decoded by a decoder no one here wrote (Foxglove's
mcap-ros2-support, which parses the .msg definitions itself), live on zenoh in both key formats,
and in the run folder's outputs.mcap."""

import json
import math
import threading
import time

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2.decoder import DecoderFactory
from zenoh.ext import Int64, z_deserialize

from neoslam_stream.nodes.recorder import RecorderNode
from neoslam_stream.nodes.ros2_out import TOPICS, Ros2Messages, Ros2OutNode, replay, type_hash
from neoslam_stream.nodes.run_folder import MCAP
from neoslam_stream.nodes.topics import EXPERIENCE_MAP, EXPERIENCE_POSE, VISUAL_TEMPLATE
from neoslam_stream.runtime.bus import open_session, wait_for_peers
from neoslam_stream.runtime.messages import Message
from neoslam_stream.runtime.ports import free_port

#: rmw_zenoh's design document (docs/design.md): demo_nodes_cpp's talker on Jazzy publishes
#: std_msgs/msg/String with this hash (the loop-closure topic's type)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

#: a hand-made walk: frame -> (experience id, x, y, theta). Experiences 0, 1, 2, then back to 0
#: (a loop closure), then 3
WALK = [(0, 0.0, 0.0, 0.0), (0, 0.5, 0.0, 0.1), (1, 1.0, 0.0, 0.2), (1, 1.5, 0.1, 1.0), (2, 1.6, 0.6, 2.0),
        (2, 1.0, 1.0, 3.0), (0, 0.1, 0.1, -2.0), (3, 0.0, -0.5, -1.5)]


def _decoder(conv, msgtype):
    return generate_dynamic(msgtype, conv.msgdef(msgtype))[msgtype]


def _feed(conv):
    outs = []
    for f, (exp, x, y, th) in enumerate(WALK):
        outs += conv.on_template(f, 10.0 + 0.25 * f, 100 + f, f == 6)
        outs += conv.on_pose(f, 10.0 + 0.25 * f, x, y, th, exp)
    return outs + conv.finish()


def _check_pose(pose, x, y, th):
    assert (pose.position.x, pose.position.y, pose.position.z) == pytest.approx((x, y, 0.0))
    q = pose.orientation
    assert (q.x, q.y) == (0.0, 0.0)
    assert math.atan2(2 * q.w * q.z, 1 - 2 * q.z * q.z) == pytest.approx(th)


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_messages_decode_with_foxglove_decoder(distro):
    conv = Ros2Messages(frame_id="map", child_frame_id="base_link", distro=distro, map_period_s=100.0)
    outs = _feed(conv)
    by_topic = {}
    for o in outs:
        by_topic.setdefault(o.topic, []).append(_decoder(conv, o.msgtype)(conv.serialize(o)))
    assert set(by_topic) == {f"/neoslam/{name}" for name, _ in TOPICS.values()}
    odoms, poses = by_topic["/neoslam/odom"], by_topic["/neoslam/pose"]
    assert len(odoms) == len(poses) == len(WALK)
    for f, ((_, x, y, th), od, ps) in enumerate(zip(WALK, odoms, poses, strict=True)):
        t = 10.0 + 0.25 * f
        assert od.header.frame_id == ps.header.frame_id == "map" and od.child_frame_id == "base_link"
        assert od.header.stamp.sec == int(t) and od.header.stamp.nanosec == round((t % 1) * 1e9)
        _check_pose(od.pose.pose, x, y, th)
        _check_pose(ps.pose, x, y, th)
    assert [m.data for m in by_topic["/neoslam/template_id"]] == [100 + f for f in range(len(WALK))]
    (event,) = by_topic["/neoslam/loop_closure"]
    assert json.loads(event.data) == {"frame": 6, "stamp": 11.5, "template_id": 106, "exp_id": 2}
    # path and map: once at the first pose (map_period_s is long), and once at the end
    paths, arrays = by_topic["/neoslam/path"], by_topic["/neoslam/map_markers"]
    assert [len(p.poses) for p in paths] == [1, len(WALK)]
    for ps, (_, x, y, th) in zip(paths[-1].poses, WALK, strict=True):
        _check_pose(ps.pose, x, y, th)
    markers = {m.ns: m for m in arrays[-1].markers}
    first_seen = {0: (0.0, 0.0), 1: (1.0, 0.0), 2: (1.6, 0.6), 3: (0.0, -0.5)}
    assert [(p.x, p.y) for p in markers["experiences"].points] == [first_seen[i] for i in range(4)]
    assert markers["experiences"].type == 7 and markers["links"].type == markers["loop_closures"].type == 5
    pairs = lambda m: [((m.points[i].x, m.points[i].y), (m.points[i + 1].x, m.points[i + 1].y))  # noqa: E731
                       for i in range(0, len(m.points), 2)]
    # links 0->1, 1->2, 0->3 go forward; 2->0 goes back to an older experience: a loop closure
    assert pairs(markers["links"]) == [(first_seen[0], first_seen[1]), (first_seen[1], first_seen[2]),
                                       (first_seen[0], first_seen[3])]
    assert pairs(markers["loop_closures"]) == [(first_seen[2], first_seen[0])]
    # the map at the end of the run replaces the drawn one
    export = {"nodes": [{"id": 0, "x": 0.05, "y": 0.0}, {"id": 1, "x": 1.0, "y": 0.1}],
              "links": [{"from": 0, "to": 1}, {"from": 1, "to": 0}]}
    (path, arr) = conv.on_map(12.0, export)
    arr = _decoder(conv, arr.msgtype)(conv.serialize(arr))
    markers = {m.ns: m for m in arr.markers}
    assert [(p.x, p.y) for p in markers["experiences"].points] == [(0.05, 0.0), (1.0, 0.1)]
    assert len(markers["loop_closures"].points) == 2
    assert conv.on_map(12.0, {"nodes": [1]}) == []  # not a map: the drawn map stays, nothing sent


def test_a_long_path_is_thinned_evenly_and_keeps_its_last_pose():
    conv = Ros2Messages(map_period_s=1e9, path_max_poses=4)
    for f in range(8):
        conv.on_pose(f, float(f), float(f), 0.0, 0.0, 0)
    (path, _) = conv.finish()
    # poses 0..3 kept; the 5th makes 5 > 4: every 2nd is kept (0, 2, 4), then 6; and the last, 7
    assert [p.pose.position.x for p in path.msg.poses] == [0.0, 2.0, 4.0, 6.0, 7.0]


def test_type_hashes_are_the_ros_ones():
    assert type_hash("std_msgs/msg/String") == STRING_HASH
    assert type_hash("std_msgs/msg/String", "humble") == "TypeHashNotSupported"


def _collector(session, key):
    got = []
    lock = threading.Lock()

    def on(sample):
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes(),
                        None if sample.attachment is None else sample.attachment.to_bytes()))

    return got, session.declare_subscriber(key, on)


def test_live_output_in_both_key_formats_on_zenoh():
    ep = f"tcp/127.0.0.1:{free_port()}"
    pub_session = open_session(listen=[ep])
    viewer = open_session(connect=[ep])
    assert wait_for_peers(viewer, 1, 10.0)
    bridged, s1 = _collector(viewer, "neoslam/**")
    rmw, s2 = _collector(viewer, "4/neoslam/**")
    time.sleep(0.5)
    node = Ros2OutNode(format="both", domain_id=4, map_period_s=100.0)
    node.bind_session(pub_session)
    time.sleep(0.3)
    for f, (exp, x, y, th) in enumerate(WALK):
        t = 10.0 + 0.25 * f
        node.process(VISUAL_TEMPLATE, Message(VISUAL_TEMPLATE, f, t, {"id": 100 + f, "is_loop_closure": f == 6}))
        node.process(EXPERIENCE_POSE, Message(EXPERIENCE_POSE, f, t, {"pose": np.array([x, y, th]), "exp_id": exp}))
    node.process(EXPERIENCE_MAP, Message(EXPERIENCE_MAP, 7, 11.75, {
        "nodes": np.array([[0, 0.05, 0.0, 0.0, 10.0], [1, 1.0, 0.1, 0.0, 10.5]]), "links": np.array([[0, 1]])}))
    node.flush()
    # rmw_zenoh's liveliness tokens: `ros2 topic list` finds the publishers
    tokens = [str(r.ok.key_expr) for r in viewer.liveliness().get("@ros2_lv/4/**", timeout=2.0) if r.ok]
    time.sleep(0.5)
    for s in (s1, s2):
        s.undeclare()
    node.close()
    viewer.close()
    pub_session.close()
    conv = node.conv
    odom_type = "nav_msgs/msg/Odometry"
    # bridge keys: the topic name without its leading slash, no attachment
    odoms = [_decoder(conv, odom_type)(p) for k, p, a in bridged if k == "neoslam/odom"]
    assert len(odoms) == len(WALK) and all(a is None for _, _, a in bridged)
    for od, (_, x, y, th) in zip(odoms, WALK, strict=True):
        _check_pose(od.pose.pose, x, y, th)
    # rmw keys: <domain>/<topic>/<DDS type>/<hash>, with attachments numbered 1, 2... per publisher
    rmw_keys = {k for k, _, _ in rmw}
    assert f"4/neoslam/loop_closure/std_msgs::msg::dds_::String_/{STRING_HASH}" in rmw_keys
    assert f"4/neoslam/odom/nav_msgs::msg::dds_::Odometry_/{type_hash(odom_type)}" in rmw_keys
    seqs = {}
    for k, _p, a in rmw:
        seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(a))  # zenoh's own deserialiser
        assert len(gid) == 16 and abs(stamp - time.time_ns()) < 120e9
        seqs.setdefault(k, []).append(seq)
    assert all(s == list(range(1, len(s) + 1)) for s in seqs.values())
    rmw_odoms = [p for k, p, _ in rmw if k.startswith("4/neoslam/odom/")]
    assert rmw_odoms == [p for k, p, _ in bridged if k == "neoslam/odom"]
    # the last map: the experience map's own (2 nodes), decoded from the rmw key
    arrays = [p for k, p, _ in rmw if k.startswith("4/neoslam/map_markers/")]
    last = _decoder(conv, "visualization_msgs/msg/MarkerArray")(arrays[-1])
    assert [(p.x, p.y) for p in {m.ns: m for m in last.markers}["experiences"].points] == [(0.05, 0.0), (1.0, 0.1)]
    assert any("/MP/%/%/neoslam/%neoslam%odom/nav_msgs::msg::dds_::Odometry_/" in t for t in tokens)
    assert any(t.endswith("/NN/%/%/neoslam") for t in tokens)


def test_recorder_writes_outputs_mcap_readable_by_the_mcap_reader(tmp_path):
    params = {"frame_id": "map", "child_frame_id": "base_link", "prefix": "/neoslam", "distro": "jazzy",
              "map_period_s": 100.0, "marker_scale": 0.1}
    rec = RecorderNode(mcap=params)
    rec.run_dir = str(tmp_path)
    for f, (exp, x, y, th) in enumerate(WALK):
        t = 10.0 + 0.25 * f
        rec.process(VISUAL_TEMPLATE, Message(VISUAL_TEMPLATE, f, t, {"id": 100 + f, "is_loop_closure": f == 6}))
        rec.process(EXPERIENCE_POSE, Message(EXPERIENCE_POSE, f, t, {"pose": np.array([x, y, th]), "exp_id": exp}))
    rec.flush()
    # the rows the file was made of (read before close, which removes the writer's scratch files)
    conv = Ros2Messages(**params)
    rows = rec.folder.mcap_rows()
    rec.close()
    assert not list(tmp_path.glob("*.f64"))
    with open(tmp_path / MCAP, "rb") as fh:
        msgs = list(make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert {s.encoding for s, _, _, _ in msgs} == {"ros2msg"} and {c.message_encoding for _, c, _, _ in msgs} == {"cdr"}
    odoms = [(m, d) for _, c, m, d in msgs if c.topic == "/neoslam/odom"]
    assert len(odoms) == len(WALK)
    for (m, d), (f, (_, x, y, th)) in zip(odoms, enumerate(WALK), strict=True):
        assert m.log_time == round((10.0 + 0.25 * f) * 1e9)
        _check_pose(d.pose.pose, x, y, th)
    # the same messages as the live output gets from the same topics
    expected = list(replay(conv, *rows, None))
    assert [r.template_id for r in rows[0]] == [100 + f for f in range(len(WALK))]
    assert [c.topic for _, c, _, _ in msgs] == [o.topic for o in expected]
    assert [m.data for _, _, m, _ in msgs] == [conv.serialize(o) for o in expected]


def test_a_run_from_an_rmw_zenoh_camera_to_ros2_and_outputs_mcap(tmp_path):
    """ROS 2 both ways in one real run: ``neoslam run --source rmw-zenoh ... --ros2-out both
    --ros2-connect EP``. A test session plays an rmw_zenoh robot (camera and odometry keys with
    attachments, sequence numbers 4 to 6 of the camera never sent) and the ROS 2 side listening on
    EP (a router in real life) gets the poses live; the run folder holds outputs.mcap."""
    import subprocess
    import sys

    from neoslam_stream.sources import cdr
    from neoslam_stream.sources.rmw_zenoh import Attachment, dds_type_name, topic_key
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    ros_ep, cam_ep = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    ros_side = open_session(listen=[ros_ep])
    bridged, s1 = _collector(ros_side, "slam/**")
    rmw, s2 = _collector(ros_side, "0/slam/**")
    run_dir = tmp_path / "run"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("base: none\nros2_out:\n  prefix: /slam\n  map_period_s: 0.5\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "neoslam_stream.cli", "run", "-c", str(cfg), "--pipeline", "ratslam", "--realtime",
         "--no-live", "--source", "rmw-zenoh", "-p", "image_topic=/cam/image_raw", "-p", "odom_topic=/odom",
         "-p", "domain_id=5", "-p", f'listen=["{cam_ep}"]', "-p", "capacity=64", "-p", "timeout_s=3",
         "--ros2-out", "both", "--ros2-connect", ros_ep, "--out", str(run_dir)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    # the robot: a synthetic drive, 43 frames at 10 Hz, each with its odometry just before it
    robot_msgs = Ros2Messages(frame_id="odom", distro="jazzy")  # builds the robot's messages
    ts = robot_msgs.ts
    robot = open_session(connect=[cam_ep])
    img_key = topic_key(5, "/cam/image_raw", dds_type_name("sensor_msgs/msg/Image"),
                        ts.hash_rihs01("sensor_msgs/msg/Image"))
    odom_key = topic_key(5, "/odom", dds_type_name("nav_msgs/msg/Odometry"),
                         ts.hash_rihs01("nav_msgs/msg/Odometry"))
    cam = robot.declare_publisher(img_key)
    odo = robot.declare_publisher(odom_key)
    deadline = time.monotonic() + 240
    while not (cam.matching_status.matching and odo.matching_status.matching):
        assert time.monotonic() < deadline and proc.poll() is None, "the run's source never subscribed"
        time.sleep(0.1)
    time.sleep(0.5)
    T = ts.types
    gid_cam, gid_odo = bytes(range(16)), bytes(range(1, 17))
    for sf in SyntheticWorldSource(frames=43, width=160, height=96):
        t = 50.0 + sf.frame / 10
        v, w, _ = sf.odom
        conv = robot_msgs
        od = conv._odometry(t - 0.001, 0.0, 0.0, 0.0)
        od.twist.twist.linear.x, od.twist.twist.angular.z = float(v), float(w)
        odo.put(cdr.serialize(od, "nav_msgs/msg/Odometry"),
                attachment=Attachment(sf.frame + 1, int(t * 1e9), gid_odo).encode())
        if sf.frame + 1 not in (4, 5, 6):  # lost on the way
            h, wd = sf.image.shape[:2]
            img = T["sensor_msgs/msg/Image"](header=conv._header(t), height=h, width=wd, encoding="rgb8",
                                             is_bigendian=0, step=wd * 3, data=sf.image.reshape(-1))
            cam.put(cdr.serialize(img, "sensor_msgs/msg/Image"),
                    attachment=Attachment(sf.frame + 1, int(t * 1e9), gid_cam).encode())
        time.sleep(0.1)
    out, _ = proc.communicate(timeout=300)
    time.sleep(0.3)
    s1.undeclare()
    s2.undeclare()
    ros_side.close()
    robot.close()
    assert proc.returncode == 0, out
    report = json.loads((run_dir / "report.json").read_text())
    assert report["source"]["lost_before_source"] == 3 and report["source"]["received"] == 40, out[-3000:] + json.dumps(report["source"])
    assert "lost before the source: 3 frames" in out
    rows = [list(map(float, line.split())) for line in (run_dir / "trajectory.tum").read_text().splitlines()]
    assert len(rows) == 40
    conv = Ros2Messages(prefix="/slam")
    dec = _decoder(conv, "nav_msgs/msg/Odometry")
    live = [dec(p) for k, p, _ in bridged if k == "slam/odom"]
    assert len(live) == len(rows)  # loopback, a subscriber that keeps up
    assert len([k for k, _, _ in rmw if k.startswith("0/slam/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_")]) == len(rows)
    for od, r in zip(live, rows, strict=True):
        assert od.header.stamp.sec + od.header.stamp.nanosec * 1e-9 == pytest.approx(r[0], abs=1e-6)
        assert (od.pose.pose.position.x, od.pose.pose.position.y) == pytest.approx((r[1], r[2]), abs=1e-6)
        assert (od.pose.pose.orientation.z, od.pose.pose.orientation.w) == pytest.approx((r[6], r[7]), abs=1e-8)
    # the robot drove about 0.3 m/s for 4.2 s: the map's last pose is that far from the start,
    # so the odometry of the lost frames was not lost
    assert math.hypot(rows[-1][1], rows[-1][2]) == pytest.approx(0.3 * 4.2, rel=0.15)
    assert any(k == "slam/map_markers" for k, _, _ in bridged)
    # outputs.mcap: the same poses, with their schemas, read back by the mcap reader
    with open(run_dir / MCAP, "rb") as fh:
        msgs = list(make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    poses = [d for _, c, _, d in msgs if c.topic == "/slam/pose"]
    assert len(poses) == len(rows)
    for ps, r in zip(poses, rows, strict=True):
        assert (ps.pose.position.x, ps.pose.position.y) == pytest.approx((r[1], r[2]), abs=1e-6)
    markers = [d for _, c, _, d in msgs if c.topic == "/slam/map_markers"]
    n_nodes = len(json.loads((run_dir / "map.json").read_text())["nodes"])
    assert len({m.ns: m for m in markers[-1].markers}["experiences"].points) == n_nodes
