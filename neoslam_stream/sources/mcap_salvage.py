"""Reading what is left of a truncated MCAP file (a recording cut short by a full disk or a crash).

rosbags' reader needs the file's footer and summary, so it refuses such a file outright. The
records before the cut are intact, though: this reader walks them in file order (magic, then
``opcode u8 | length u64 | content``), opens uncompressed chunks even when they are cut, complete
compressed chunks (zstd, lz4), and stops at the first incomplete record. It offers the small part
of rosbags' ``AnyReader`` interface that :class:`~neoslam_stream.sources.bag.BagSource` uses
(``connections``, ``start_time``/``end_time``, ``messages()``, ``deserialize()``) for ROS 2 CDR
messages. Written from the MCAP specification (https://mcap.dev/spec).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAGIC = b"\x89MCAP0\r\n"
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x03, 0x04, 0x05, 0x06


@dataclass
class SalvagedConnection:
    id: int
    topic: str
    msgtype: str
    msgcount: int = 0


class _Cut(Exception):
    """The data ends inside a record."""


def _u16(b: memoryview, i: int) -> tuple[int, int]:
    if i + 2 > len(b):
        raise _Cut
    return struct.unpack_from("<H", b, i)[0], i + 2


def _u32(b: memoryview, i: int) -> tuple[int, int]:
    if i + 4 > len(b):
        raise _Cut
    return struct.unpack_from("<I", b, i)[0], i + 4


def _u64(b: memoryview, i: int) -> tuple[int, int]:
    if i + 8 > len(b):
        raise _Cut
    return struct.unpack_from("<Q", b, i)[0], i + 8


def _bytes(b: memoryview, i: int, n: int) -> tuple[bytes, int]:
    if i + n > len(b):
        raise _Cut
    return bytes(b[i:i + n]), i + n


def _string(b: memoryview, i: int) -> tuple[str, int]:
    n, i = _u32(b, i)
    raw, i = _bytes(b, i, n)
    return raw.decode("utf-8", errors="replace"), i


def _records(b: memoryview, i: int = 0) -> Iterator[tuple[int, memoryview]]:
    """(opcode, content) of each complete record from offset ``i``; stops at a cut."""
    while i + 9 <= len(b):
        op = b[i]
        (length,) = struct.unpack_from("<Q", b, i + 1)
        start = i + 9
        if start + length > len(b):
            if op == OP_CHUNK:  # an uncompressed chunk cut short still holds whole records
                yield op, b[start:]
            return
        yield op, b[start:start + length]
        i = start + length


class SalvageMcapReader:
    """The readable records of a (truncated) MCAP file. ``messages_read`` and ``cut`` say how much
    was recovered and whether the file ended inside a record."""

    def __init__(self, path: str | Path, typestore: Any) -> None:
        self.path = Path(path)
        self.typestore = typestore
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, SalvagedConnection] = {}
        self._messages: list[tuple[int, int, bytes]] = []
        self.cut = False
        data = memoryview(self.path.read_bytes())
        if not bytes(data[:8]) == MAGIC:
            raise ValueError(f"{self.path} is not an MCAP file (no magic)")
        self._walk(data[8:], top=True)
        for ch_id, _t, _raw in self._messages:
            self.channels[ch_id].msgcount += 1
        times = [t for _c, t, _r in self._messages]
        self.start_time = min(times) if times else 0
        self.end_time = max(times) if times else 0
        self.messages_read = len(self._messages)

    def _walk(self, b: memoryview, top: bool) -> None:
        consumed = 0
        for op, content in _records(b):
            consumed += 9 + len(content)
            try:
                if op == OP_SCHEMA:
                    sid, i = _u16(content, 0)
                    name, i = _string(content, i)
                    enc, i = _string(content, i)
                    n, i = _u32(content, i)
                    text, i = _bytes(content, i, n)
                    self.schemas[sid] = (name, enc, text)
                elif op == OP_CHANNEL:
                    cid, i = _u16(content, 0)
                    sid, i = _u16(content, i)
                    topic, i = _string(content, i)
                    _enc, i = _string(content, i)
                    name = self.schemas.get(sid, ("", "", b""))[0]
                    self.channels[cid] = SalvagedConnection(cid, topic, name)
                elif op == OP_MESSAGE:
                    cid, i = _u16(content, 0)
                    _seq, i = _u32(content, i)
                    log_time, i = _u64(content, i)
                    _pub, i = _u64(content, i)
                    if cid in self.channels:
                        self._messages.append((cid, log_time, bytes(content[i:])))
                elif op == OP_CHUNK and top:
                    i = 24  # message start/end time, uncompressed size
                    _crc, i = _u32(content, i)
                    compression, i = _string(content, i)
                    size, i = _u64(content, i)
                    records = content[i:i + size]
                    if len(records) < size:
                        self.cut = True
                    if compression == "":
                        self._walk(records, top=False)
                    elif len(records) == size:
                        self._walk(memoryview(_decompress(compression, bytes(records))), top=False)
                    else:
                        self.cut = True
                        return
            except _Cut:
                self.cut = True
                return
        if consumed < len(b):
            self.cut = True

    # --- the AnyReader subset BagSource uses
    @property
    def connections(self) -> list[SalvagedConnection]:
        return list(self.channels.values())

    def messages(self, connections: list[SalvagedConnection] | None = None) -> Iterator[tuple[Any, int, bytes]]:
        wanted = {c.id for c in connections} if connections is not None else set(self.channels)
        for cid, t, raw in self._messages:
            if cid in wanted:
                yield self.channels[cid], t, raw

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        if msgtype not in self.typestore.types:
            self._register(msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def _register(self, msgtype: str) -> None:
        from rosbags.typesys import get_types_from_msg

        for name, enc, text in self.schemas.values():
            if name == msgtype and enc == "ros2msg":
                self.typestore.register(get_types_from_msg(text.decode(), name))
                return
        raise ValueError(f"no definition for message type {msgtype} in {self.path}")

    def __enter__(self) -> SalvageMcapReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None


def _decompress(kind: str, data: bytes) -> bytes:
    if kind == "zstd":
        try:
            from compression import zstd  # Python 3.14
        except ImportError:
            from backports import zstd  # type: ignore[no-redef]
        return zstd.decompress(data)
    if kind == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise ValueError(f"chunk compression {kind!r} is not supported")
