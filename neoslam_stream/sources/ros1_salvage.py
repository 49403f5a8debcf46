"""Reading what is left of a ROS 1 bag cut short (a robot that lost power, a copy interrupted).

rosbags' reader needs the bag's index, which is written last, so it refuses such a file. The
chunks before the cut are intact, though: this reader walks the top-level records in file order
(``header_len u32 | header | data_len u32 | data``, header fields ``len u32 | name=value``),
opens each chunk (none, bz2 or lz4; of a chunk cut short, the part that decompresses), reads its
connection and message-data records, and stops at the first incomplete or damaged record. Only
an index of the recovered messages is kept; their bytes are read again, chunk by chunk, when the
messages are iterated. It offers the part of rosbags' ``AnyReader`` interface that
:class:`~neoslam_stream.sources.bag.BagSource` uses, as :mod:`.mcap_salvage` does for MCAP.
Written from the public description of the ROS bag format 2.0.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

from .mcap_salvage import SalvagedConnection

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_CONNECTION, OP_CHUNK = 0x02, 0x07, 0x05
#: the other top-level records of the format: bag header, index data, chunk info (skipped)
OP_SKIPPED = (0x03, 0x04, 0x06)
#: a record header or a chunk larger than this is taken for damage, not read
MAX_RECORD = 1 << 31
COMPRESSIONS = ("none", "bz2", "lz4")


class _Stop(Exception):
    """Reading ends here: the data ends inside a record (``cut``) or a record is damaged."""

    def __init__(self, cause: str, cut: bool) -> None:
        super().__init__(cause)
        self.cut = cut


def parse_header(raw: bytes) -> dict[str, bytes]:
    """The ``name=value`` fields of a record header; :class:`_Stop` when they do not add up."""
    fields: dict[str, bytes] = {}
    i = 0
    while i < len(raw):
        if i + 4 > len(raw):
            raise _Stop("a header field's length is cut", cut=False)
        (n,) = struct.unpack_from("<I", raw, i)
        i += 4
        if n > len(raw) - i:
            raise _Stop(f"a header field claims {n} bytes, {len(raw) - i} are left", cut=False)
        name, sep, value = raw[i:i + n].partition(b"=")
        if not sep:
            raise _Stop("a header field without '='", cut=False)
        fields[name.decode("ascii", errors="replace")] = value
        i += n
    return fields


def _u32(fields: dict[str, bytes], name: str) -> int:
    value = fields.get(name, b"")
    if len(value) != 4:
        raise _Stop(f"field {name!r} is missing or not 4 bytes", cut=False)
    return struct.unpack("<I", value)[0]


def _op(fields: dict[str, bytes]) -> int:
    if len(fields.get("op", b"")) != 1:
        raise _Stop("a record without its op field", cut=False)
    return fields["op"][0]


def _records(buf: bytes) -> Iterator[tuple[int, dict[str, bytes], int, int]]:
    """(op, header fields, data offset, data length) of each record of a chunk's data; ends
    with :class:`_Stop` at an incomplete or damaged record."""
    i = 0
    while i < len(buf):
        if i + 4 > len(buf):
            raise _Stop("the data ends inside a record", cut=True)
        (hlen,) = struct.unpack_from("<I", buf, i)
        if i + 4 + hlen + 4 > len(buf):
            raise _Stop("the data ends inside a record", cut=True)
        fields = parse_header(buf[i + 4:i + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", buf, i + 4 + hlen)
        start = i + 8 + hlen
        if start + dlen > len(buf):
            raise _Stop("the data ends inside a record", cut=True)
        yield _op(fields), fields, start, dlen
        i = start + dlen


def decompress(kind: str, data: bytes, complete: bool) -> bytes:
    """A chunk's records: all of them, or for a chunk cut short (``complete`` False) the part of
    its compressed stream that decodes."""
    if kind == "none":
        return data
    if kind == "bz2":
        import bz2

        return bz2.decompress(data) if complete else bz2.BZ2Decompressor().decompress(data)
    if kind == "lz4":
        try:
            import lz4.frame
        except ImportError:  # rosbags depends on it, so it is normally there
            raise ValueError("lz4 chunks need the lz4 module (pip install lz4)") from None
        return lz4.frame.decompress(data) if complete else lz4.frame.LZ4FrameDecompressor().decompress(data)
    raise ValueError(f"chunk compression {kind!r} is not one of {', '.join(COMPRESSIONS)}")


def _read(f: BinaryIO, n: int) -> bytes:
    data = f.read(n)
    if len(data) < n:
        raise _Stop("the file ends inside a record", cut=True)
    return data


def _normal_type(ros1_type: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (rosbags' and our spelling)."""
    pkg, _, name = ros1_type.partition("/")
    return f"{pkg}/msg/{name}" if name and "/msg/" not in ros1_type else ros1_type


