"""ROS1 bag index, fast path: the chunk records and index-data records of a bag in the usual layout
(fields in name order, as rosbag's C++ writer, librealsense and darp write them; each chunk's index-data
records in chunk-info order, ending where the next chunk starts), read with one ``pread`` per chunk and
checked and parsed with numpy instead of per-record Python.

Every assumption is checked on the bytes read; if any fails, :func:`usual_index` answers ``None`` and
the caller takes the general path (:func:`darp.formats.realsense.rosbag1.index._indexed_general`), so the
result, and any error, is that of the general path.
"""

from __future__ import annotations

import os

import numpy as np

from darp.formats.realsense.rosbag1.records import INDEX_HEAD, ByteSource, Chunk
from darp.formats.realsense.rosbag1.write import OP_CHUNK, OP_INDEX_DATA, encode_header


def _chunk_prefix(compression: str) -> bytes:
    """The bytes of a usual chunk record up to its ``size`` value: header length, then fields in name order."""
    header = encode_header({"compression": compression.encode(), "op": bytes([OP_CHUNK]), "size": bytes(4)})
    return len(header).to_bytes(4, "little") + header[:-4]


_PREFIX_LZ4, _PREFIX_NONE = _chunk_prefix("lz4"), _chunk_prefix("none")
HEAD_SIZE = len(_PREFIX_NONE) + 8  # bytes read for a chunk head: the longer prefix, size u32, data length u32
_P_LZ4 = np.frombuffer(_PREFIX_LZ4, np.uint8)
_P_NONE = np.frombuffer(_PREFIX_NONE, np.uint8)

# An index-data record head (INDEX_HEAD): the bytes that are the same in every usual record, and where the
# conn, count and data-length values lie.
_INDEX_TEMPLATE = np.frombuffer(INDEX_HEAD.pack(47, 9, b"conn=", 0, 10, b"count=", 0, 4, b"op=", OP_INDEX_DATA,
                                                8, b"ver=", 0, 0), np.uint8)
_VALUE_AT = {"conn": 13, "count": 27, "ver": 47, "data_len": 51}
_INDEX_FIXED_AT = np.setdiff1d(np.arange(INDEX_HEAD.size),
                               np.concatenate([np.arange(at, at + 4) for at in _VALUE_AT.values()]))
_INDEX_VALUES = np.dtype({"names": list(_VALUE_AT), "formats": ["<u4"] * 4, "offsets": list(_VALUE_AT.values()),
                          "itemsize": INDEX_HEAD.size})


def run_sums(values: np.ndarray, counts: np.ndarray) -> list[int]:
    """Exact sums of consecutive runs of ``values``, ``counts`` items each (Python ints: no overflow)."""
    totals = np.concatenate([np.zeros(1, np.uint64), np.cumsum(values, dtype=np.uint64)]).tolist()
    ends = np.cumsum(counts).tolist()
    return [totals[end] - totals[end - count] for end, count in zip(ends, counts.tolist(), strict=True)]


