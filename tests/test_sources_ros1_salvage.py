"""ROS 1 bags cut short (a robot that lost power): the bag source reads their chunks in order
without the index and replays the frames before the cut exactly as the whole bag's first frames.

The bags are written here with rosbags' ROS 1 writer (small chunks, as a long recording has many),
uncompressed, bz2 and lz4, with Image or CompressedImage frames, odometry and ground truth."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from neoslam_stream.sources.bag import BagSource

N = 40
FRAME_T = 1.013 + 0.1 * np.arange(N)
ODOM_T = 1.0 + 0.05 * np.arange(2 * N + 2)
TOPICS = {"image_topic": "/cam", "odom_topic": "/odom", "groundtruth_topic": "/pose"}


def _write_bag(path: Path, compression: str | None, image_type: str) -> list[bytes]:
    """The bag, in time order; returns each frame's pixel bytes (random, so each is unique)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types

    def header(t):
        return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](
            sec=int(t), nanosec=int(round((t % 1) * 1e9))), frame_id="base")

    vec, point, quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    rng = np.random.default_rng(3)
    msgs, payloads = [], []
    for k, t in enumerate(ODOM_T):
        pose = T["geometry_msgs/msg/Pose"](position=point(x=0.0, y=0.0, z=0.0), orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0))
        msgs.append((t, 0, "/odom", "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
            header=header(t), child_frame_id="base",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=vec(x=0.2 + 0.01 * k, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.3 - 0.01 * k)),
                covariance=np.zeros(36)))))
    for i, t in enumerate(FRAME_T):
        # ground truth at the frame's own stamp, so a frame's interpolated pose needs no later sample
        msgs.append((t, 0, "/pose", "geometry_msgs/msg/PoseStamped", T["geometry_msgs/msg/PoseStamped"](
            header=header(t), pose=T["geometry_msgs/msg/Pose"](
                position=point(x=0.1 * i, y=-0.05 * i, z=0.0),
                orientation=quat(x=0.0, y=0.0, z=float(np.sin(0.02 * i)), w=float(np.cos(0.02 * i)))))))
        pixels = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
        if image_type == "CompressedImage":
            data = cv2.imencode(".png", pixels)[1].ravel()
            msg = T["sensor_msgs/msg/CompressedImage"](header=header(t), format="png", data=data)
        else:
            data = pixels.reshape(-1)
            msg = T["sensor_msgs/msg/Image"](header=header(t), height=24, width=32, encoding="rgb8",
                                             is_bigendian=0, step=96, data=data)
        payloads.append(bytes(data))
        msgs.append((t, 1, "/cam", f"sensor_msgs/msg/{image_type}", msg))
    w = Writer(path)
    w.chunk_threshold = 8 * 1024  # many chunks, as in a long recording
    if compression:
        w.set_compression(Writer.CompressionFormat[compression.upper()])
    with w:
        conns = {topic: w.add_connection(topic, typ, typestore=ts) for _t, _o, topic, typ, _m in
                 sorted({(0, 0, m[2], m[3], None) for m in msgs})}
        for t, _o, topic, typ, m in sorted(msgs, key=lambda m: (m[0], m[1])):
            w.write(conns[topic], int(round(t * 1e9)), ts.serialize_ros1(m, typ))
    return payloads


def _same_frames(got, full) -> None:
    assert [f.frame for f in got] == list(range(len(got)))
    for a, b in zip(got, full, strict=False):
        assert (a.frame, a.stamp, a.odom, a.groundtruth) == (b.frame, b.stamp, b.odom, b.groundtruth)
        assert a.compressed == b.compressed and a.encoding == b.encoding
        assert (a.image is None) == (b.image is None)
        if a.image is not None:
            np.testing.assert_array_equal(a.image, b.image)


def _whole_before(data: bytes, payloads: list[bytes], end: int) -> int:
    """Frames whose pixels lie wholly in data[:end] (an uncompressed bag stores them as they are,
    last in their message record)."""
    return sum(1 for p in payloads if 0 <= data.find(p) and data.find(p) + len(p) <= end)


@pytest.mark.parametrize("compression,image_type", [(None, "Image"), (None, "CompressedImage"),
                                                    ("bz2", "CompressedImage"), ("lz4", "Image")])
