"""ROS1 bag format 2.0: the record constants and the pure encoders (the chunking writer is
:mod:`darp.formats.realsense.bag.writer`, the index reader :mod:`darp.formats.realsense.rosbag1.index`).

A bag is ``#ROSBAG V2.0\\n``, a 4096-byte bag header record (``index_pos``, ``conn_count``,
``chunk_count``), then chunk records, each followed by one index-data record per connection it holds,
then at ``index_pos`` every connection record and one chunk-info record per chunk. A record is
``uint32 header_len, header (fields "name=value", each uint32-length prefixed), uint32 data_len, data``.
Header fields are written in name order, like rosbag's C++ writer (and librealsense's copy of it).
"""

from __future__ import annotations

import struct
from typing import cast

import lz4.frame

from darp.formats.realsense.ros_messages import MessageType

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_INDEX_DATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7
BAG_HEADER_RECORD_LENGTH = 4096  # the whole record, length fields included (the rest is space padding)
_U32 = struct.Struct("<I")
# librealsense accepts only LZ4 frames with independent blocks, a content checksum and no stored size.
_LZ4_OPTIONS = {"block_size": lz4.frame.BLOCKSIZE_MAX4MB, "block_linked": False, "content_checksum": True,
                "store_size": False, "compression_level": 0}


def encode_header(fields: dict[str, bytes]) -> bytes:
    """Record header bytes (without its length), fields in name order like rosbag's C++ writer."""
    parts = []
    for name in sorted(fields):
        item = name.encode() + b"=" + fields[name]
        parts.append(_U32.pack(len(item)) + item)
    return b"".join(parts)


def pack_time(ns: int) -> bytes:
    return struct.pack("<II", ns // 1_000_000_000, ns % 1_000_000_000)


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
    return cast(bytes, lz4.frame.compress(raw, **_LZ4_OPTIONS))  # python-lz4 has no type information


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
