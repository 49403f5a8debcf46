"""Wire codec: round trips, validation, one MessageError per fault, and explicit schema registration."""

import pickle
import subprocess
import sys

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from neoslam_stream.nodes.topics import ALGORITHM_TOPICS
from neoslam_stream.runtime.messages import (
    MAX_MESSAGE_BYTES,
    SCHEMA_VERSION,
    SCHEMAS,
    Field,
    Message,
    MessageError,
    Topic,
    decode,
    encode,
    register_schema,
    register_topics,
    register_unvalidated,
)
from neoslam_stream.runtime.node import Node

# what a process of a run does at its start: the algorithms' topics are validated from here on,
# and the free-form types of these tests are declared as such
register_topics(ALGORITHM_TOPICS)
register_unvalidated("anything")
register_unvalidated("custom")


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


def _raw(mtype, data):
    return msgpack.packb({"v": SCHEMA_VERSION, "type": mtype, "frame": 0, "stamp": 0.0, "trace": [],
                          "data": data}, use_bin_type=True)


def test_a_type_nobody_registered_is_refused_with_a_clear_message():
    with pytest.raises(MessageError, match=r"'never_registered' has no registered schema.*register"):
        decode(_raw("never_registered", {"x": 1}))
    with pytest.raises(MessageError, match="no registered schema"):
        encode(Message("never_registered", 0, 0.0, {"x": 1}))


def test_declaring_a_topic_registers_nothing_registering_it_validates():
    probe = Topic("probe_topic", {"n": Field("int"), "v": Field("float", optional=True, finite=True)})
    assert "probe_topic" not in SCHEMAS
    with pytest.raises(MessageError, match="no registered schema"):
        decode(_raw("probe_topic", {"n": 1}))
    register_topics([probe])
    assert decode(_raw("probe_topic", {"n": 3}))["n"] == 3
    with pytest.raises(MessageError, match=r"probe_topic.n: expected int"):
        decode(_raw("probe_topic", {"n": "3"}))
    with pytest.raises(MessageError, match="required field 'n' missing"):
        decode(_raw("probe_topic", {"v": 1.0}))
    with pytest.raises(MessageError, match="not finite"):
        decode(_raw("probe_topic", {"n": 1, "v": float("nan")}))
    register_topics([probe])  # the same again: fine
    with pytest.raises(ValueError, match="already registered with other fields"):
        register_schema("probe_topic", {"n": Field("str")})


def test_a_free_form_type_is_registered_explicitly():
    register_unvalidated("probe_free")
    assert decode(_raw("probe_free", {"anything": [1, "x"]}))["anything"] == [1, "x"]
    with pytest.raises(MessageError, match="negative"):  # the envelope is still checked
        decode(msgpack.packb({"v": SCHEMA_VERSION, "type": "probe_free", "frame": -1, "stamp": 0.0,
                              "trace": [], "data": {}}, use_bin_type=True))
    with pytest.raises(ValueError, match="already registered"):
        register_schema("probe_free", {"x": Field("int")})


def test_building_a_node_registers_the_topics_it_declares():
    declared = Topic("probe_node_out", {"k": Field("int")})

    class Probe(Node):
        inputs = ("image",)
        outputs = (declared,)

    assert "probe_node_out" not in SCHEMAS
    Probe()
    with pytest.raises(MessageError, match="probe_node_out.k"):
        decode(_raw("probe_node_out", {"k": 1.5}))


def test_a_topic_crosses_a_spawn_with_its_schema():
    sdr = next(t for t in ALGORITHM_TOPICS if t == "sdr")
    back = pickle.loads(pickle.dumps(sdr))
    assert back == "sdr" and isinstance(back, Topic) and back.schema == sdr.schema


def test_importing_the_topics_validates_nothing_in_a_fresh_process():
    # no import side effect: a process that decodes the algorithms' topics must register them
    code = ("import msgpack\n"
            "from neoslam_stream.nodes import topics\n"
            "from neoslam_stream.runtime.messages import MessageError, decode, register_topics\n"
            "raw = msgpack.packb({'v': 1, 'type': 'sdr', 'frame': 0, 'stamp': 0.0, 'trace': [],"
            " 'data': {'cells': [1], 'size': 4}})\n"
            "try:\n    decode(raw)\nexcept MessageError as e:\n    print('refused:', e)\n"
            "register_topics(topics.ALGORITHM_TOPICS)\n"
            "try:\n    decode(raw)\nexcept MessageError as e:\n    print('invalid:', e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         timeout=120).stdout
    assert "refused: message type 'sdr' has no registered schema" in out
    assert "invalid: sdr.cells: expected an array" in out