def test_a_bag_cut_at_60_percent_replays_the_first_frames_of_the_whole_bag(tmp_path, compression, image_type,
                                                                           caplog):
    path = tmp_path / "run.bag"
    payloads = _write_bag(path, compression, image_type)
    full_src = BagSource(str(path), **TOPICS)
    full = list(full_src)
    assert len(full) == N and full_src.salvaged is None  # read through the index, as before
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    end = int(len(data) * 0.6)
    cut.write_bytes(data[:end])
    with caplog.at_level("WARNING"):
        src = BagSource(str(cut), **TOPICS)
        got = list(src)
    assert 0 < len(got) < N
    _same_frames(got, full)
    if compression is None:  # every frame wholly before the cut is recovered, none after it
        assert len(got) == _whole_before(data, payloads, end)
    else:  # whole chunks, and of the cut one what decompresses: at least half of what is left
        assert len(got) >= N * 0.6 / 2
    info = src.info()
    n = info["salvaged_messages"]
    assert n >= 2 * len(got)  # frames, their odometry and ground truth
    assert f"truncated: read its first {n} messages chunk by chunk" in info["salvaged"]
    assert src.errors == {info["salvaged"]: 1}  # one source error with its cause
    assert sum(info["salvaged"] in r.getMessage() for r in caplog.records) == 1  # logged once
    assert src.length == len(got)


def test_reading_stops_at_the_first_damaged_record(tmp_path):
    path = tmp_path / "run.bag"
    payloads = _write_bag(path, None, "Image")
    data = bytearray(path.read_bytes())
    # the fourth chunk record gets an op no record has; the file is cut too (no index)
    chunk_ops = [i for i in range(len(data)) if data.startswith(b"op=\x05", i)]
    assert len(chunk_ops) > 6
    bad = chunk_ops[3]
    data[bad + 3] = 0x09
    cut = tmp_path / "damaged.bag"
    cut.write_bytes(bytes(data[: int(len(data) * 0.9)]))
    src = BagSource(str(cut), **TOPICS)
    got = list(src)
    full = list(BagSource(str(path), **TOPICS))
    assert 0 < len(got) == _whole_before(bytes(data), payloads, bad)
    _same_frames(got, full)
    assert "up to a record with the unknown op 0x09" in src.info()["salvaged"]
    assert "truncated" not in src.info()["salvaged"]


def test_a_bag_never_indexed_is_read_to_its_end(tmp_path):
    """A recorder killed before it wrote the index: its header says index_pos 0, and the file ends
    after the last chunk."""
    import struct

    from rosbags.rosbag1 import Writer

    path = tmp_path / "run.bag"
    _write_bag(path, None, "CompressedImage")
    data = path.read_bytes()
    at = data.find(b"index_pos=") + len(b"index_pos=")
    (index_pos,) = struct.unpack("<Q", data[at:at + 8])
    raw = tmp_path / "raw.bag"
    w = Writer(raw)  # the magic and header of a bag opened and never closed
    w.open()
    w.abort()
    head = raw.read_bytes()
    unindexed = tmp_path / "unindexed.bag"
    unindexed.write_bytes(head + data[len(head):index_pos])
    src = BagSource(str(unindexed), **TOPICS)
    got = list(src)
    assert src.salvaged is not None and "truncated" not in src.salvaged
    assert len(got) == N
    _same_frames(got, list(BagSource(str(path), **TOPICS)))


def test_a_file_that_is_no_bag_is_one_clear_error(tmp_path):
    path = tmp_path / "notes.bag"
    path.write_bytes(b"these are not the bytes of a bag\n" * 100)
    with pytest.raises(ValueError, match=r"notes.bag: not a ROS 1 bag \(it would start with #ROSBAG V2.0\)"):
        BagSource(str(path), image_topic="/cam")


@pytest.mark.parametrize("kind", ["bz2", "lz4"])
def test_a_compressed_chunk_cut_short_gives_the_part_that_decodes(kind):
    import bz2

    import lz4.frame

    from neoslam_stream.sources.ros1_salvage import decompress

    rng = np.random.default_rng(0)
    records = rng.integers(0, 8, 600_000, dtype=np.uint8).tobytes()  # compressible, several blocks
    packed = bz2.compress(records, 1) if kind == "bz2" else lz4.frame.compress(
        records, block_size=lz4.frame.BLOCKSIZE_MAX64KB)
    assert decompress(kind, packed, complete=True) == records
    part = decompress(kind, packed[: int(len(packed) * 0.7)], complete=False)
    assert 0 < len(part) < len(records) and records.startswith(part)
