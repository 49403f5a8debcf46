"""Wire codec: round trips, validation, and one MessageError per fault."""

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from neoslam_stream.runtime.messages import (
    MAX_MESSAGE_BYTES,
    SCHEMA_VERSION,
    Message,
    MessageError,
    decode,
    encode,
)


def _body(**over):
    body = {"v": SCHEMA_VERSION, "type": "control", "frame": 0, "stamp": 0.0, "trace": [],
            "data": {"command": "stop"}}
    body.update(over)
    return msgpack.packb(body, use_bin_type=True)


def test_round_trip_keeps_arrays_frame_stamp_trace():
    cells = np.array([3, 17, 65535], dtype=np.uint32)
    msg = Message("sdr", 12, 3.25, {"cells": cells, "size": 65536, "anomaly": 0.5},
                  [("A", 1.0, 1.5, 2.0)])
    out = decode(encode(msg))
    assert out.type == "sdr" and out.frame == 12 and out.stamp == 3.25
    assert out.trace == [("A", 1.0, 1.5, 2.0)]
    np.testing.assert_array_equal(out["cells"], cells)
    assert out["cells"].dtype == np.uint32
    assert not out["cells"].flags.writeable  # a view on the received buffer, not a copy


def test_arrays_are_little_endian_on_the_wire():
    arr = np.array([1, 2], dtype=">u4")  # big-endian input
    raw = encode(Message("bin_features", 0, 0.0, {"bits": arr, "size": 2048}))
    # the raw little-endian bytes of 1 and 2 must appear in the payload
    assert np.array([1, 2], dtype="<u4").tobytes() in raw
    np.testing.assert_array_equal(decode(raw)["bits"], [1, 2])


def test_image_shapes_and_dtype_validated():
    ok = Message("image", 1, 0.1, {"image": np.zeros((4, 5, 3), np.uint8), "encoding": "rgb8"})
    assert decode(encode(ok))["image"].shape == (4, 5, 3)
    with pytest.raises(MessageError, match="dtype"):
        encode(Message("image", 1, 0.1, {"image": np.zeros((4, 5, 3), np.float32)}))
    with pytest.raises(MessageError, match="ndim"):
        encode(Message("image", 1, 0.1, {"image": np.zeros((4,), np.uint8)}))
    with pytest.raises(MessageError, match="either"):
        encode(Message("image", 1, 0.1, {"encoding": "rgb8"}))


def test_nan_rejected_where_finite_required():
    feats = np.zeros(10, np.float32)
    feats[3] = np.nan
    with pytest.raises(MessageError, match="NaN"):
        encode(Message("visual_features", 0, 0.0, {"features": feats}))
    with pytest.raises(MessageError, match="not finite"):
        encode(Message("odom", 0, 0.0, {"vtrans": float("inf"), "vrot": 0.0}))


@pytest.mark.parametrize("payload, cause", [
    (b"", "empty"),
    (b"\xc1\x00", "msgpack"),
    (msgpack.packb([1, 2, 3]), "map"),
    (_body(v=99), "version"),
    (_body(frame=-1), "negative"),
    (_body(frame="3"), "frame"),
    (_body(trace=[["A", 1.0]]), "trace"),
    (_body(data={}), "command"),
    (_body(type="sdr", data={"cells": [1, 2], "size": 4}), "array"),
])
def test_malformed_payloads_raise_one_error_type(payload, cause):
    with pytest.raises(MessageError, match=cause):
        decode(payload)


def test_unknown_dtype_and_truncated_array_rejected():
    good = encode(Message("sdr", 0, 0.0, {"cells": np.arange(8, dtype=np.uint32), "size": 64}))
    with pytest.raises(MessageError):
        decode(good[:-3])  # truncated: the array or the map is short
    # forge an ext payload claiming an object dtype
    forged = msgpack.packb({"v": SCHEMA_VERSION, "type": "sdr", "frame": 0, "stamp": 0.0, "trace": [],
                            "data": {"cells": msgpack.ExtType(42, b"\x06object\x01" + (1).to_bytes(8, "little")),
                                     "size": 1}}, use_bin_type=True)
    with pytest.raises(MessageError, match="not allowed"):
        decode(forged)


def test_size_limit_enforced_before_parsing():
    with pytest.raises(MessageError, match="exceeds"):
        decode(b"\x00" * (MAX_MESSAGE_BYTES + 1))


def test_expected_type_checked():
    with pytest.raises(MessageError, match="expected"):
        decode(_body(), expected_type="image")


def test_no_pickle_for_unknown_objects():
    with pytest.raises(MessageError, match="cannot encode"):
        encode(Message("custom", 0, 0.0, {"x": object()}))


@settings(max_examples=60, deadline=None)
@given(arr=hnp.arrays(dtype=st.sampled_from([np.uint8, np.int16, np.uint32, np.float32, np.float64]),
                      shape=hnp.array_shapes(min_dims=1, max_dims=3, max_side=6)),
       frame=st.integers(0, 2**40), stamp=st.floats(-1e9, 1e9))
def test_property_round_trip(arr, frame, stamp):
    out = decode(encode(Message("anything", frame, stamp, {"a": arr, "s": "x", "n": [1, 2]})))
    assert out.frame == frame and out.stamp == stamp
    np.testing.assert_array_equal(out["a"], arr)
    assert out["a"].dtype == arr.dtype.newbyteorder("<") or arr.dtype.itemsize == 1


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_property_random_bytes_never_crash(data):
    try:
        decode(data)
    except MessageError:
        pass
