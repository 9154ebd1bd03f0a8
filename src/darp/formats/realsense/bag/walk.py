"""Walking chosen data messages of a bag in order, with their metadata, chunk by chunk.

Both frame streaming and the frame table (numbers, timestamps, domains of every frame) visit data
messages in an order (recording order, or file order for the table), each with the KeyValue metadata
messages stored at the same bag time. :class:`Walk` works out, with numpy, which metadata messages
belong to which frame and which chunks will be needed in what order; it hands the messages out as
:class:`Block`\\ s of plain lists (no per-frame lookup in the index), gives the chunk bytes as the
consumer moves from chunk to chunk (:meth:`Walk.enter`: that is where the upcoming chunks are announced to
the :class:`~darp.formats.realsense.bag.chunks.ChunkStore`, which decodes LZ4 chunks ahead on worker threads), and
parses any one message the general way (:meth:`Walk.visit`).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from darp.errors import DecodeError
from darp.formats.realsense.bag.chunks import ChunkStore
from darp.formats.realsense.bag.frames import MetadataSource, message_span

_AHEAD = 8  # chunks announced ahead of the one being read (the store caps what is in flight)
_BLOCK = 1024  # messages prepared (as Python lists) at a time


class CorruptMessage(DecodeError):
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


@dataclass(slots=True)
class Block:
    """Up to ``_BLOCK`` consecutive messages of a walk, one item per message in each list: stream code,
    position in its stream, bag time, chunk, offset of its record in the chunk, its metadata rows
    ``lo:hi`` and the step of the chunk plan it belongs to. ``metadata[code]`` is (first row, chunks,
    offsets) of the metadata rows that the block's messages of that stream use."""

    codes: list[int]
    positions: list[int]
    times: list[int]
    chunks: list[int]
    offsets: list[int]
    lo: list[int]
    hi: list[int]
    steps: list[int]
    metadata: list[tuple[int, list[int], list[int]]]


class Walk:
    """Messages ``positions[k]`` of the index entries ``data[k]`` of each stream ``k``.

    ``metadata[k]`` are the index entries of stream ``k``'s metadata messages. Order: bag time (ties by
    chunk and offset), or ``file_order`` (chunk, offset). ``before_chunk(number)`` runs whenever the
    consumer moves to another chunk (the reader checks it is open and releases streamed file pages there).
    """

    def __init__(self, store: ChunkStore, data: list[np.ndarray], positions: list[np.ndarray],
                 metadata: list[np.ndarray], file_order: bool = False,
                 before_chunk: Callable[[int], None] | None = None) -> None:
        self._store, self._metadata, self._before_chunk = store, metadata, before_chunk
        self.get = store.get
        self._announced = -1
        entries = [d[p] for d, p in zip(data, positions, strict=True)]
        self.size = sum(e.size for e in entries)
        if self.size == 0:
            return
        codes = np.concatenate([np.full(e.size, k, np.int64) for k, e in enumerate(entries)])
        position = np.concatenate(positions).astype(np.int64)
        merged = np.concatenate(entries)
        order = (np.lexsort((merged["offset"], merged["chunk"])) if file_order
                 else np.lexsort((merged["offset"], merged["chunk"], merged["time"])))
        codes, position, merged = codes[order], position[order], merged[order]
        times, chunks = merged["time"], merged["chunk"].astype(np.int64)
        lo, hi = np.zeros(codes.size, np.int64), np.zeros(codes.size, np.int64)
        first_meta, last_meta = chunks.copy(), chunks.copy()
        for k, meta in enumerate(metadata):
            mine = codes == k
            meta_times = meta["time"]
            lo[mine] = meta_times.searchsorted(times[mine], "left")
            hi[mine] = meta_times.searchsorted(times[mine], "right")
            has = mine & (hi > lo)
            first_meta[has], last_meta[has] = meta["chunk"][lo[has]], meta["chunk"][hi[has] - 1]
        # the chunks in the order they are first needed, and where each message's own chunk sits in that plan
        needed = np.stack([chunks, first_meta, last_meta], 1).ravel()
        fresh = np.ones(needed.size, bool)
        fresh[1:] = needed[1:] != needed[:-1]
        self._plan = needed[fresh]
        self._columns = (codes, position, times, chunks, merged["offset"], lo, hi, np.cumsum(fresh)[::3] - 1)

    def blocks(self) -> Iterator[Block]:
        """The messages, a block of Python lists at a time (memory stays flat)."""
        if self.size == 0:
            return
        for start in range(0, self.size, _BLOCK):
            window = slice(start, start + _BLOCK)
            codes, positions, times, chunks, offsets, lo, hi, steps = (c[window] for c in self._columns)
            yield Block(codes.tolist(), positions.tolist(), times.tolist(), chunks.tolist(), offsets.tolist(),
                        lo.tolist(), hi.tolist(), steps.tolist(),
                        _metadata_lists(self._metadata, codes, lo, hi))

    def enter(self, chunk: int, step: int) -> memoryview:
        """The bytes of ``chunk``, which the consumer moves to (plan step ``step``): announces the chunks
        that follow it to the store first."""
        if self._before_chunk is not None:
            self._before_chunk(chunk)
        if step > self._announced:
            self._store.prefetch(self._plan[step + 1:step + 1 + _AHEAD].tolist())
            self._announced = step
        return self._store.get(chunk)

    def visit(self, block: Block, i: int, buf: memoryview) -> Visit:
        """Message ``i`` of ``block`` (in chunk bytes ``buf``) parsed the general way: a record that does
        not fit its chunk raises :class:`CorruptMessage`."""
        code, lo, hi = block.codes[i], block.lo[i], block.hi[i]
        base, meta_chunks, meta_offsets = block.metadata[code]
        return _visit(self.get, code, block.positions[i], block.times[i], block.chunks[i], block.offsets[i],
                      meta_chunks[lo - base:hi - base], meta_offsets[lo - base:hi - base], buf)


