"""An independent Foxglove WebSocket client for the tests: the protocol spoken by hand.

It shares no code with the server (the foxglove-sdk's Rust server) or with neoslam's viewer:
``websockets`` for the WebSocket itself, the protocol's messages as its specification gives them
(JSON ``serverInfo`` / ``advertise`` / ``unadvertise`` / ``status`` from the server, ``subscribe``
from the client, binary Message Data frames: opcode 0x01, uint32 subscription id, uint64 receive
timestamp in ns, little-endian, then the payload), and each payload decoded with the schema its
channel advertised: JSON checked against its JSON schema (types and required keys, checked here),
protobuf parsed by Google's protobuf runtime from the FileDescriptorSet the server sent.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from dataclasses import dataclass, field
from typing import Any

#: the subprotocols offered: the SDK's current name first, the protocol's original name second
#: (the same protocol, renamed; an older server or client speaks the second)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
_DATA = struct.Struct("<BIQ")  # opcode, subscription id, receive timestamp (ns)
_JSON_TYPES = {"integer": int, "number": (int, float), "string": str, "boolean": bool, "object": dict,
               "array": list, "null": type(None)}


class SchemaError(AssertionError):
    """A message that does not fit the schema its channel advertised."""


def check_json(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """``value`` against a JSON schema's ``type``, ``required`` and ``properties`` (what the
    server's schemas use); anything else in the schema is not checked."""
    types = schema.get("type")
    if types is not None:
        names = types if isinstance(types, list) else [types]
        ok = any(isinstance(value, _JSON_TYPES[t]) and not (t in ("integer", "number") and isinstance(value, bool))
                 for t in names)
        if not ok:
            raise SchemaError(f"{where}: {value!r} is not of type {types}")
    if isinstance(value, dict):
        for key in schema.get("required", []):
            if key not in value:
                raise SchemaError(f"{where}: required key {key!r} missing")
        for key, sub in (schema.get("properties") or {}).items():
            if key in value:
                check_json(value[key], sub, f"{where}.{key}")


def protobuf_class(schema_name: str, schema_b64: str) -> Any:
    """The message class of ``schema_name`` built from an advertised FileDescriptorSet."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    while pending:  # dependencies first, whatever order the set lists them in
        added = [f for f in pending if all(d in {g.name for g in fds.file if g not in pending} for d in f.dependency)]
        if not added:
            raise SchemaError(f"{schema_name}: unresolved imports in {[f.name for f in pending]}")
        for f in added:
            pool.Add(f)
            pending.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


@dataclass
class Channel:
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: str
    decode: Any = None


@dataclass
class Received:
    """What a client got: the server's info, its channels by topic, the decoded messages per
    topic as (receive time ns, message), status messages, and the raw frames' count."""

    subprotocol: str = ""
    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, Channel] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=dict)
    status: list[dict[str, Any]] = field(default_factory=list)
    frames: int = 0


def _decoder(ch: Channel) -> Any:
    if ch.encoding == "json":
        if ch.schema_encoding != "jsonschema":
            raise SchemaError(f"{ch.topic}: JSON messages with a {ch.schema_encoding!r} schema")
        schema = json.loads(ch.schema)

        def dec(payload: bytes) -> Any:
            value = json.loads(payload)
            check_json(value, schema, ch.topic)
            return value
        return dec
    if ch.encoding == "protobuf":
        if ch.schema_encoding != "protobuf":
            raise SchemaError(f"{ch.topic}: protobuf messages with a {ch.schema_encoding!r} schema")
        cls = protobuf_class(ch.schema_name, ch.schema)

        def dec_pb(payload: bytes) -> Any:
            from google.protobuf.json_format import MessageToDict

            return MessageToDict(cls.FromString(payload), preserving_proto_field_name=True)
        return dec_pb
    raise SchemaError(f"{ch.topic}: unknown message encoding {ch.encoding!r}")


async def connect(url: str, timeout: float) -> Any:
    """A WebSocket connection to ``url`` with the protocol's subprotocols, retried until ``timeout``."""
    import websockets

    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        try:
            return await websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None)
        except (OSError, websockets.exceptions.InvalidHandshake):
            if loop.time() > deadline:
                raise
            await asyncio.sleep(0.2)


async def collect(url: str, until_s: float, connect_timeout: float = 240.0, on_first: Any = None,
                  publish_attempt: bool = False, stop_when: Any = None) -> Received:
    """Connect, subscribe to every channel as it is advertised, decode everything until the
    server closes the connection, ``stop_when(received)`` holds after a message, or ``until_s``
    seconds after connecting. ``on_first``: called (no arguments) once the first subscription was
    sent; ``publish_attempt``: also try to advertise a client channel and publish on it (a
    read-only server refuses)."""
    import websockets

    got = Received()
    ws = await connect(url, connect_timeout)
    got.subprotocol = ws.subprotocol or ""
    subs: dict[int, Channel] = {}
    next_sub = 1
    loop = asyncio.get_running_loop()
    end = loop.time() + until_s
    try:
        while True:
            left = end - loop.time()
            if left <= 0:
                break
            try:
                raw = await asyncio.wait_for(ws.recv(), left)
            except (asyncio.TimeoutError, websockets.exceptions.ConnectionClosed):
                break
            if isinstance(raw, bytes):
                opcode, sub_id, stamp = _DATA.unpack_from(raw)
                assert opcode == 0x01, f"unexpected binary opcode {opcode}"
                ch = subs[sub_id]
                got.messages.setdefault(ch.topic, []).append((stamp, ch.decode(raw[_DATA.size:])))
                got.frames += 1
                if stop_when is not None and stop_when(got):
                    break
                continue
            msg = json.loads(raw)
            op = msg.get("op")
            if op == "serverInfo":
                got.server_info = msg
            elif op == "status":
                got.status.append(msg)
            elif op == "advertise":
                new = []
                for c in msg["channels"]:
                    ch = Channel(c["id"], c["topic"], c["encoding"], c["schemaName"], c.get("schemaEncoding", ""),
                                 c.get("schema", ""))
                    ch.decode = _decoder(ch)
                    got.channels[ch.topic] = ch
                    subs[next_sub] = ch
                    new.append({"id": next_sub, "channelId": ch.id})
                    next_sub += 1
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                if publish_attempt:
                    publish_attempt = False
                    await ws.send(json.dumps({"op": "advertise", "channels": [
                        {"id": 1, "topic": "/neoslam/control", "encoding": "json", "schemaName": "x"}]}))
                    await ws.send(struct.pack("<BI", 0x01, 1) + b'{"command": "stop"}')
                if on_first is not None:
                    on_first()
                    on_first = None
    finally:
        await ws.close()
    return got


async def stall(url: str, hold_s: float, connect_timeout: float = 240.0) -> int:
    """A client that subscribes to everything advertised first and then reads nothing for
    ``hold_s`` seconds (a viewer that hangs), then leaves; the frames it had read."""
    ws = await connect(url, connect_timeout)
    try:
        while True:
            msg = json.loads(await ws.recv())
            if msg.get("op") == "advertise":
                subs = [{"id": i + 1, "channelId": c["id"]} for i, c in enumerate(msg["channels"])]
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                break
        await asyncio.sleep(hold_s)
    finally:
        await ws.close()
    return 0
