"""ROS1 bag format 2.0 at the record level, reading side: parse a bag's index (or rebuild it by
scanning) and fetch chunk bytes. The record constants and encoders live in
:mod:`darp.formats.realsense.rosbag1.write` and are re-exported here.

An interrupted write leaves ``index_pos = 0`` (or a cut file): :func:`load_index` then scans the chunks
sequentially up to the last complete one and flags the index ``truncated``.

Opening a long recording means reading a few hundred bytes around every chunk (its header, and the
index-data records after it). In the usual layout (fields in name order, as rosbag's C++ writer,
librealsense and darp write them) the index-data records of one chunk end where the next chunk starts,
and their size follows from the chunk-info counts, so one small read per chunk fetches both; other
layouts take the general path.
"""

from __future__ import annotations

import itertools
import struct
from pathlib import Path

import numpy as np

from darp.errors import DecodeError, RecordingError
from darp.formats.realsense.rosbag1.records import (  # re-exported: the record level of the format
    ENTRY_DTYPE,
    INDEX_HEAD,
    BagIndex,
    ByteSource,
    Chunk,
    Connection,
    Incomplete,
    check_compression,
    chunk_data,
    chunk_from,
    connection_from,
    decode_header,
    field_u32,
    index_record,
    read_record,
    record_at,
    record_op,
)
from darp.formats.realsense.rosbag1.scan import parse_chunk, scan
from darp.formats.realsense.rosbag1.usual import run_sums, usual_index
from darp.formats.realsense.rosbag1.write import (  # re-exported: the writer side of the format
    BAG_HEADER_RECORD_LENGTH,
    MAGIC,
    OP_BAG_HEADER,
    OP_CHUNK,
    OP_CHUNK_INFO,
    OP_CONNECTION,
    OP_INDEX_DATA,
    OP_MESSAGE,
    bag_header_record,
    chunk_head,
    chunk_info_record,
    compress_lz4,
    connection_record,
    encode_header,
    index_data_record,
    message_head,
    pack_time,
    record,
    record_head,
)

_U32 = struct.Struct("<I")


def load_index(source: ByteSource | memoryview, path: Path) -> BagIndex:
    """Parse the bag header and the index; rebuild the index by scanning when it is missing or cut."""
    src = source if isinstance(source, ByteSource) else ByteSource(source)
    if src.read(0, len(MAGIC)) != MAGIC:
        raise RecordingError("not a ROS1 bag (no '#ROSBAG V2.0' magic)", path)
    try:
        fields, data_start, data_len, _ = record_at(src, len(MAGIC), with_data=False)
        if record_op(fields) != OP_BAG_HEADER:
            raise DecodeError("first record is not a bag header")
        index_pos = struct.unpack("<Q", fields["index_pos"])[0]
        conn_count, chunk_count = field_u32(fields, "conn_count"), field_u32(fields, "chunk_count")
    except Incomplete:
        raise RecordingError(f"truncated bag header ({src.size} bytes): no chunk to read", path) from None
    except (ValueError, KeyError, struct.error) as err:
        raise RecordingError(f"corrupt bag header at byte offset {len(MAGIC)}: {err}", path) from err
    first = data_start + data_len
    if index_pos == 0:
        return scan(src, path, first, "no index (interrupted recording?)")
    if index_pos >= src.size:
        return scan(src, path, first, f"no index (cut short? its position {index_pos} lies past the end of the file)")
    try:
        return _indexed(src, path, index_pos, conn_count, chunk_count)
    except (Incomplete, ValueError, KeyError, struct.error) as err:
        return scan(src, path, first, f"unreadable index at byte offset {index_pos} ({str(err) or 'cut short'})")


def _indexed(src: ByteSource, path: Path, index_pos: int, conn_count: int, chunk_count: int) -> BagIndex:
    tail = src.read(index_pos, src.size - index_pos)  # the connection and chunk-info records
    connections, infos = _index_tail(tail, index_pos, conn_count + chunk_count)
    pairs, pairs_per_chunk = _chunk_info_pairs(tail, infos)
    usual = usual_index(src, [chunk_pos for chunk_pos, _, _ in infos], pairs, pairs_per_chunk)
    if usual is not None:
        chunks, rows, conn, numbers = usual
        return BagIndex(connections, chunks, _entries_from_table(rows, conn, numbers))
    return _indexed_general(src, path, connections, infos, pairs, pairs_per_chunk)