def _metadata_lists(metadata: list[np.ndarray], codes: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray) -> list[tuple[int, list[int], list[int]]]:
    """Per stream: (first metadata message used, chunk and offset lists from there) for a block of visits."""
    lists: list[tuple[int, list[int], list[int]]] = []
    for k, meta in enumerate(metadata):
        mine = (codes == k) & (hi > lo)
        if not mine.any():
            lists.append((0, [], []))
            continue
        first, stop = int(lo[mine].min()), int(hi[mine].max())
        lists.append((first, meta["chunk"][first:stop].tolist(), meta["offset"][first:stop].tolist()))
    return lists


def metadata_source(get: Callable[[int], memoryview], chunk: int, buf: memoryview, chunks: list[int],
              offsets: list[int]) -> MetadataSource:
    """A frame's metadata messages, holding the chunk buffers they lie in (``buf`` is chunk ``chunk``)."""
    first, last = chunks[0], chunks[-1]
    held = {first: buf if first == chunk else get(first)}
    if last != first:
        for other in set(chunks):
            if other not in held:
                held[other] = buf if other == chunk else get(other)
    return MetadataSource(held, chunks, offsets)


def _visit(get: Callable[[int], memoryview], code: int, position: int, time_ns: int, chunk: int, offset: int,
           meta_chunks: list[int], meta_offsets: list[int], buf: memoryview | None = None) -> Visit:
    """One message parsed on its own: its span in its chunk and its metadata source."""
    if buf is None:
        buf = get(chunk)
    try:
        start, end = message_span(buf, offset)
    except (ValueError, struct.error) as err:
        raise CorruptMessage(chunk, err) from err
    source = metadata_source(get, chunk, buf, meta_chunks, meta_offsets) if meta_chunks else None
    return Visit(code, position, time_ns, chunk, buf, start, end, source)


def visit_one(store: ChunkStore, data: np.ndarray, position: int, metadata: np.ndarray) -> Visit:
    """The single message ``position`` of the index entries ``data`` (random access: no plan, no workers)."""
    entry = data[position]
    time_ns, chunk, offset = int(entry["time"]), int(entry["chunk"]), int(entry["offset"])
    buf = store.get(chunk)
    times = metadata["time"]
    lo, hi = int(times.searchsorted(time_ns, "left")), int(times.searchsorted(time_ns, "right"))
    return _visit(store.get, 0, position, time_ns, chunk, offset, metadata["chunk"][lo:hi].tolist(),
                  metadata["offset"][lo:hi].tolist(), buf)