class SalvageRos1Reader:
    """The readable messages of a (truncated) ROS 1 bag. ``messages_read``, ``cut`` (the file ends
    inside a record) and ``stopped`` (why reading stopped before the end, or None) say how much
    was recovered."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.channels: dict[int, SalvagedConnection] = {}
        self._defs: dict[int, tuple[str, str]] = {}  # conn id -> (type as written, definition)
        #: file position, length, compression and whether whole, of every chunk read
        self._chunks: list[tuple[int, int, str, bool]] = []
        #: (time ns, write order, conn id, chunk number, data offset, data length) per message
        self._index: list[tuple[int, int, int, int, int, int]] = []
        self.cut = False
        self.stopped: str | None = None
        self._typestore: Any = None
        with self.path.open("rb") as f:
            self._size = os.fstat(f.fileno()).st_size
            if f.read(len(MAGIC)) != MAGIC:
                raise ValueError(f"{self.path} is not a ROS 1 bag (version 2.0)")
            try:
                self._walk(f)
            except _Stop as stop:
                self.cut, self.stopped = stop.cut, str(stop)
        self._index.sort()
        for _t, _n, cid, *_ in self._index:
            self.channels[cid].msgcount += 1
        self.start_time = self._index[0][0] if self._index else 0
        self.end_time = self._index[-1][0] if self._index else 0
        self.messages_read = len(self._index)

    def _walk(self, f: BinaryIO) -> None:
        while True:
            head = f.read(4)
            if not head:
                return
            if len(head) < 4:
                raise _Stop("the file ends inside a record", cut=True)
            (hlen,) = struct.unpack("<I", head)
            if hlen > MAX_RECORD:
                raise _Stop(f"a record header claims {hlen} bytes", cut=False)
            fields = parse_header(_read(f, hlen))
            (dlen,) = struct.unpack("<I", _read(f, 4))
            op = _op(fields)
            if op == OP_CHUNK:
                kind = fields.get("compression", b"").decode("ascii", errors="replace")
                if kind not in COMPRESSIONS:
                    raise _Stop(f"a chunk compressed with {kind!r}, not one of {', '.join(COMPRESSIONS)}",
                                cut=False)
                pos = f.tell()
                data = f.read(dlen)
                self._chunks.append((pos, len(data), kind, len(data) == dlen))
                self._read_chunk(len(self._chunks) - 1, data)
                if len(data) < dlen:
                    raise _Stop("the file ends inside a chunk", cut=True)
            elif op == OP_CONNECTION:
                self._connection(fields, _read(f, dlen))
            elif op in OP_SKIPPED:
                if f.seek(dlen, 1) > self._size:
                    raise _Stop("the file ends inside a record", cut=True)
            else:
                raise _Stop(f"a record with the unknown op {op:#04x}", cut=False)

    def _chunk_data(self, number: int, data: bytes | None = None) -> bytes:
        pos, size, kind, complete = self._chunks[number]
        if data is None:
            with self.path.open("rb") as f:
                f.seek(pos)
                data = f.read(size)
        try:
            return decompress(kind, data, complete)
        except (OSError, EOFError, RuntimeError) as exc:  # bz2 / lz4: a damaged stream
            raise _Stop(f"a {kind} chunk that does not decompress ({exc})", cut=False) from None

    def _read_chunk(self, number: int, data: bytes) -> None:
        buf = self._chunk_data(number, data)
        try:
            self._chunk_records(number, buf)
        except _Stop as stop:
            if stop.cut and self._chunks[number][3]:  # a whole chunk whose records do not fit in it
                raise _Stop(f"a chunk whose last record is incomplete ({stop})", cut=False) from None
            raise

    def _chunk_records(self, number: int, buf: bytes) -> None:
        for op, fields, start, length in _records(buf):
            if op == OP_CONNECTION:
                self._connection(fields, buf[start:start + length])
            elif op == OP_MESSAGE:
                cid = _u32(fields, "conn")
                stamp = fields.get("time", b"")
                if len(stamp) != 8:
                    raise _Stop("a message without its 8-byte time", cut=False)
                sec, nsec = struct.unpack("<II", stamp)
                if cid not in self.channels:
                    raise _Stop(f"a message of connection {cid}, which no record defined", cut=False)
                self._index.append((sec * 1_000_000_000 + nsec, len(self._index), cid, number, start, length))
            else:
                raise _Stop(f"a record with op {op:#04x} inside a chunk", cut=False)

    def _connection(self, fields: dict[str, bytes], data: bytes) -> None:
        cid = _u32(fields, "conn")
        info = parse_header(data)
        topic = fields.get("topic", info.get("topic", b"")).decode("utf-8", errors="replace")
        written = info.get("type", b"").decode("utf-8", errors="replace")
        if cid not in self.channels:
            self.channels[cid] = SalvagedConnection(cid, topic, _normal_type(written))
            self._defs[cid] = (written, info.get("message_definition", b"").decode("utf-8", errors="replace"))

    # --- the AnyReader subset BagSource uses
    @property
    def connections(self) -> list[SalvagedConnection]:
        return list(self.channels.values())

    def messages(self, connections: list[SalvagedConnection] | None = None) -> Iterator[tuple[Any, int, bytes]]:
        """(connection, time ns, raw message) in time order (messages of equal time as written)."""
        wanted = {c.id for c in connections} if connections is not None else set(self.channels)
        cache: dict[int, bytes] = {}
        for t, _n, cid, chunk, start, length in self._index:
            if cid not in wanted:
                continue
            if chunk not in cache:
                if len(cache) >= 2:  # a message's chunk is almost always the current or the next one
                    cache.pop(next(iter(cache)))
                cache[chunk] = self._chunk_data(chunk)
            yield self.channels[cid], t, cache[chunk][start:start + length]

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore

            self._typestore = get_typestore(Stores.EMPTY)
        if msgtype not in self._typestore.types:
            self._register(msgtype)
        return self._typestore.deserialize_ros1(raw, msgtype)

    def _register(self, msgtype: str) -> None:
        from rosbags.typesys import get_types_from_msg

        for cid, (_written, text) in self._defs.items():
            if self.channels[cid].msgtype == msgtype and text:
                self._typestore.register(get_types_from_msg(text, msgtype))
                return
        raise ValueError(f"no definition for message type {msgtype} in {self.path}")

    def __enter__(self) -> SalvageRos1Reader:
        return self

    def __exit__(self, *exc: Any) -> None:
        return None