def _chunk_info_pairs(tail: bytes, infos: list[tuple[int, int, int]]) -> tuple[np.ndarray, np.ndarray]:
    """The (conn, count) pairs of the chunk infos ``(chunk position, data start, pair count)``, all in one
    array (u32), and how many per chunk; read from the data start whatever the record's data length."""
    starts = np.array([start for _, start, _ in infos], np.int64)
    per_chunk = np.array([count for _, _, count in infos], np.int64)
    past = np.flatnonzero(starts + 8 * per_chunk > len(tail))
    if len(past):  # the first such chunk info raises struct's own error, as unpacking it would
        struct.unpack_from(f"<{2 * infos[past[0]][2]}I", tail, infos[past[0]][1])
    run = np.repeat(np.arange(len(infos)), per_chunk)
    at = np.repeat(starts, per_chunk) + 8 * (np.arange(int(per_chunk.sum())) - (np.cumsum(per_chunk) - per_chunk)[run])
    data = np.frombuffer(tail, np.uint8)
    pairs = np.ascontiguousarray(data[at[:, None] + np.arange(8)]).view("<u4").reshape(-1, 2)
    return pairs, per_chunk


def _indexed_general(src: ByteSource, path: Path, connections: dict[int, Connection],
                     infos: list[tuple[int, int, int]], pairs: np.ndarray, pairs_per_chunk: np.ndarray) -> BagIndex:
    """Any layout: per chunk, parse its head and its index-data records one by one."""
    messages_per_chunk = run_sums(pairs[:, 1], pairs_per_chunk)
    guesses = [count * INDEX_HEAD.size + 12 * messages
               for count, messages in zip(pairs_per_chunk.tolist(), messages_per_chunk, strict=True)]
    rows: list[tuple[int, int, int, bytes]] = []  # (conn, chunk number, count, raw rows) per index-data record
    chunks: list[Chunk] = []
    ahead, ahead_pos = b"", 0  # bytes already read, from file offset ahead_pos: the next chunk's header
    for number, ((chunk_pos, _, conn_in_chunk), guess) in enumerate(zip(infos, guesses, strict=True)):
        skip = chunk_pos - ahead_pos
        head = ahead[skip:] if skip >= 0 and skip + _HEAD_HINT <= len(ahead) else src.read(chunk_pos, _HEAD_HINT)
        chunks.append(_chunk_at(src, head, chunk_pos, path))
        # the index-data records after the chunk: their usual size is known from the chunk info, and in the
        # usual layout they end where the next chunk starts, so the same read fetches that chunk's header
        index_start = chunks[-1].data_start + chunks[-1].data_len
        following = infos[number + 1][0] if number + 1 < len(infos) else -1
        want = guess + (_HEAD_HINT if following == index_start + guess else 0)
        while True:
            region = src.read(index_start, want)
            try:
                pos, found = 0, []
                for _ in range(conn_in_chunk):
                    conn, count, start, length = index_record(region, pos, len(region))
                    if count * 12 > length:
                        raise DecodeError(
                            f"index-data record at byte offset {index_start + pos} is shorter than its count")
                    found.append((conn, number, count, region[start:start + 12 * count]))
                    pos = start + length
                rows += found
                break
            except Incomplete:
                if len(region) < want:
                    raise
                want *= 4
        ahead, ahead_pos = region, index_start
    if not rows:
        return BagIndex(connections, chunks, {})
    conns, numbers, counts, raw = zip(*rows, strict=True)
    table = np.frombuffer(b"".join(raw), "<u4").reshape(-1, 3)
    return BagIndex(connections, chunks, _entries_from_table(table, np.repeat(np.array(conns, np.int64), counts),
                                                             np.repeat(np.array(numbers, np.int32), counts)))


def _entries_from_table(table: np.ndarray, conn: np.ndarray, numbers: np.ndarray) -> dict[int, np.ndarray]:
    """Per connection, its index entries sorted by (time, chunk, offset), from index-data rows (u32 sec,
    nsec, offset) with each row's connection and chunk number."""
    if not len(table):
        return {}
    conn = conn.astype(np.int64, copy=False)
    merged = np.empty(len(table), ENTRY_DTYPE)
    merged["time"] = table[:, 0].astype(np.int64) * 1_000_000_000 + table[:, 1]
    merged["chunk"] = numbers
    merged["offset"] = table[:, 2]
    # usually each connection's rows already come in (time, chunk, offset) order: a stable sort by
    # connection alone then gives the full order (checked); otherwise sort by all four keys
    order = np.argsort(conn.astype(np.uint16) if conn.max() < 1 << 16 else conn, kind="stable")
    conn, merged = conn[order], merged[order]
    if not _in_order(conn, merged):
        order = np.lexsort((merged["offset"], merged["chunk"], merged["time"], conn))
        conn, merged = conn[order], merged[order]
    cuts = [0, *(np.flatnonzero(np.diff(conn)) + 1).tolist(), len(conn)]
    return {int(conn[a]): merged[a:b] for a, b in itertools.pairwise(cuts) if b > a}


