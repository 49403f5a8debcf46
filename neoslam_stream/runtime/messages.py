"""Message types and the msgpack wire codec.

Every message on the bus is a msgpack map::

    {"v": SCHEMA_VERSION, "type": <str>, "frame": <int>, "stamp": <float>,
     "trace": [[stage, received, started, finished], ...], "data": {...}}

``frame`` is the source's sequence number (one camera frame end to end), ``stamp`` the source time
in seconds, ``trace`` the per-stage times (``received`` when the worker took the message, ``started``
/ ``finished`` bracket the service time tau_i). numpy arrays travel as ext type :data:`NDARRAY_EXT`
(dtype, shape, raw little-endian bytes; decoded as read-only views, no copy); nothing is pickled.

Decoding validates the envelope, size limits, dtypes, shapes and the ``data`` fields of the type's
registered schema, and raises one exception type, :class:`MessageError`, with the cause. The codec
knows only the runtime's own types; every other type must be registered in the process that encodes
or decodes it (:func:`register_topics`; a free-form type explicitly with :func:`register_unvalidated`).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

SCHEMA_VERSION = 1
NDARRAY_EXT = 42
#: Messages larger than this are refused before any parsing (bytes).
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
#: No single array may hold more elements than this.
MAX_ARRAY_ELEMENTS = 16 * 1024 * 1024
MAX_ARRAY_NDIM = 4
#: Frame numbers are int64 end to end (numpy arrays, state files): a larger one is refused.
MAX_FRAME = 2**63 - 1

ALLOWED_DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name).newbyteorder("<") if np.dtype(name).itemsize > 1 else np.dtype(name)
    for name in ("bool", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64",
                 "float16", "float32", "float64")
}


class MessageError(ValueError):
    """A received message is malformed; the text says what is wrong."""


# --------------------------------------------------------------------------- array ext type

_ARR_HEADER = struct.Struct("<B")  # length of the dtype name


def _pack_array(arr: np.ndarray) -> msgpack.ExtType:
    name = arr.dtype.name
    if name not in ALLOWED_DTYPES:
        raise MessageError(f"dtype {arr.dtype} is not allowed on the wire (allowed: {sorted(ALLOWED_DTYPES)})")
    if arr.ndim > MAX_ARRAY_NDIM:
        raise MessageError(f"array has {arr.ndim} dimensions, at most {MAX_ARRAY_NDIM} allowed")
    le = np.ascontiguousarray(arr, dtype=ALLOWED_DTYPES[name])
    dname = name.encode()
    header = _ARR_HEADER.pack(len(dname)) + dname + struct.pack(f"<B{arr.ndim}Q", arr.ndim, *arr.shape)
    return msgpack.ExtType(NDARRAY_EXT, header + le.tobytes())


def _unpack_array(data: bytes | memoryview) -> np.ndarray:
    buf = memoryview(data)
    try:
        (nlen,) = _ARR_HEADER.unpack_from(buf, 0)
        pos = 1
        name = bytes(buf[pos:pos + nlen]).decode("ascii")
        pos += nlen
        (ndim,) = struct.unpack_from("<B", buf, pos)
        pos += 1
        if ndim > MAX_ARRAY_NDIM:
            raise MessageError(f"array has {ndim} dimensions, at most {MAX_ARRAY_NDIM} allowed")
        shape = struct.unpack_from(f"<{ndim}Q", buf, pos)
        pos += 8 * ndim
    except (struct.error, UnicodeDecodeError) as exc:
        raise MessageError(f"truncated or corrupt array header: {exc}") from None
    if name not in ALLOWED_DTYPES:
        raise MessageError(f"array dtype {name!r} is not allowed")
    dtype = ALLOWED_DTYPES[name]
    count = math.prod(shape)
    if count > MAX_ARRAY_ELEMENTS:
        raise MessageError(f"array of {count} elements exceeds the limit of {MAX_ARRAY_ELEMENTS}")
    nbytes = count * dtype.itemsize
    if len(buf) - pos != nbytes:
        raise MessageError(
            f"array {name}{list(shape)} needs {nbytes} bytes, payload has {len(buf) - pos}")
    arr = np.frombuffer(buf, dtype=dtype, count=count, offset=pos).reshape(shape)
    return arr


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise MessageError(f"cannot encode value of type {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code == NDARRAY_EXT:
        return _unpack_array(data)
    raise MessageError(f"unknown msgpack ext type {code}")


# --------------------------------------------------------------------------- schemas

@dataclass(frozen=True)
class Field:
    """One required (or optional) field of a message type's ``data`` map."""

    kind: str  # "int", "float", "bool", "str", "bytes", "array", "map", "list", "any"
    dtypes: tuple[str, ...] = ()  # for arrays: allowed dtype names (empty = any allowed)
    ndim: tuple[int, ...] = ()  # for arrays: allowed ndim values (empty = any)
    shape: tuple[int | None, ...] | None = None  # for arrays: exact shape with None as wildcard
    optional: bool = False
    finite: bool = False  # for floats and float arrays: NaN/inf rejected


