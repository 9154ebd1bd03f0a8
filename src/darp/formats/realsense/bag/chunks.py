"""The uncompressed bytes of a bag's chunks, by chunk number, for
:class:`~darp.formats.realsense.bag.reader.BagRecording`.

Uncompressed chunks are read in place: read-only views into the file mapping. LZ4 chunks are decoded
(:mod:`darp.formats.realsense.rosbag1.lz4`) into pooled buffers, and the last few are cached. While frames are
streamed the reader announces the chunks it will need next (:meth:`ChunkStore.prefetch`); they are
decoded ahead on worker threads (the decoder releases the GIL), so decoding overlaps the consumer's own
work and, with two workers, uses two cores. A chunk the consumer needs that no worker has started yet (the
workers are busy or not scheduled) is decoded by the consumer itself rather than waited for.

A pooled buffer is written again only when no frame, view or array can still read it (its reference
count is back to the pool's own), so frames that a consumer keeps stay valid.

**Reading only what is needed.** The reader maps the file with ``MADV_RANDOM`` (no read-ahead on a page
fault), and the store asks the kernel for exactly the bytes a consumer will read (``willneed``: an
``MADV_WILLNEED`` of a byte range): a chunk's compressed bytes before they are decoded, an uncompressed
chunk when a frame of it is read or streamed (and the announced chunks ahead of it). While
:attr:`ChunkStore.headers_only` is set (the frame table, which reads a few bytes of each message) uncompressed
chunks are not asked for, so a frame table of an uncompressed bag reads the pages that hold the messages'
headers and metadata, not the images (on a cold page cache: tens of MB instead of the whole file).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from darp.errors import RecordingError
from darp.formats.realsense.rosbag1.index import Chunk, check_compression
from darp.formats.realsense.rosbag1.lz4 import ChunkBuffer, Lz4Error, decode_frame

_IDLE_BUFFERS = 6  # released buffers kept for reuse
_ADVISED = 64  # uncompressed chunks remembered as already asked for (a few syscalls saved per chunk)
_FORKS = [0]  # forks of this process so far (seen in the child): cheaper to check than os.getpid() per chunk
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=lambda: _FORKS.__setitem__(0, _FORKS[0] + 1))


class _Pool:
    """Decode buffers handed back by the cache, reused once nothing views them (thread-safe)."""

    def __init__(self) -> None:
        self._idle: deque[ChunkBuffer] = deque()
        self._lock = threading.Lock()

    def take(self, size: int) -> ChunkBuffer:
        with self._lock:
            for buffer in self._idle:
                if buffer.capacity >= size and not buffer.in_use():
                    self._idle.remove(buffer)
                    return buffer
        return ChunkBuffer(size)

    def give(self, buffer: ChunkBuffer) -> None:
        with self._lock:
            self._idle.append(buffer)
            if len(self._idle) > _IDLE_BUFFERS:  # still viewed by frames someone keeps: let them own it
                self._idle.popleft()


class ChunkStore:
    """Chunk bytes by chunk number: in-place views (uncompressed) or cached, pooled LZ4 decodes.

    ``threads`` workers decode announced chunks ahead (0: decode only on demand). Not thread-safe
    itself: one consumer calls :meth:`get` and :meth:`prefetch`. ``willneed(offset, length)`` (optional) asks
    the kernel for a byte range of the file that is about to be read (the reader's ``MADV_WILLNEED``).
    """

    def __init__(self, view: memoryview, chunks: list[Chunk], path: Path, verify: bool, threads: int = 2,
                 cache_size: int = 4, willneed: Callable[[int, int], None] | None = None) -> None:
        self._view, self._chunks, self._path, self._verify = view, chunks, path, verify
        self._willneed = willneed
        self._advised: OrderedDict[int, None] = OrderedDict()
        self.headers_only = False  # set while only the messages' headers are read: uncompressed chunks not asked for
        self._threads, self._cache_size = threads, cache_size
        self._cache: OrderedDict[int, tuple[ChunkBuffer, memoryview]] = OrderedDict()
        self._pending: dict[int, Future[tuple[ChunkBuffer, memoryview]]] = {}
        self._pool = _Pool()
        self._executor: ThreadPoolExecutor | None = None
        self._closed = False
        self._forks = _FORKS[0]
        self._decoding = any(chunk.compression != "none" for chunk in chunks)  # anything for the workers?

    def get(self, number: int) -> memoryview:
        """The uncompressed bytes of chunk ``number`` (read-only)."""
        if self._closed:
            raise RecordingError("recording is closed", self._path)
        if self._forks != _FORKS[0]:
            self._forked()
        chunk = self._chunks[number]
        if chunk.compression == "none":
            self._advise(number)
            return self._view[chunk.data_start:chunk.data_start + chunk.data_len]
        cached = self._cache.get(number)
        if cached is not None:
            self._cache.move_to_end(number)
            return cached[1]
        future = self._pending.pop(number, None)
        if future is not None and not future.cancel():  # being decoded (or done): wait for it
            decoded = future.result()
        else:  # not announced, or no worker has started it yet: decoding it here is the quickest way
            decoded = self._decode(number)
        self._cache[number] = decoded
        while len(self._cache) > self._cache_size:
            self._pool.give(self._cache.popitem(last=False)[1][0])
        return decoded[1]

    def prefetch(self, numbers: Iterable[int]) -> None:
        """Start decoding these LZ4 chunks (in this order) on the workers, a few at a time; ask the kernel for
        the uncompressed ones (unless :attr:`headers_only`)."""
        numbers = list(numbers)
        if self._willneed is not None and not self.headers_only and not self._closed:
            for number in numbers:
                if self._chunks[number].compression == "none":
                    self._advise(number)
        if self._threads <= 0 or self._closed or not self._decoding:
            return
        if self._forks != _FORKS[0]:
            self._forked()
        limit = 2 * self._threads
        for number in numbers:
            if len(self._pending) >= limit:
                break
            if number in self._pending or number in self._cache or self._chunks[number].compression == "none":
                continue
            if self._executor is None:
                self._executor = ThreadPoolExecutor(self._threads, thread_name_prefix="darp-bag-lz4")
            self._pending[number] = self._executor.submit(self._decode, number)

    def _forked(self) -> None:
        """In a child process (fork) the workers do not exist: forget them, their pending work and the
        pool's lock (a worker may have held it), and start afresh."""
        self._forks, self._executor, self._pending, self._pool = _FORKS[0], None, {}, _Pool()

    def _advise(self, number: int) -> None:
        """Ask the kernel for uncompressed chunk ``number`` once (recently asked ones are remembered)."""
        if self._willneed is None or self.headers_only or number in self._advised:
            return
        chunk = self._chunks[number]
        self._willneed(chunk.data_start, chunk.data_len)
        self._advised[number] = None
        if len(self._advised) > _ADVISED:
            self._advised.popitem(last=False)

    def cancel(self) -> None:
        """Forget chunks announced but not fetched (a stream that was abandoned)."""
        for future in self._pending.values():
            future.cancel()
        self._pending.clear()

    def _decode(self, number: int) -> tuple[ChunkBuffer, memoryview]:
        """Decode an LZ4 chunk into a pooled buffer (runs on worker threads too)."""
        chunk = self._chunks[number]
        check_compression(chunk, self._path)
        if self._willneed is not None:  # the compressed bytes are all read: one request, not a fault per page
            self._willneed(chunk.data_start, chunk.data_len)
        buffer = self._pool.take(chunk.size)
        try:
            decode_frame(self._view[chunk.data_start:chunk.data_start + chunk.data_len], buffer, chunk.size,
                         self._verify)
        except (Lz4Error, ValueError) as err:
            self._pool.give(buffer)
            raise RecordingError(f"corrupt LZ4 chunk at byte offset {chunk.pos}: {err}", self._path) from err
        return buffer, buffer.view(chunk.size)

    def close(self) -> None:
        """Stop the workers (waiting for a decode in progress: it reads the file mapping) and drop the cache."""
        self._closed = True
        self.cancel()
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        self._cache.clear()