def _in_order(conn: np.ndarray, entries: np.ndarray) -> bool:
    """Whether rows sorted by connection are, within each connection, in (time, chunk, offset) order."""
    time, chunk, offset = entries["time"], entries["chunk"], entries["offset"]
    later = (conn[1:] != conn[:-1]) | (time[1:] > time[:-1])
    tie = time[1:] == time[:-1]
    later |= tie & (chunk[1:] > chunk[:-1])
    later |= tie & (chunk[1:] == chunk[:-1]) & (offset[1:] >= offset[:-1])
    return bool(later.all())


# The usual header layouts (fields in name order), each recognised with one struct unpack.
_CHUNK_INFO_HEAD = struct.Struct("<II10sQI6sII9sIII3sBI11sIII4sII")
_CHUNK_INFO_FIXED = (100, 18, b"chunk_pos=", 10, b"count=", 17, b"end_time=", 4, b"op=", OP_CHUNK_INFO, 19,
                     b"start_time=", 8, b"ver=")
_CHUNK_HEADS = {name: _U32.pack(len(h)) + h[:-4] for name in ("lz4", "none") for h in [
    encode_header({"compression": name.encode(), "op": bytes([OP_CHUNK]), "size": bytes(4)})]}
_HEAD_HINT = 128  # bytes read for a chunk record header


def _index_tail(tail: bytes, index_pos: int, records: int) -> tuple[dict[int, Connection], list[tuple[int, int, int]]]:
    """Connections and, per chunk in file order, (position, start of its chunk info's data in ``tail``,
    connections in it)."""
    connections: dict[int, Connection] = {}
    infos = []
    pos, end = 0, len(tail)
    for _ in range(records):
        if pos + _CHUNK_INFO_HEAD.size <= end:
            h = _CHUNK_INFO_HEAD.unpack_from(tail, pos)
            if (h[0], h[1], h[2], h[4], h[5], h[7], h[8], h[11], h[12], h[13], h[14], h[15], h[18], h[19]) == \
                    _CHUNK_INFO_FIXED:
                chunk_pos, count, start, length = h[3], h[6], pos + _CHUNK_INFO_HEAD.size, h[21]
                infos.append((chunk_pos, start, count))
                pos = start + length
                continue
        fields, start, length = read_record(tail, pos, end)
        op = record_op(fields)
        if op == OP_CONNECTION:
            conn = connection_from(fields, tail, start, length)
            connections[conn.conn_id] = conn
        elif op == OP_CHUNK_INFO:
            infos.append((struct.unpack("<Q", fields["chunk_pos"])[0], start, field_u32(fields, "count")))
        else:
            raise DecodeError(f"unexpected record op {op} in the index at byte offset {index_pos + pos}")
        pos = start + length
    if pos > end:
        raise Incomplete
    return connections, sorted(infos)


def _chunk_at(src: ByteSource, head: bytes, pos: int, path: Path) -> Chunk:
    """The chunk record whose first bytes are ``head``: the usual layouts directly, others parsed."""
    for compression, prefix in _CHUNK_HEADS.items():
        if head.startswith(prefix) and len(head) >= len(prefix) + 8:
            size, data_len = struct.unpack_from("<II", head, len(prefix))
            data_start = pos + len(prefix) + 8
            if data_start + data_len > src.size:
                raise Incomplete
            return Chunk(pos, data_start, data_len, compression, size)
    fields, data_start, data_len, _ = record_at(src, pos, with_data=False, hint=_HEAD_HINT)
    return chunk_from(fields, pos, data_start, data_len, path)


__all__ = [  # the record level of the format, its writer side and the index reader
    "BAG_HEADER_RECORD_LENGTH",
    "BagIndex",
    "ByteSource",
    "Chunk",
    "Connection",
    "ENTRY_DTYPE",
    "INDEX_HEAD",
    "Incomplete",
    "MAGIC",
    "OP_BAG_HEADER",
    "OP_CHUNK",
    "OP_CHUNK_INFO",
    "OP_CONNECTION",
    "OP_INDEX_DATA",
    "OP_MESSAGE",
    "bag_header_record",
    "check_compression",
    "chunk_data",
    "chunk_from",
    "chunk_head",
    "chunk_info_record",
    "compress_lz4",
    "connection_from",
    "connection_record",
    "decode_header",
    "encode_header",
    "field_u32",
    "index_data_record",
    "index_record",
    "load_index",
    "message_head",
    "pack_time",
    "parse_chunk",
    "read_record",
    "record",
    "record_at",
    "record_head",
    "record_op",
    "scan",
]