class Topic(str):
    """A topic name that carries the schema of its messages' ``data`` map.

    It is a ``str`` (``Topic("sdr", {...}) == "sdr"``), so nodes declare ``inputs``/``outputs``
    with it and the runtime uses it as a plain name. Declaring a topic registers nothing: a process
    registers the topics it handles (:func:`register_topics`; a node's declared topics are
    registered when the node is built, a run's by every process at its start).
    """

    schema: dict[str, Field]

    def __new__(cls, name: str, schema: dict[str, Field]) -> Topic:
        obj = super().__new__(cls, name)
        obj.schema = dict(schema)
        return obj

    def __reduce__(self) -> tuple[Any, ...]:  # crosses a ``spawn`` with its schema
        return (Topic, (str(self), self.schema))


#: Schema of a type registered as free-form: its ``data`` map is not checked.
UNVALIDATED = None


def register_schema(mtype: str, schema: dict[str, Field] | None) -> None:
    """Declare the ``data`` fields of message type ``mtype`` (``None``: free-form, see
    :func:`register_unvalidated`). Registering the same schema again is a no-op; a different one
    for a registered type is a programming error (ValueError)."""
    new = None if schema is None else dict(schema)
    if mtype in SCHEMAS and SCHEMAS[mtype] != new:
        raise ValueError(f"message type {mtype!r} is already registered with other fields")
    SCHEMAS[mtype] = new


def register_unvalidated(mtype: str) -> None:
    """Let messages of type ``mtype`` pass with any ``data`` map (the envelope is still checked)."""
    register_schema(mtype, UNVALIDATED)


def register_topics(topics: Iterable[Topic]) -> None:
    """Register the schema of every topic declaration in ``topics``."""
    for t in topics:
        register_schema(str(t), t.schema)


_POSE3 = Field("array", ("float64", "float32"), (1,), (3,), finite=True)

# The sources' topics (frames, odometry, ground truth) and the runtime's own.
#: A camera frame. Either a raw array (``image``, HxW or HxWxC uint8) or compressed bytes with
#: ``format`` "jpeg"/"png". ``encoding`` follows ROS names: rgb8, bgr8, mono8.
IMAGE = Topic("image", {
    "image": Field("array", ("uint8",), (2, 3), optional=True),
    "compressed": Field("bytes", optional=True),
    "format": Field("str", optional=True),
    "encoding": Field("str", optional=True),
})
#: Odometry: forward speed (m/s) and yaw rate (rad/s) as RatSLAM uses them, over dt seconds since
#: the previous odometry sample; optional integrated pose.
ODOM = Topic("odom", {
    "vtrans": Field("float", finite=True),
    "vrot": Field("float", finite=True),
    "dt": Field("float", finite=True, optional=True),
    "pose": Field("array", ("float64", "float32"), (1,), (3,), optional=True, finite=True),
})
GROUNDTRUTH = Topic("groundtruth", {"pose": _POSE3})
STATS = Topic("stats", {"stage": Field("str")})
#: ``token``: the run's secret (see bus.ControlGate); ``target``: one process, or all when absent
CONTROL = Topic("control", {"command": Field("str"), "token": Field("str", optional=True),
                            "target": Field("str", optional=True)})
