"""Walking chosen data messages of a bag in order, with their metadata, chunk by chunk.

Both frame streaming and the frame table (numbers, timestamps, domains of every frame) visit data
messages in an order (recording order, or file order for the table), each with the KeyValue metadata
messages stored at the same bag time. This module works out, with numpy, which metadata messages
belong to which frame and which chunks will be needed in what order, announces the upcoming chunks to
the :class:`~darp.formats.bag_chunks.ChunkStore` (which decodes LZ4 chunks ahead on worker threads),
and yields each message's bytes without any per-frame lookup in the index.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from darp.formats.bag_chunks import ChunkStore
from darp.formats.bag_frames import MetadataSource, message_span

_AHEAD = 8  # chunks announced ahead of the one being read (the store caps what is in flight)
_BLOCK = 1024  # visits prepared (as Python lists) at a time


class CorruptMessage(ValueError):
    """A message record that does not fit its chunk; ``chunk`` is the chunk's number."""

    def __init__(self, chunk: int, err: Exception) -> None:
        super().__init__(str(err))
        self.chunk = chunk


@dataclass(slots=True)
class Visit:
    """One data message: its stream (code into the walk's keys), position in that stream, bag time, the
    chunk bytes holding it and its data span, and where its metadata is (None: no metadata)."""

    code: int
    position: int
    time_ns: int
    chunk: int
    buf: memoryview
    start: int
    end: int
    metadata: MetadataSource | None


def walk(store: ChunkStore, data: list[np.ndarray], positions: list[np.ndarray], metadata: list[np.ndarray],
         file_order: bool = False, before_chunk: Callable[[int], None] | None = None) -> Iterator[Visit]:
    """Visit messages ``positions[k]`` of the index entries ``data[k]`` of each stream ``k``.

    ``metadata[k]`` are the index entries of stream ``k``'s metadata messages. Order: bag time (ties by
    chunk and offset), or ``file_order`` (chunk, offset). ``before_chunk(number)`` runs whenever the walk
    moves to another chunk (the reader checks it is open and releases streamed file pages there).
    A message that does not fit its chunk raises :class:`CorruptMessage`.
    """
    entries = [d[p] for d, p in zip(data, positions)]
    if not entries or sum(e.size for e in entries) == 0:
        return
    codes = np.concatenate([np.full(e.size, k, np.int64) for k, e in enumerate(entries)])
    position = np.concatenate(positions).astype(np.int64)
    merged = np.concatenate(entries)
    order = (np.lexsort((merged["offset"], merged["chunk"])) if file_order
             else np.lexsort((merged["offset"], merged["chunk"], merged["time"])))
    codes, position, merged = codes[order], position[order], merged[order]
    times, chunks, offsets = merged["time"], merged["chunk"].astype(np.int64), merged["offset"]
    lo, hi = np.zeros(codes.size, np.int64), np.zeros(codes.size, np.int64)
    first_meta, last_meta = chunks.copy(), chunks.copy()
    for k, meta in enumerate(metadata):
        mine = codes == k
        meta_times = meta["time"]
        lo[mine], hi[mine] = meta_times.searchsorted(times[mine], "left"), meta_times.searchsorted(times[mine], "right")
        has = mine & (hi > lo)
        first_meta[has], last_meta[has] = meta["chunk"][lo[has]], meta["chunk"][hi[has] - 1]
    # the chunks in the order they are first needed, and where each message's own chunk sits in that plan
    needed = np.stack([chunks, first_meta, last_meta], 1).ravel()
    fresh = np.ones(needed.size, bool)
    fresh[1:] = needed[1:] != needed[:-1]
    plan = needed[fresh]
    plan_at = np.cumsum(fresh)[::3] - 1

    get, announced = store.get, -1
    current, buf = -1, None
    for block in range(0, codes.size, _BLOCK):  # Python lists for one block at a time: memory stays flat
        window = slice(block, block + _BLOCK)
        meta_lists = _metadata_lists(metadata, codes[window], lo[window], hi[window])
        for code, pos, time_ns, chunk, offset, a, b, step in zip(
                codes[window].tolist(), position[window].tolist(), times[window].tolist(), chunks[window].tolist(),
                offsets[window].tolist(), lo[window].tolist(), hi[window].tolist(), plan_at[window].tolist()):
            if chunk != current:
                if before_chunk is not None:
                    before_chunk(chunk)
                if step > announced:
                    store.prefetch(plan[step + 1:step + 1 + _AHEAD].tolist())
                    announced = step
                buf, current = get(chunk), chunk
            try:
                start, end = message_span(buf, offset)
            except (ValueError, struct.error) as err:
                raise CorruptMessage(chunk, err) from err
            source = None
            if a < b:
                base, meta_chunks, meta_offsets = meta_lists[code]
                source = _metadata(get, chunk, buf, meta_chunks[a - base:b - base], meta_offsets[a - base:b - base])
            yield Visit(code, pos, time_ns, chunk, buf, start, end, source)


def _metadata_lists(metadata: list[np.ndarray], codes: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray) -> list[tuple[int, list[int], list[int]]]:
    """Per stream: (first metadata message used, chunk and offset lists from there) for a block of visits."""
    lists = []
    for k, meta in enumerate(metadata):
        mine = (codes == k) & (hi > lo)
        if not mine.any():
            lists.append((0, [], []))
            continue
        first, stop = int(lo[mine].min()), int(hi[mine].max())
        lists.append((first, meta["chunk"][first:stop].tolist(), meta["offset"][first:stop].tolist()))
    return lists


def _metadata(get: Callable[[int], memoryview], chunk: int, buf: memoryview, chunks: list[int],
              offsets: list[int]) -> MetadataSource:
    """A frame's metadata messages, holding the chunk buffers they lie in (``buf`` is chunk ``chunk``)."""
    first, last = chunks[0], chunks[-1]
    held = {first: buf if first == chunk else get(first)}
    if last != first:
        for other in set(chunks):
            if other not in held:
                held[other] = buf if other == chunk else get(other)
    return MetadataSource(held, chunks, offsets)


def visit_one(store: ChunkStore, data: np.ndarray, position: int, metadata: np.ndarray) -> Visit:
    """The single message ``position`` of the index entries ``data`` (random access: no plan, no workers)."""
    entry = data[position]
    time_ns, chunk, offset = int(entry["time"]), int(entry["chunk"]), int(entry["offset"])
    buf = store.get(chunk)
    try:
        start, end = message_span(buf, offset)
    except (ValueError, struct.error) as err:
        raise CorruptMessage(chunk, err) from err
    times = metadata["time"]
    lo, hi = int(times.searchsorted(time_ns, "left")), int(times.searchsorted(time_ns, "right"))
    source = None
    if lo < hi:
        source = _metadata(store.get, chunk, buf, metadata["chunk"][lo:hi].tolist(), metadata["offset"][lo:hi].tolist())
    return Visit(0, position, time_ns, chunk, buf, start, end, source)
