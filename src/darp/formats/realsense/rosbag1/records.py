"""ROS1 bag format 2.0, reading side: the records (header fields, chunk, connection and index-data
records), chunk bytes, and small reads from a bag file. Used by :mod:`darp.formats.realsense.rosbag1.index`
(the index) and :mod:`darp.formats.realsense.rosbag1.scan` (rebuilding a missing index).
"""

from __future__ import annotations

import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from darp.errors import DecodeError, RecordingError
from darp.formats.realsense.rosbag1.lz4 import ChunkBuffer, Lz4Error, decode_frame
from darp.formats.realsense.rosbag1.write import OP_CHUNK, OP_INDEX_DATA

_U32 = struct.Struct("<I")
ENTRY_DTYPE = np.dtype([("time", "<i8"), ("chunk", "<i4"), ("offset", "<u4")])


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
    truncated: bool = False  # rebuilt by scanning: no usable index
    problems: tuple[str, ...] = ()  # (scanned) why, and what was cut or skipped, one phrase each
    truncated_at: int | None = None  # (scanned) byte offset of the first incomplete or unreadable record

    @property
    def note(self) -> str:
        """What was missing and what was recovered, in one line ("" for an indexed bag)."""
        if not self.truncated:
            return ""
        return "; ".join([*self.problems, f"{len(self.chunks)} complete chunks recovered by scanning"])


class Incomplete(Exception):
    """A record runs past the end of the bytes available (a cut file)."""


# -- records ----------------------------------------------------------------------------------------
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
            raise DecodeError("malformed record header field")
        fields[raw[i:equals].decode("ascii", errors="replace")] = raw[equals + 1:stop]
        i = stop
    return fields


def read_record(buf: bytes | memoryview | mmap.mmap, pos: int, end: int) -> tuple[dict[str, bytes], int, int]:
    """(header fields, data start, data length) of the record at ``pos``; :class:`Incomplete` if cut."""
    if pos + 4 > end:
        raise Incomplete
    (header_len,) = _U32.unpack_from(buf, pos)
    header_end = pos + 4 + header_len
    if header_end + 4 > end:
        raise Incomplete
    fields = decode_header(buf, pos + 4, header_end)
    (data_len,) = _U32.unpack_from(buf, header_end)
    data_start = header_end + 4
    if data_start + data_len > end:
        raise Incomplete
    return fields, data_start, data_len


def record_op(fields: dict[str, bytes]) -> int:
    op = fields.get("op")
    if op is None or len(op) != 1:
        raise DecodeError("record without a valid 'op' field")
    return op[0]


def field_u32(fields: dict[str, bytes], name: str) -> int:
    (value,) = _U32.unpack(fields[name])
    return int(value)


def connection_from(fields: dict[str, bytes], buf: bytes | memoryview | mmap.mmap, start: int,
                    length: int) -> Connection:
    info = decode_header(buf, start, start + length)
    text = {k: v.decode("utf-8", errors="replace") for k, v in info.items()}
    return Connection(field_u32(fields, "conn"), fields["topic"].decode("utf-8", errors="replace"),
                      text.get("type", ""), text.get("md5sum", ""), text.get("message_definition", ""))


# -- reading --------------------------------------------------------------------------------------
def check_compression(chunk: Chunk, path: Path) -> None:
    """Refuse chunks darp cannot read (BZ2, unknown) with a clear error."""
    if chunk.compression == "bz2":
        raise RecordingError(f"BZ2-compressed chunk at byte offset {chunk.pos}: darp reads LZ4 or "
                             "uncompressed bags only (librealsense cannot play BZ2 bags either)", path)
    if chunk.compression not in ("none", "lz4"):
        raise RecordingError(f"unknown chunk compression {chunk.compression!r} at byte offset {chunk.pos}", path)


def chunk_data(view: memoryview, chunk: Chunk, path: Path, verify: bool = True) -> memoryview:
    """The uncompressed bytes of ``chunk`` (read-only): a view into the file, or freshly decoded LZ4.

    ``verify`` checks the LZ4 content checksum, as librealsense does.
    """
    raw = view[chunk.data_start:chunk.data_start + chunk.data_len]
    if chunk.compression == "none":
        return raw
    check_compression(chunk, path)
    buffer = ChunkBuffer(chunk.size)
    try:
        decode_frame(raw, buffer, chunk.size, verify)
    except Lz4Error as err:
        raise RecordingError(f"corrupt LZ4 chunk at byte offset {chunk.pos}: {err}", path) from err
    return buffer.view(chunk.size)


class ByteSource:
    """Small reads from a bag: ``os.pread`` on its file descriptor (the index lies scattered through the
    file; reading it this way neither maps those pages into the process nor reads ahead around them), or
    slices of an in-memory buffer. ``view`` is the whole file, for chunk data."""

    def __init__(self, view: memoryview, fd: int | None = None) -> None:
        self.view, self.size, self._fd = view, len(view), fd

    def read(self, pos: int, length: int) -> bytes:
        length = max(0, min(length, self.size - pos))
        return os.pread(self._fd, length, pos) if self._fd is not None else bytes(self.view[pos:pos + length])


def record_at(src: ByteSource, pos: int, with_data: bool, hint: int = 512) -> tuple[dict[str, bytes], int, int, bytes]:
    """(header fields, data start, data length, data or b"") of the record at ``pos``, in one or two reads."""
    head = src.read(pos, hint)
    if len(head) < 4:
        raise Incomplete
    need = 8 + _U32.unpack_from(head, 0)[0]
    if need > len(head):
        head = src.read(pos, need + hint)
        if need > len(head):
            raise Incomplete
    fields = decode_header(head, 4, need - 4)
    (data_len,) = _U32.unpack_from(head, need - 4)
    if pos + need + data_len > src.size:
        raise Incomplete
    if not with_data:
        return fields, pos + need, data_len, b""
    data = head[need:need + data_len] if need + data_len <= len(head) else src.read(pos + need, data_len)
    return fields, pos + need, data_len, data


def chunk_from(fields: dict[str, bytes], pos: int, data_start: int, data_len: int, path: Path) -> Chunk:
    if record_op(fields) != OP_CHUNK:
        raise DecodeError(f"expected a chunk record at byte offset {pos}")
    chunk = Chunk(pos, data_start, data_len, fields["compression"].decode("ascii", errors="replace"),
                  field_u32(fields, "size"))
    check_compression(chunk, path)
    return chunk


# An index-data record header as rosbag's C++ writer (and darp's) lays it out: fields in name order.
INDEX_HEAD = struct.Struct("<II5sII6sII3sBI4sII")
INDEX_FIXED = (47, 9, b"conn=", 10, b"count=", 4, b"op=", OP_INDEX_DATA, 8, b"ver=")


def index_record(view: bytes | memoryview, pos: int, size: int) -> tuple[int, int, int, int]:
    """(conn, count, data start, data length) of the index-data record at ``pos``; a fast path for the
    usual layout (one struct unpack), the generic header parser otherwise."""
    if pos + INDEX_HEAD.size <= size:
        h = INDEX_HEAD.unpack_from(view, pos)
        if (h[0], h[1], h[2], h[4], h[5], h[7], h[8], h[9], h[10], h[11]) == INDEX_FIXED:
            start = pos + INDEX_HEAD.size
            if start + h[13] > size:
                raise Incomplete
            return h[3], h[6], start, h[13]
    fields, start, length = read_record(view, pos, size)
    if record_op(fields) != OP_INDEX_DATA:
        raise DecodeError(f"expected an index-data record at byte offset {pos}")
    return field_u32(fields, "conn"), field_u32(fields, "count"), start, length