#: one log line of a run's process (runlog.py): its level, process, logger name and text
LOG = Topic("log", {"level": Field("str"), "process": Field("str"), "name": Field("str"), "message": Field("str")})
#: the types the codec knows without registration: the sources' and the runtime's own
RUNTIME_TOPICS = (IMAGE, ODOM, GROUNDTRUTH, STATS, CONTROL, LOG)

#: ``data`` schema per registered message type (None: registered as free-form); the runtime's own
#: types from the start, every other one by :func:`register_schema` in the process that needs it
SCHEMAS: dict[str, dict[str, Field] | None] = {str(t): dict(t.schema) for t in RUNTIME_TOPICS}

_PY_KIND = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,),
            "bytes": (bytes, bytearray, memoryview), "map": (dict,), "list": (list, tuple)}


def _check_field(mtype: str, name: str, spec: Field, value: Any) -> None:
    where = f"{mtype}.{name}"
    if spec.kind == "any":
        return
    if spec.kind == "array":
        if not isinstance(value, np.ndarray):
            raise MessageError(f"{where}: expected an array, got {type(value).__name__}")
        if spec.dtypes and value.dtype.name not in spec.dtypes:
            raise MessageError(f"{where}: dtype {value.dtype.name} not in {list(spec.dtypes)}")
        if spec.ndim and value.ndim not in spec.ndim:
            raise MessageError(f"{where}: {value.ndim}-D array, expected ndim in {list(spec.ndim)}")
        if spec.shape is not None:
            if len(spec.shape) != value.ndim or any(
                    s is not None and s != v for s, v in zip(spec.shape, value.shape, strict=False)):
                raise MessageError(f"{where}: shape {value.shape} does not match {spec.shape}")
        if spec.finite and value.dtype.kind == "f" and not np.isfinite(value).all():
            raise MessageError(f"{where}: contains NaN or inf")
        return
    if spec.kind == "int" and isinstance(value, bool):
        raise MessageError(f"{where}: expected int, got bool")
    if not isinstance(value, _PY_KIND[spec.kind]):
        raise MessageError(f"{where}: expected {spec.kind}, got {type(value).__name__}")
    if spec.kind == "float" and spec.finite and not math.isfinite(value):
        raise MessageError(f"{where}: {value} is not finite")


def validate_data(mtype: str, data: dict[str, Any]) -> None:
    """Check ``data`` against the registered schema of ``mtype``; a type never registered in this
    process is refused (MessageError), one registered as free-form passes."""
    base = mtype.split("/")[0] if mtype.startswith("stats") else mtype
    if base not in SCHEMAS:
        raise MessageError(f"message type {mtype!r} has no registered schema in this process (register "
                           f"its Topic with register_topics, or a free-form type with register_unvalidated)")
    schema = SCHEMAS[base]
    if schema is None:
        return
    for name, spec in schema.items():
        if name not in data:
            if not spec.optional:
                raise MessageError(f"{mtype}: required field {name!r} missing")
            continue
        _check_field(mtype, name, spec, data[name])
    if mtype == "image" and "image" not in data and "compressed" not in data:
        raise MessageError("image: needs either 'image' (raw array) or 'compressed' (bytes)")


# --------------------------------------------------------------------------- message

TraceEntry = tuple[str, float, float, float]


