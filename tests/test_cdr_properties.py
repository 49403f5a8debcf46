"""Property-based tests of the zero-copy CDR parser (the zenoh-bridged ROS 2 camera path).

The reference is rosbags' CDR serialiser: any Image it writes (any size, encoding, row padding)
must parse to exactly its pixels; any other byte string must give a CdrError, never another
exception (a malformed sample from the network is counted and skipped, it must not kill the source).
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from neoslam_stream.sources import cdr

CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}


def _image_msg(height, width, encoding, pad, seed, frame_id):
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    ch = CHANNELS[encoding]
    step = width * ch + pad
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, 256, (height, step), dtype=np.uint8)
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=12, nanosec=500_000_000),
                                      frame_id=frame_id)
    msg = T["sensor_msgs/msg/Image"](header=header, height=height, width=width, encoding=encoding,
                                     is_bigendian=0, step=step, data=rows.reshape(-1))
    pixels = rows[:, : width * ch].reshape(height, width, ch) if ch > 1 else rows[:, :width]
    return ts.serialize_cdr(msg, "sensor_msgs/msg/Image"), pixels


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(height=st.integers(1, 12), width=st.integers(1, 12), encoding=st.sampled_from(sorted(CHANNELS)),
       pad=st.integers(0, 7), seed=st.integers(0, 2**16), frame_id=st.text(max_size=9))
# found by this test: the parser stripped every trailing NUL, not just the terminator
@example(height=1, width=1, encoding="bgr8", pad=0, seed=0, frame_id="\x00")
def test_any_image_rosbags_writes_parses_to_its_pixels(height, width, encoding, pad, seed, frame_id):
    raw, pixels = _image_msg(height, width, encoding, pad, seed, frame_id)
    got = cdr.parse_image(raw)
    assert (got["height"], got["width"], got["step"]) == (height, width, width * CHANNELS[encoding] + pad)
    assert got["frame_id"] == frame_id
    assert got["stamp"] == 12.5
    np.testing.assert_array_equal(got["image"], pixels)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=200))
def test_random_bytes_give_cdr_errors_only(data):
    for parse in (cdr.parse_image, lambda b: cdr.decode(b, "nav_msgs/msg/Odometry")):
        try:
            parse(data)
        except cdr.CdrError:
            pass


@settings(max_examples=200, deadline=None)
@given(cut=st.integers(0, 400), flip=st.integers(0, 400), value=st.integers(0, 255))
def test_truncated_or_corrupted_images_give_cdr_errors_only(cut, flip, value):
    raw, _ = _image_msg(5, 7, "rgb8", 3, 1, "cam")
    broken = bytearray(raw[: min(cut, len(raw))] if cut < len(raw) else raw)
    if flip < len(broken):
        broken[flip] = value
    try:
        got = cdr.parse_image(bytes(broken))
    except cdr.CdrError:
        return
    # whatever parsed is self-consistent: the view lies inside the payload
    assert got["image"].size == got["height"] * got["width"] * (1 if got["encoding"] == "mono8" else
                                                                CHANNELS.get(got["encoding"], 3))


def test_unknown_encoding_and_type_are_named_in_the_error():
    raw, _ = _image_msg(2, 2, "rgb8", 0, 0, "cam")
    yuv = bytes(raw).replace(b"rgb8", b"yuv4")  # same length: only the encoding differs
    try:
        cdr.parse_image(yuv)
    except cdr.CdrError as exc:
        assert "yuv4" in str(exc)
    else:
        raise AssertionError("an unsupported encoding was accepted")
    try:
        cdr.decode(raw, "sensor_msgs/msg/PointCloud2")
    except cdr.CdrError as exc:
        assert "PointCloud2" in str(exc)
    else:
        raise AssertionError("an unsupported type was accepted")
