"""ROS1 bag format 2.0 at the record level: parse a bag's index (or rebuild it by scanning), fetch chunks,
and write records, chunks and the index.

A bag is ``#ROSBAG V2.0\\n``, a 4096-byte bag header record (``index_pos``, ``conn_count``,
``chunk_count``), then chunk records, each followed by one index-data record per connection it holds,
then at ``index_pos`` every connection record and one chunk-info record per chunk. A record is
``uint32 header_len, header (fields "name=value", each uint32-length prefixed), uint32 data_len, data``.

An interrupted write leaves ``index_pos = 0`` (or a cut file): :func:`load_index` then scans the chunks
sequentially up to the last complete one and flags the index ``truncated``.
"""

from __future__ import annotations

import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import lz4.block
import lz4.frame
import numpy as np

from darp.errors import RecordingError
from darp.formats.ros_messages import MessageType

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_INDEX_DATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7
BAG_HEADER_RECORD_LENGTH = 4096  # the whole record, length fields included (the rest is space padding)
ENTRY_DTYPE = np.dtype([("time", "<i8"), ("chunk", "<i4"), ("offset", "<u4")])
_U32 = struct.Struct("<I")
# librealsense accepts only LZ4 frames with independent blocks, a content checksum and no stored size.
_LZ4_OPTIONS = {"block_size": lz4.frame.BLOCKSIZE_MAX4MB, "block_linked": False, "content_checksum": True,
                "store_size": False, "compression_level": 0}


@dataclass(frozen=True)
class Connection:
    conn_id: int
    topic: str
    msgtype: str
    md5sum: str = ""
    definition: str = ""


@dataclass(frozen=True)
class Chunk:
    pos: int  # file offset of the chunk record
    data_start: int  # file offset of the (compressed) chunk data
    data_len: int
    compression: str  # none, lz4 (bz2 is refused)
    size: int  # uncompressed size


@dataclass
class BagIndex:
    """Where every message is: per connection, (bag time ns, chunk number, offset in the chunk)."""

    connections: dict[int, Connection]
    chunks: list[Chunk]
    entries: dict[int, np.ndarray]  # ENTRY_DTYPE, sorted by (time, chunk, offset)
    truncated: bool = False
    note: str = ""


class _Incomplete(Exception):
    """A record runs past the end of the bytes available (a cut file)."""


# -- records ----------------------------------------------------------------------------------------
def encode_header(fields: dict[str, bytes]) -> bytes:
    """Record header bytes (without its length), fields in name order like rosbag's C++ writer."""
    parts = []
    for name in sorted(fields):
        item = name.encode() + b"=" + fields[name]
        parts.append(_U32.pack(len(item)) + item)
    return b"".join(parts)


def decode_header(buf: bytes | memoryview | mmap.mmap, pos: int, end: int) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    raw = bytes(buf[pos:end])
    i, n = 0, len(raw)
    while i < n:
        (length,) = _U32.unpack_from(raw, i)
        i += 4
        stop = i + length
        equals = raw.find(b"=", i, stop)
        if stop > n or equals < 0:
            raise ValueError("malformed record header field")
        fields[raw[i:equals].decode("ascii", errors="replace")] = raw[equals + 1:stop]
        i = stop
    return fields


def read_record(buf: bytes | memoryview | mmap.mmap, pos: int, end: int) -> tuple[dict[str, bytes], int, int]:
    """(header fields, data start, data length) of the record at ``pos``; :class:`_Incomplete` if cut."""
    if pos + 4 > end:
        raise _Incomplete
    (header_len,) = _U32.unpack_from(buf, pos)
    header_end = pos + 4 + header_len
    if header_end + 4 > end:
        raise _Incomplete
    fields = decode_header(buf, pos + 4, header_end)
    (data_len,) = _U32.unpack_from(buf, header_end)
    data_start = header_end + 4
    if data_start + data_len > end:
        raise _Incomplete
    return fields, data_start, data_len


def _op(fields: dict[str, bytes]) -> int:
    op = fields.get("op")
    if op is None or len(op) != 1:
        raise ValueError("record without a valid 'op' field")
    return op[0]


def _u32(fields: dict[str, bytes], name: str) -> int:
    return _U32.unpack(fields[name])[0]