@dataclass
class Message:
    """One message on the bus. ``data`` fields per type: the registered :data:`SCHEMAS`."""

    type: str
    frame: int
    stamp: float
    data: dict[str, Any] = field(default_factory=dict)
    trace: list[TraceEntry] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.type = str(self.type)  # a Topic declaration is a str subclass; the wire wants a str

    def derive(self, mtype: str, data: dict[str, Any]) -> Message:
        """A downstream message for the same camera frame: same frame, stamp and trace so far."""
        return Message(mtype, self.frame, self.stamp, data, list(self.trace))

    def __getitem__(self, key: str) -> Any:
        return self.data[key]


def encode(msg: Message, validate: bool = True) -> bytes:
    """Serialise a message to bytes (msgpack); arrays become little-endian ext payloads."""
    if validate:
        validate_data(msg.type, msg.data)
        if not 0 <= int(msg.frame) <= MAX_FRAME:
            raise MessageError(f"frame number {msg.frame} is outside [0, 2**63 - 1] (int64)")
    body = {"v": SCHEMA_VERSION, "type": msg.type, "frame": int(msg.frame), "stamp": float(msg.stamp),
            "trace": [list(t) for t in msg.trace], "data": msg.data}
    out = msgpack.packb(body, default=_default, use_bin_type=True)
    if len(out) > MAX_MESSAGE_BYTES:
        raise MessageError(f"message of {len(out)} bytes exceeds MAX_MESSAGE_BYTES={MAX_MESSAGE_BYTES}")
    return out


def decode(payload: bytes | bytearray | memoryview, expected_type: str | None = None) -> Message:
    """Parse and validate bytes into a :class:`Message`; raises :class:`MessageError` on any fault.

    The size limit is enforced before parsing. Arrays are read-only views on ``payload``.
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise MessageError(f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > MAX_MESSAGE_BYTES:
        raise MessageError(f"message of {len(payload)} bytes exceeds MAX_MESSAGE_BYTES={MAX_MESSAGE_BYTES}")
    if len(payload) == 0:
        raise MessageError("empty payload")
    try:
        body = msgpack.unpackb(payload, ext_hook=_ext_hook, raw=False, strict_map_key=True)
    except MessageError:
        raise
    except Exception as exc:  # msgpack raises several types (ExtraData, FormatError, ValueError...)
        raise MessageError(f"not a valid msgpack message: {type(exc).__name__}: {exc}") from None
    if not isinstance(body, dict):
        raise MessageError(f"message must be a map, got {type(body).__name__}")
    version = body.get("v")
    if version != SCHEMA_VERSION:
        raise MessageError(f"schema version {version!r} not supported (this build speaks {SCHEMA_VERSION})")
    for key, kinds in (("type", (str,)), ("frame", (int,)), ("stamp", (int, float)),
                       ("trace", (list,)), ("data", (dict,))):
        if key not in body:
            raise MessageError(f"required envelope field {key!r} missing")
        if not isinstance(body[key], kinds) or isinstance(body[key], bool):
            raise MessageError(f"envelope field {key!r} has type {type(body[key]).__name__}")
    mtype = body["type"]
    if expected_type is not None and mtype != expected_type:
        raise MessageError(f"expected a {expected_type!r} message, got {mtype!r}")
    if body["frame"] < 0:
        raise MessageError(f"frame number {body['frame']} is negative")
    if body["frame"] > MAX_FRAME:
        raise MessageError(f"frame number {body['frame']} does not fit in int64")
    if not math.isfinite(body["stamp"]):
        raise MessageError("stamp is not finite")
    trace: list[TraceEntry] = []
    for entry in body["trace"]:
        if (not isinstance(entry, list) or len(entry) != 4 or not isinstance(entry[0], str)
                or not all(isinstance(x, (int, float)) for x in entry[1:])):
            raise MessageError(f"malformed trace entry {entry!r}")
        trace.append((entry[0], float(entry[1]), float(entry[2]), float(entry[3])))
    validate_data(mtype, body["data"])
    return Message(mtype, body["frame"], float(body["stamp"]), body["data"], trace)