def usual_index(src: ByteSource, chunk_positions: list[int], pairs: np.ndarray,
                pairs_per_chunk: np.ndarray) -> tuple[list[Chunk], np.ndarray, np.ndarray, np.ndarray] | None:
    """(chunks, rows, conn per row, chunk number per row), or ``None`` when the layout is not the usual one.

    ``chunk_positions`` are the chunk positions in file order; ``pairs`` the chunk infos' (conn, count) pairs, in
    that order, ``pairs_per_chunk`` of them per chunk. ``rows`` are the index entries (sec, nsec, offset)
    as u32, in file order.
    """
    n = len(chunk_positions)
    if n == 0 or max(chunk_positions) >= src.size:
        return None
    chunk_pos = np.array(chunk_positions, np.int64)
    counts = pairs[:, 1].astype(np.int64)
    record_size = INDEX_HEAD.size + 12 * counts
    index_size = np.array(run_sums(record_size, pairs_per_chunk), np.int64)
    if index_size.sum() > src.size:
        return None
    run = np.repeat(np.arange(n), pairs_per_chunk)  # each chunk-info pair's chunk number
    # one read per chunk: its index-data records (ending where the next chunk starts) and the next chunk's head
    index_start = np.empty(n, np.int64)
    index_start[:-1] = chunk_pos[1:] - index_size[:-1]
    if (index_start[:-1] < 0).any():
        return None
    fd = src._fd

    def read(length: int, at: int) -> bytes:
        return os.pread(fd, length, at) if fd is not None else src.read(at, length)

    parts = [read(HEAD_SIZE, int(chunk_pos[0]))]
    parts += [read(int(size) + HEAD_SIZE, int(start))
              for start, size in zip(index_start[:-1].tolist(), index_size[:-1].tolist(), strict=True)]
    if any(len(part) < HEAD_SIZE for part in parts):
        return None
    head = np.frombuffer(parts[-1], np.uint8, HEAD_SIZE, len(parts[-1]) - HEAD_SIZE)
    last = _head_values(head[None])
    if last is None:
        return None
    index_start[-1] = int(chunk_pos[-1]) + int(last[1][0]) + int(last[3][0])
    parts.append(read(int(index_size[-1]), int(index_start[-1])))
    if len(parts[-1]) < index_size[-1] or index_start[-1] + index_size[-1] > src.size:
        return None
    # what the reads hold, back to back: per chunk its head, then per index-data record (in chunk-info order)
    # its INDEX_HEAD and its rows; one kind label per byte then separates heads, record heads and rows
    buffer = np.frombuffer(b"".join(parts), np.uint8)
    records = len(counts)
    kinds = np.empty(n + 2 * records, np.uint8)
    lengths = np.empty(n + 2 * records, np.int64)
    head_seg = np.arange(n) + 2 * (np.cumsum(pairs_per_chunk) - pairs_per_chunk)
    record_seg = run + 1 + 2 * np.arange(records)
    kinds[head_seg], lengths[head_seg] = 0, HEAD_SIZE
    kinds[record_seg], lengths[record_seg] = 1, INDEX_HEAD.size
    kinds[record_seg + 1], lengths[record_seg + 1] = 2, 12 * counts
    if lengths.sum() != len(buffer):
        return None
    kind = np.repeat(kinds, lengths)
    values = _head_values(buffer[kind == 0].reshape(n, HEAD_SIZE))
    if values is None:
        return None
    is_lz4, head_len, size, data_len = values
    data_start = chunk_pos + head_len
    if (data_start + data_len != index_start).any():
        return None
    heads = buffer[kind == 1].reshape(records, INDEX_HEAD.size)
    if (heads[:, _INDEX_FIXED_AT] != _INDEX_TEMPLATE[_INDEX_FIXED_AT]).any():
        return None
    fields = heads.view(_INDEX_VALUES).ravel()
    if (fields["count"] != counts).any() or (fields["data_len"] != 12 * counts).any():
        return None
    rows = buffer[kind == 2].view("<u4").reshape(-1, 3)
    row_record = np.repeat(np.arange(records), counts)
    compression = np.where(is_lz4, "lz4", "none").tolist()
    chunks = list(map(Chunk, chunk_pos.tolist(), data_start.tolist(), data_len.tolist(), compression, size.tolist()))
    return chunks, rows, fields["conn"][row_record], run[row_record].astype(np.int32)


def _head_values(heads: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(is LZ4, head length, uncompressed size, data length) of usual chunk heads (rows of HEAD_SIZE bytes)."""
    is_lz4 = (heads[:, :len(_P_LZ4)] == _P_LZ4).all(1)
    is_none = (heads[:, :len(_P_NONE)] == _P_NONE).all(1)
    if not (is_lz4 | is_none).all():
        return None
    at = np.where(is_lz4, len(_P_LZ4), len(_P_NONE))
    size = np.ascontiguousarray(heads[np.arange(len(heads))[:, None], at[:, None] + np.arange(8)]).view("<u4")
    return is_lz4, at.astype(np.int64) + 8, size[:, 0].astype(np.int64), size[:, 1].astype(np.int64)
