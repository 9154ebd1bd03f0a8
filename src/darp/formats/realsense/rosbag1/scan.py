"""Rebuilding a ROS1 bag's index from its chunks, for bags without a usable one (an interrupted write
leaves ``index_pos = 0``; a cut copy loses the index at the end): every complete chunk is kept, adopting
its index-data records, or parsing the chunk itself when they are missing or cut.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from darp.errors import DecodeError, RecordingError
from darp.formats.realsense.rosbag1.records import (
    ENTRY_DTYPE,
    BagIndex,
    ByteSource,
    Chunk,
    Connection,
    Incomplete,
    chunk_data,
    chunk_from,
    connection_from,
    field_u32,
    read_record,
    record_at,
    record_op,
)
from darp.formats.realsense.rosbag1.write import OP_CHUNK, OP_CONNECTION, OP_INDEX_DATA, OP_MESSAGE

_Parts = dict[int, list[tuple[int, np.ndarray]]]  # conn -> [(chunk number, uint32 rows of sec, nsec, offset)]


def _add_index_data(parts: _Parts, conn: int, count: int, view: bytes | memoryview, start: int, length: int,
                    chunk_number: int) -> None:
    if count * 12 > length:
        raise DecodeError(f"index-data record at byte offset {start} is shorter than its count")
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
        op = record_op(fields)
        if op == OP_CONNECTION:
            conn = connection_from(fields, data, start, length)
            connections.setdefault(conn.conn_id, conn)
        elif op == OP_MESSAGE:
            sec, nsec = struct.unpack("<II", fields["time"])
            found.setdefault(field_u32(fields, "conn"), []).append((sec, nsec, pos))
        pos = start + length
    for conn_id, rows in found.items():
        parts.setdefault(conn_id, []).append((chunk_number, np.array(rows, "<u4").reshape(-1, 3)))


def scan(src: ByteSource, path: Path, pos: int, reason: str) -> BagIndex:
    """Rebuild the index from the chunks themselves, up to the last complete chunk."""
    size = src.size
    connections: dict[int, Connection] = {}
    chunks: list[Chunk] = []
    pending: _Parts = {}  # index data of the chunk being scanned
    parts: _Parts = {}
    cut_at = None
    problems = [reason]

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
        except (RecordingError, Incomplete, ValueError, KeyError, struct.error) as err:
            if not last:
                if isinstance(err, RecordingError):
                    raise
                raise RecordingError(f"corrupt chunk at byte offset {chunk.pos}: {err}", path) from err
            chunks.pop()
            problems.append(f"last chunk at byte offset {chunk.pos} is unreadable and was skipped")
            return
        for conn, arrays in found.items():
            parts.setdefault(conn, []).extend(arrays)

    while pos < size:
        try:
            fields, start, length, _ = record_at(src, pos, with_data=False)
            op = record_op(fields)
        except Incomplete:
            cut_at = pos
            problems.append(f"truncated at byte {pos}: last record incomplete ({size - pos} bytes ignored)")
            break
        except (ValueError, KeyError, struct.error):
            cut_at = pos
            problems.append(f"unreadable record at byte offset {pos} ({size - pos} bytes ignored)")
            break
        try:
            if op == OP_CHUNK:
                if chunks:
                    settle(last=False)
                pending = {}
                chunks.append(chunk_from(fields, pos, start, length, path))
            elif op == OP_INDEX_DATA and chunks:
                _add_index_data(pending, field_u32(fields, "conn"), field_u32(fields, "count"),
                                src.read(start, length), 0, length, len(chunks) - 1)
            elif op == OP_CONNECTION:
                conn = connection_from(fields, src.read(start, length), 0, length)
                connections.setdefault(conn.conn_id, conn)
        except (ValueError, KeyError, struct.error) as err:
            raise RecordingError(f"corrupt {_NAMES.get(op, 'record')} at byte offset {pos}: {err}", path) from err
        pos = start + length
    if chunks:
        settle(last=True)
    return BagIndex(connections, chunks, _sorted_entries(parts), truncated=True, problems=tuple(problems),
                    truncated_at=cut_at)


_NAMES = {OP_CHUNK: "chunk record", OP_INDEX_DATA: "index-data record", OP_CONNECTION: "connection record"}