def pack_time(ns: int) -> bytes:
    return struct.pack("<II", ns // 1_000_000_000, ns % 1_000_000_000)


def _connection(fields: dict[str, bytes], buf: bytes | memoryview | mmap.mmap, start: int, length: int) -> Connection:
    info = decode_header(buf, start, start + length)
    text = {k: v.decode("utf-8", errors="replace") for k, v in info.items()}
    return Connection(_u32(fields, "conn"), fields["topic"].decode("utf-8", errors="replace"),
                      text.get("type", ""), text.get("md5sum", ""), text.get("message_definition", ""))


# -- reading --------------------------------------------------------------------------------------
def check_compression(chunk: Chunk, path: Path) -> None:
    """Refuse chunks darp cannot read (BZ2, unknown) with a clear error."""
    if chunk.compression == "bz2":
        raise RecordingError(f"BZ2-compressed chunk at byte offset {chunk.pos}: darp reads LZ4 or "
                             "uncompressed bags only (librealsense cannot play BZ2 bags either)", path)
    if chunk.compression not in ("none", "lz4"):
        raise RecordingError(f"unknown chunk compression {chunk.compression!r} at byte offset {chunk.pos}", path)


def chunk_data(view: memoryview, chunk: Chunk, path: Path, verify: bool = True) -> memoryview | bytes:
    """The uncompressed bytes of ``chunk``: a view into the file, or freshly decompressed LZ4.

    ``verify`` checks the LZ4 content checksum (as librealsense does); without it, blocks are decoded
    directly, about twice as fast, and only structural damage is detected.
    """
    raw = view[chunk.data_start:chunk.data_start + chunk.data_len]
    if chunk.compression == "none":
        return raw
    check_compression(chunk, path)
    try:
        data = _lz4_blocks(raw, chunk.size) if not verify else None
        if data is None:  # lz4's low-level frame API: reads the mapped bytes in place, checks the checksum
            data, _, complete = lz4.frame.decompress_chunk(lz4.frame.create_decompression_context(), raw,
                                                           max_length=chunk.size)
            if not complete:
                raise ValueError("the LZ4 frame ends early")
    except (RuntimeError, ValueError, struct.error, lz4.block.LZ4BlockError) as err:
        raise RecordingError(f"corrupt LZ4 chunk at byte offset {chunk.pos}: {err}", path) from err
    if len(data) != chunk.size:
        raise RecordingError(f"corrupt LZ4 chunk at byte offset {chunk.pos}: {len(data)} bytes "
                             f"decompressed, its header says {chunk.size}", path)
    return data


def _lz4_blocks(frame: memoryview, size: int) -> bytes | None:
    """Decode an LZ4 frame of independent blocks without its checksum; None if the blocks are linked."""
    if len(frame) < 7 or _U32.unpack_from(frame, 0)[0] != 0x184D2204:
        raise ValueError("no LZ4 frame magic")
    flags, block_id = frame[4], (frame[5] >> 4) & 0x7
    if not flags & 0x20:
        return None
    block_max, pos, parts = 1 << (8 + 2 * block_id), 7 + 8 * bool(flags & 0x08) + 4 * bool(flags & 0x01), []
    remaining = size
    while True:
        (length,) = _U32.unpack_from(frame, pos)
        pos += 4
        if length == 0:
            break
        stored, length = bool(length >> 31), length & 0x7FFFFFFF
        block = frame[pos:pos + length]
        expected = min(block_max, remaining)
        parts.append(bytes(block) if stored else lz4.block.decompress(block, uncompressed_size=expected))
        remaining -= len(parts[-1])
        pos += length + 4 * bool(flags & 0x10)
    return parts[0] if len(parts) == 1 else b"".join(parts)


class ByteSource:
    """Small reads from a bag: ``os.pread`` on its file descriptor (the index lies scattered through the
    file; reading it this way neither maps those pages into the process nor reads ahead around them), or
    slices of an in-memory buffer. ``view`` is the whole file, for chunk data."""

    def __init__(self, view: memoryview, fd: int | None = None) -> None:
        self.view, self.size, self._fd = view, len(view), fd

    def read(self, pos: int, length: int) -> bytes:
        length = max(0, min(length, self.size - pos))
        return os.pread(self._fd, length, pos) if self._fd is not None else bytes(self.view[pos:pos + length])


def _record_at(src: ByteSource, pos: int, with_data: bool, hint: int = 512) -> tuple[dict[str, bytes], int, int, bytes]:
    """(header fields, data start, data length, data or b"") of the record at ``pos``, in one or two reads."""
    head = src.read(pos, hint)
    if len(head) < 4:
        raise _Incomplete
    need = 8 + _U32.unpack_from(head, 0)[0]
    if need > len(head):
        head = src.read(pos, need + hint)
        if need > len(head):
            raise _Incomplete
    fields = decode_header(head, 4, need - 4)
    (data_len,) = _U32.unpack_from(head, need - 4)
    if pos + need + data_len > src.size:
        raise _Incomplete
    if not with_data:
        return fields, pos + need, data_len, b""
    data = head[need:need + data_len] if need + data_len <= len(head) else src.read(pos + need, data_len)
    return fields, pos + need, data_len, data


def _chunk(fields: dict[str, bytes], pos: int, data_start: int, data_len: int, path: Path) -> Chunk:
    if _op(fields) != OP_CHUNK:
        raise ValueError(f"expected a chunk record at byte offset {pos}")
    chunk = Chunk(pos, data_start, data_len, fields["compression"].decode("ascii", errors="replace"),
                  _u32(fields, "size"))
    check_compression(chunk, path)
    return chunk


def load_index(source: ByteSource | memoryview, path: Path) -> BagIndex:
    """Parse the bag header and the index; rebuild the index by scanning when it is missing or cut."""
    src = source if isinstance(source, ByteSource) else ByteSource(source)
    if src.read(0, len(MAGIC)) != MAGIC:
        raise RecordingError("not a ROS1 bag (no '#ROSBAG V2.0' magic)", path)
    try:
        fields, data_start, data_len, _ = _record_at(src, len(MAGIC), with_data=False)
        if _op(fields) != OP_BAG_HEADER:
            raise ValueError("first record is not a bag header")
        index_pos = struct.unpack("<Q", fields["index_pos"])[0]
        conn_count, chunk_count = _u32(fields, "conn_count"), _u32(fields, "chunk_count")
    except _Incomplete:
        raise RecordingError(f"truncated bag header ({src.size} bytes): no chunk to read", path) from None
    except (ValueError, KeyError, struct.error) as err:
        raise RecordingError(f"corrupt bag header at byte offset {len(MAGIC)}: {err}", path) from err
    first = data_start + data_len
    if index_pos == 0:
        return _scan(src, path, first, "no index (interrupted write)")
    if index_pos >= src.size:
        return _scan(src, path, first, f"index position {index_pos} lies past the end of the file ({src.size} bytes)")
    try:
        return _indexed(src, path, index_pos, conn_count, chunk_count)
    except (_Incomplete, ValueError, KeyError, struct.error) as err:
        return _scan(src, path, first, f"unreadable index at byte offset {index_pos} ({err or 'cut short'})")


def _indexed(src: ByteSource, path: Path, index_pos: int, conn_count: int, chunk_count: int) -> BagIndex:
    tail = src.read(index_pos, src.size - index_pos)  # the connection and chunk-info records
    connections: dict[int, Connection] = {}
    infos: list[tuple[int, int, int]] = []  # (chunk position, connections in it, messages in it)
    pos = 0
    for _ in range(conn_count + chunk_count):
        fields, start, length = read_record(tail, pos, len(tail))
        op = _op(fields)
        if op == OP_CONNECTION:
            conn = _connection(fields, tail, start, length)
            connections[conn.conn_id] = conn
        elif op == OP_CHUNK_INFO:
            counts = np.frombuffer(tail, "<u4", 2 * _u32(fields, "count"), start)[1::2]
            infos.append((struct.unpack("<Q", fields["chunk_pos"])[0], len(counts), int(counts.sum())))
        else:
            raise ValueError(f"unexpected record op {op} in the index at byte offset {index_pos + pos}")
        pos = start + length
    parts: _Parts = {}
    chunks: list[Chunk] = []
    for chunk_pos, conn_in_chunk, messages in sorted(infos):
        fields, data_start, data_len, _ = _record_at(src, chunk_pos, with_data=False, hint=128)
        chunks.append(_chunk(fields, chunk_pos, data_start, data_len, path))
        # the index-data records that follow the chunk; their usual size is known from the chunk info
        guess = conn_in_chunk * _INDEX_HEAD.size + 12 * messages
        while True:
            region = src.read(data_start + data_len, guess)
            try:
                pos = 0
                for _ in range(conn_in_chunk):
                    conn, count, start, length = _index_record(region, pos, len(region))
                    _add_index_data(parts, conn, count, region, start, length, len(chunks) - 1)
                    pos = start + length
                break
            except _Incomplete:
                if len(region) < guess:
                    raise
                guess *= 4
    return BagIndex(connections, chunks, _sorted_entries(parts))


_Parts = dict[int, list[tuple[int, np.ndarray]]]  # conn -> [(chunk number, uint32 rows of sec, nsec, offset)]
# An index-data record header as rosbag's C++ writer (and darp's) lays it out: fields in name order.
_INDEX_HEAD = struct.Struct("<II5sII6sII3sBI4sII")
_INDEX_FIXED = (47, 9, b"conn=", 10, b"count=", 4, b"op=", OP_INDEX_DATA, 8, b"ver=")


def _index_record(view: memoryview, pos: int, size: int) -> tuple[int, int, int, int]:
    """(conn, count, data start, data length) of the index-data record at ``pos``; a fast path for the
    usual layout (one struct unpack), the generic header parser otherwise."""
    if pos + _INDEX_HEAD.size <= size:
        h = _INDEX_HEAD.unpack_from(view, pos)
        if (h[0], h[1], h[2], h[4], h[5], h[7], h[8], h[9], h[10], h[11]) == _INDEX_FIXED:
            start = pos + _INDEX_HEAD.size
            if start + h[13] > size:
                raise _Incomplete
            return h[3], h[6], start, h[13]
    fields, start, length = read_record(view, pos, size)
    if _op(fields) != OP_INDEX_DATA:
        raise ValueError(f"expected an index-data record at byte offset {pos}")
    return _u32(fields, "conn"), _u32(fields, "count"), start, length


def _add_index_data(parts: _Parts, conn: int, count: int, view: memoryview, start: int, length: int,
                    chunk_number: int) -> None:
    if count * 12 > length:
        raise ValueError(f"index-data record at byte offset {start} is shorter than its count")
    rows = np.frombuffer(view, "<u4", count=3 * count, offset=start).reshape(count, 3)
    parts.setdefault(conn, []).append((chunk_number, rows))


def _sorted_entries(parts: _Parts) -> dict[int, np.ndarray]:
    entries = {}
    for conn, items in parts.items():
        rows = np.concatenate([r for _, r in items]) if len(items) > 1 else items[0][1]
        merged = np.empty(len(rows), ENTRY_DTYPE)
        merged["time"] = rows[:, 0].astype(np.int64) * 1_000_000_000 + rows[:, 1]
        merged["chunk"] = np.repeat(np.array([c for c, _ in items], np.int32), [len(r) for _, r in items])
        merged["offset"] = rows[:, 2]
        entries[conn] = merged[np.lexsort((merged["offset"], merged["chunk"], merged["time"]))]
    return entries


def parse_chunk(data: bytes | memoryview, chunk_number: int, connections: dict[int, Connection],
                parts: _Parts) -> None:
    """Collect the connection and message records of one uncompressed chunk."""
    pos, end = 0, len(data)
    found: dict[int, list[tuple[int, int, int]]] = {}
    while pos < end:
        fields, start, length = read_record(data, pos, end)
        op = _op(fields)
        if op == OP_CONNECTION:
            conn = _connection(fields, data, start, length)
            connections.setdefault(conn.conn_id, conn)
        elif op == OP_MESSAGE:
            sec, nsec = struct.unpack("<II", fields["time"])
            found.setdefault(_u32(fields, "conn"), []).append((sec, nsec, pos))
        pos = start + length
    for conn_id, rows in found.items():
        parts.setdefault(conn_id, []).append((chunk_number, np.array(rows, "<u4").reshape(-1, 3)))


def _scan(src: ByteSource, path: Path, pos: int, reason: str) -> BagIndex:
    """Rebuild the index from the chunks themselves, up to the last complete chunk."""
    size = src.size
    connections: dict[int, Connection] = {}
    chunks: list[Chunk] = []
    pending: _Parts = {}  # index data of the chunk being scanned
    parts: _Parts = {}
    cut_at = None
    notes = [reason]

    def settle(last: bool) -> None:
        """Adopt the scanned chunk's index data, or read the chunk itself when that is not enough."""
        number = len(chunks) - 1
        chunk = chunks[number]
        if not last and pending and all(conn in connections for conn in pending):
            for conn, arrays in pending.items():
                parts.setdefault(conn, []).extend(arrays)
            return
        found: _Parts = {}
        try:  # no, possibly cut, or unresolvable index data: parse the chunk's own records
            parse_chunk(chunk_data(src.view, chunk, path), number, connections, found)
        except (RecordingError, _Incomplete, ValueError, KeyError, struct.error) as err:
            if not last:
                if isinstance(err, RecordingError):
                    raise
                raise RecordingError(f"corrupt chunk at byte offset {chunk.pos}: {err}", path) from err
            chunks.pop()
            notes.append(f"last chunk at byte offset {chunk.pos} is unreadable and was skipped")
            return
        for conn, arrays in found.items():
            parts.setdefault(conn, []).extend(arrays)

    while pos < size:
        try:
            fields, start, length, _ = _record_at(src, pos, with_data=False)
            op = _op(fields)
        except _Incomplete:
            cut_at = pos
            break
        except (ValueError, KeyError, struct.error):
            cut_at = pos
            notes.append(f"unreadable record at byte offset {pos}")
            break
        try:
            if op == OP_CHUNK:
                if chunks:
                    settle(last=False)
                pending = {}
                chunks.append(_chunk(fields, pos, start, length, path))
            elif op == OP_INDEX_DATA and chunks:
                _add_index_data(pending, _u32(fields, "conn"), _u32(fields, "count"), src.read(start, length), 0,
                                length, len(chunks) - 1)
            elif op == OP_CONNECTION:
                conn = _connection(fields, src.read(start, length), 0, length)
                connections.setdefault(conn.conn_id, conn)
        except (ValueError, KeyError, struct.error) as err:
            raise RecordingError(f"corrupt {_NAMES.get(op, 'record')} at byte offset {pos}: {err}", path) from err
        pos = start + length
    if chunks:
        settle(last=True)
    if cut_at is not None:
        notes.append(f"{size - cut_at} trailing bytes from offset {cut_at} are an incomplete record")
    notes.insert(1, f"{len(chunks)} complete chunks recovered by scanning")
    return BagIndex(connections, chunks, _sorted_entries(parts), truncated=True, note="; ".join(notes))


_NAMES = {OP_CHUNK: "chunk record", OP_INDEX_DATA: "index-data record", OP_CONNECTION: "connection record"}


# -- writing (pure encoders; the chunking writer is darp.formats.bag_writer) --------------------------
def record(fields: dict[str, bytes], data: bytes | bytearray = b"") -> bytes:
    header = encode_header(fields)
    return _U32.pack(len(header)) + header + _U32.pack(len(data)) + data


def record_head(fields: dict[str, bytes], data_len: int) -> bytes:
    """A record up to its data, for data written separately (messages, chunks)."""
    header = encode_header(fields)
    return _U32.pack(len(header)) + header + _U32.pack(data_len)


def message_head(conn_id: int, time_ns: int, data_len: int) -> bytes:
    return record_head({"conn": _U32.pack(conn_id), "op": bytes([OP_MESSAGE]), "time": pack_time(time_ns)}, data_len)


def chunk_head(compression: str, size: int, data_len: int) -> bytes:
    return record_head({"compression": compression.encode(), "op": bytes([OP_CHUNK]), "size": _U32.pack(size)},
                       data_len)


def compress_lz4(raw: bytes | bytearray) -> bytes:
    return lz4.frame.compress(raw, **_LZ4_OPTIONS)


def index_data_record(conn_id: int, items: list[tuple[int, int]]) -> bytes:
    """The index of one connection in one chunk: (bag time ns, offset in the chunk) per message."""
    entries = b"".join(pack_time(t) + _U32.pack(offset) for t, offset in items)
    return record({"conn": _U32.pack(conn_id), "count": _U32.pack(len(items)), "op": bytes([OP_INDEX_DATA]),
                   "ver": _U32.pack(1)}, entries)


def chunk_info_record(chunk_pos: int, start_ns: int, end_ns: int, counts: dict[int, int]) -> bytes:
    fields = {"chunk_pos": struct.pack("<Q", chunk_pos), "count": _U32.pack(len(counts)),
              "end_time": pack_time(end_ns), "op": bytes([OP_CHUNK_INFO]), "start_time": pack_time(start_ns),
              "ver": _U32.pack(1)}
    return record(fields, b"".join(struct.pack("<II", c, n) for c, n in sorted(counts.items())))


def connection_record(conn_id: int, topic: str, msgtype: MessageType) -> bytes:
    data = encode_header({"md5sum": msgtype.md5sum.encode(), "message_definition": msgtype.definition.encode(),
                          "topic": topic.encode(), "type": msgtype.name.encode()})
    return record({"conn": _U32.pack(conn_id), "op": bytes([OP_CONNECTION]), "topic": topic.encode()}, data)


def bag_header_record(index_pos: int, conn_count: int, chunk_count: int) -> bytes:
    """The bag header record, padded with spaces to 4096 bytes so that it can be rewritten in place."""
    header = encode_header({"chunk_count": _U32.pack(chunk_count), "conn_count": _U32.pack(conn_count),
                            "index_pos": struct.pack("<Q", index_pos), "op": bytes([OP_BAG_HEADER])})
    padding = BAG_HEADER_RECORD_LENGTH - 8 - len(header)
    return _U32.pack(len(header)) + header + _U32.pack(padding) + b" " * padding
