"""Reader for the ROS1 ``.bag`` recordings librealsense writes (file_version 3 and 4).

Opening maps the file and parses its index and the small static messages (device, streams,
extrinsics, depth units); pixels are decoded on demand. Uncompressed chunks are read in place through
``mmap`` (frames are zero-copy views); LZ4 chunks are decoded into pooled buffers, ahead of the consumer
on worker threads while frames are streamed (:mod:`darp.formats.realsense.bag.chunks`), so iterating a
recording uses memory that does not grow with its length. A frame's metadata dict is parsed only when it is
read. Streaming takes each usual message inline (:mod:`darp.formats.realsense.bag.stream`: a few
microseconds a frame) and anything unusual the general way (:meth:`BagRecording._frame`). A bag without a
usable index (an interrupted write, a cut copy) is read by scanning up to its last complete chunk and
flagged ``truncated``.

Frame arrays are read-only views (into the file or a decoded chunk); copy one to modify it.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from darp.errors import RecordingError
from darp.formats.realsense.bag import stream as bag_stream
from darp.formats.realsense.bag.chunks import ChunkStore
from darp.formats.realsense.bag.description import describe
from darp.formats.realsense.bag.frames import (
    DEFAULT_DOMAIN,
    BagFrame,
    ImageDecoder,
    header_stamp,
    imu_sample,
    message_span,
)
from darp.formats.realsense.bag.walk import CorruptMessage, Visit, Walk, visit_one
from darp.formats.realsense.recording import Recording, require_regular_file
from darp.formats.realsense.rosbag1.index import ByteSource, load_index
from darp.formats.realsense.types import FrameInfo, Salvage

_RELEASE_STEP = 8 << 20  # drop streamed file pages in steps of this many bytes
_LOW_LEVEL = (struct.error, ValueError, KeyError, IndexError, UnicodeDecodeError)


def _advise(handle: BinaryIO, advice: str) -> None:
    """Read-ahead hint for the open file (POSIX only; a no-op elsewhere)."""
    if hasattr(os, advice):
        os.posix_fadvise(handle.fileno(), 0, 0, getattr(os, advice))


def _map_advice(mm: mmap.mmap | None, advice: str, start: int = 0, length: int = 0) -> bool:
    """``madvise`` on (a range of) the mapping; False where the platform lacks it or refuses."""
    if mm is None or not hasattr(mm, "madvise") or not hasattr(mmap, advice):
        return False
    try:
        if length:
            mm.madvise(getattr(mmap, advice), start, length)
        else:
            mm.madvise(getattr(mmap, advice))
    except (OSError, ValueError):
        return False
    return True


def _default_threads() -> int:
    """LZ4 decoding workers: one per core, at most four (none on a single core). Decoding dominates an
    LZ4 read, so a single worker would only overlap the consumer's (small) share."""
    cores = os.cpu_count() or 1
    return min(cores, 4) if cores >= 2 else 0


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int


class BagRecording(Recording):
    """A librealsense ROS1 ``.bag`` opened for reading.

    Extras beyond :class:`Recording`: ``truncated`` (no usable index: frames were recovered by scanning
    complete chunks; ``salvage`` says what was missing and what was recovered, ``truncation_note`` the
    same in one line), ``depth_scale_source`` (``option``, ``frame`` or ``default``), ``compressions``
    (chunk compressions present), ``sensor_names`` and :meth:`topics`. ``verify_checksums=False`` skips
    the LZ4 content checksum (librealsense checks it; damage inside literal runs then goes unnoticed).
    ``decode_threads`` LZ4 chunks are decoded ahead on that many worker threads while frames are
    streamed (default: one per core, at most 4; 0: none).
    """

    def __init__(self, path: str | Path, *, verify_checksums: bool = True, decode_threads: int | None = None) -> None:
        self.path = Path(path)
        self._view: memoryview | None = None
        self._mm: mmap.mmap | None = None
        self._chunks: ChunkStore | None = None
        self._size = require_regular_file(self.path).st_size
        if self._size == 0:
            raise RecordingError("empty file (0 bytes): not a RealSense recording", self.path)
        try:
            handle = open(self.path, "rb")  # noqa: SIM115 (closed by the with below)
        except OSError as err:
            raise RecordingError(f"cannot open: {err.strerror}", self.path) from None
        with handle:
            try:
                self._mm = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
            except (OSError, ValueError) as err:
                raise RecordingError(f"cannot map the file: {err}", self.path) from None
            self._view = memoryview(self._mm)
            self._released = 0
            try:
                _advise(handle, "POSIX_FADV_RANDOM")  # the index is read in small scattered pieces
                self._index = load_index(ByteSource(self._view, handle.fileno()), self.path)
                _advise(handle, "POSIX_FADV_NORMAL")
                threads = _default_threads() if decode_threads is None else max(0, int(decode_threads))
                # No read-ahead on page faults: the frame table reads a few bytes per message, and read-ahead
                # (8 MB on some disks) made it read the whole file. What is read in full is asked for
                # explicitly (ChunkStore's willneed: a chunk before it is decoded or its frames are read).
                self._random = _map_advice(self._mm, "MADV_RANDOM")
                self._chunks = ChunkStore(self._view, self._index.chunks, self.path, verify_checksums, threads,
                                          willneed=self._willneed if self._random else None)
                self._describe()
            except BaseException as err:
                self.close()
                if isinstance(err, _LOW_LEVEL):
                    raise RecordingError(f"malformed recording: {err}", self.path) from err
                raise
        self._tables: dict[str, dict[str, np.ndarray]] = {}
        self._infos: dict[str, list[FrameInfo]] = {}
        self._decoders = {key: ImageDecoder() for key, profile in self.streams.items() if profile.is_image}
        self._inline = True  # usual messages parsed inline (bag_stream); False: all the general way

    def _describe(self) -> None:
        self.truncated, self.truncation_note = self._index.truncated, self._index.note
        self.compressions = sorted({chunk.compression for chunk in self._index.chunks})
        description = describe(self._index, lambda e: self._message(int(e["chunk"]), int(e["offset"])), self.path)
        self.file_version, self.device = description.file_version, description.device
        self.sensor_names, self.streams = description.sensor_names, description.streams
        self.depth_scale, self.depth_scale_source = description.depth_scale, description.depth_scale_source
        self._topics, self._types, self._tf = description.topics, description.types, description.tf
        self._data, self._metadata_entries = description.data, description.metadata
        if self._index.truncated:
            self.salvage = Salvage(self._index.problems, {key: self.frame_count(key) for key in self.streams},
                                   self.duration_s, len(self._index.chunks), self._index.truncated_at)

    def _willneed(self, offset: int, length: int) -> None:
        """Ask the kernel to read bytes ``offset .. offset + length`` of the file now (they are about to be read)."""
        start = offset - offset % mmap.PAGESIZE
        _map_advice(self._mm, "MADV_WILLNEED", start, min(length + offset - start, self._size - start))

    def _message(self, chunk: int, offset: int) -> tuple[memoryview, int, int]:
        """(chunk bytes, start, end) of the data of the message record at ``offset`` in chunk ``chunk``."""
        if self._chunks is None or self._view is None:
            raise RecordingError("recording is closed", self.path)
        buf = self._chunks.get(chunk)
        try:
            start, end = message_span(buf, offset)
        except (struct.error, ValueError):
            raise RecordingError(f"corrupt message record at offset {offset} of the chunk at byte offset "
                                 f"{self._index.chunks[chunk].pos}", self.path) from None
        return buf, start, end

    # -- frames ---------------------------------------------------------------------------------
    def _walk(self, keys: list[str], positions: list[np.ndarray], file_order: bool = False) -> Walk:
        """The chosen data messages (with their metadata) in recording order, or file order."""
        return Walk(self._check_open(), [self._data[k] for k in keys], positions,
                    [self._metadata_entries[k] for k in keys], file_order, self._before_chunk)

    def _before_chunk(self, chunk: int) -> None:
        self._check_open()
        self._release_before(self._index.chunks[chunk].data_start)

    def _corrupt(self, key: str, position: int, chunk: int, err: Exception) -> RecordingError:
        return RecordingError(f"corrupt {key} frame {position} in the chunk at byte offset "
                              f"{self._index.chunks[chunk].pos}: {err}", self.path)

    def _metadata_error(self, info: FrameInfo, err: Exception) -> RecordingError:
        return RecordingError(f"corrupt metadata of {info.stream} frame {info.index}: {err}", self.path)

    def _frame(self, key: str, visit: Visit) -> BagFrame:
        """The general way to make a frame of a message (:mod:`darp.formats.realsense.bag.stream` takes the usual
        ones inline)."""
        try:
            if key in self._decoders:
                seq, stamp_ms, data = self._decoders[key].decode(visit.buf, visit.start, visit.end)
            else:
                seq, stamp_ms, data = imu_sample(visit.buf, visit.start, key == "accel")
            domain = visit.metadata.domain() if visit.metadata is not None else DEFAULT_DOMAIN
        except _LOW_LEVEL as err:
            raise self._corrupt(key, visit.position, visit.chunk, err) from err
        info = FrameInfo(key, visit.position, seq, stamp_ms, domain, visit.time_ns)
        return BagFrame(info, data, None if visit.metadata is not None else {}, source=visit.metadata,
                        on_error=self._metadata_error)

    def _bad_record(self, err: CorruptMessage) -> RecordingError:
        return RecordingError(f"corrupt message record in the chunk at byte offset "
                              f"{self._index.chunks[err.chunk].pos}: {err}", self.path)

    def _check_streaming(self) -> None:
        if self._view is None:
            raise RecordingError("recording is closed", self.path)

    def _stream(self, keys: list[str], positions: list[np.ndarray]) -> Iterator[BagFrame]:
        walk = self._walk(keys, positions)
        frames: Generator[BagFrame, None, None]
        if self._inline:
            frames = bag_stream.frames(walk, keys, self._decoders, self._frame, self._check_streaming,
                                       self._metadata_error)
        else:
            frames = (self._frame(keys[visit.code], visit)
                      for visit in self._general_visits(walk, streaming=True))
        try:
            yield from frames
        except CorruptMessage as err:
            raise self._bad_record(err) from err
        finally:
            frames.close()
            if self._chunks is not None:
                self._chunks.cancel()

    def _general_visits(self, walk: Walk, streaming: bool = False) -> Iterator[Visit]:
        """Every message of ``walk`` parsed the general way (``_inline = False``: what the inline loops of
        :mod:`darp.formats.realsense.bag.stream` are tested against)."""
        current, buf = -1, memoryview(b"")
        for block in walk.blocks():
            for i, (chunk, step) in enumerate(zip(block.chunks, block.steps, strict=True)):
                if chunk != current:
                    buf, current = walk.enter(chunk, step), chunk
                visit = walk.visit(block, i, buf)
                if streaming:
                    self._check_streaming()
                yield visit

    def _frame_table(self, keys: list[str]) -> dict[str, dict[str, np.ndarray]]:
        """Frame number, timestamp and domain of every frame of ``keys``: one pass over their chunks in
        file order, built on first use and kept. Only the bytes of each message's header and metadata are
        read from uncompressed chunks (:attr:`ChunkStore.headers_only`: no image is paged in). Where those
        chunks are LZ4-compressed they are decoded in full, so other streams whose messages lie (nearly) all
        in them come along."""
        missing = [key for key in keys if key not in self._tables]
        if missing:
            chunks = self._chunk_numbers(missing)
            compressed = any(self._index.chunks[c].compression != "none" for c in chunks.tolist())
            for key in self.streams:
                if not compressed:
                    break
                extra = np.setdiff1d(self._chunk_numbers([key]), chunks)
                if key not in self._tables and key not in missing and extra.size <= max(2, chunks.size // 20):
                    missing.append(key)
                    chunks = np.union1d(chunks, extra)
            sizes = [self._data[key].size for key in missing]
            columns = [(np.zeros(n, np.int64), np.zeros(n, np.float64), np.full(n, DEFAULT_DOMAIN, object))
                       for n in sizes]

            def general(visit: Visit) -> None:
                numbers, stamps, domains = columns[visit.code]
                try:
                    numbers[visit.position], stamps[visit.position] = header_stamp(visit.buf, visit.start)
                    if visit.metadata is not None:
                        domains[visit.position] = visit.metadata.domain()
                except _LOW_LEVEL as err:
                    raise self._corrupt(missing[visit.code], visit.position, visit.chunk, err) from err

            walk = self._walk(missing, [np.arange(n) for n in sizes], file_order=True)
            store = self._check_open()
            store.headers_only = True
            try:
                if self._inline:
                    bag_stream.table(walk, columns, general)
                else:
                    for visit in self._general_visits(walk):
                        general(visit)
            except CorruptMessage as err:
                raise self._bad_record(err) from err
            finally:
                store.headers_only = False
                if self._chunks is not None:
                    self._chunks.cancel()
            for key, (numbers, stamps, domains) in zip(missing, columns, strict=True):
                self._tables[key] = {"frame_number": numbers, "timestamp_ms": stamps, "domain": domains}
        return self._tables

    def _chunk_numbers(self, keys: list[str]) -> np.ndarray:
        """The chunks holding the frames or metadata of streams ``keys``."""
        return np.unique(np.concatenate([self._data[k]["chunk"] for k in keys] +
                                        [self._metadata_entries[k]["chunk"] for k in keys]))

    # -- the Recording interface ----------------------------------------------------------------
    def frame_infos(self, stream: str) -> list[FrameInfo]:
        self.stream(stream)
        if stream not in self._infos:
            row, times = self._frame_table([stream])[stream], self._data[stream]["time"]
            self._infos[stream] = [
                FrameInfo(stream, i, n, t, d, r) for i, (n, t, d, r) in enumerate(zip(
                    row["frame_number"].tolist(), row["timestamp_ms"].tolist(), row["domain"].tolist(),
                    times.tolist(), strict=True))
            ]
        return list(self._infos[stream])

    def frame_count(self, stream: str) -> int:
        self.stream(stream)
        return int(self._data[stream].size)

    def timestamps_ms(self, stream: str) -> np.ndarray:
        self.stream(stream)
        return self._frame_table([stream])[stream]["timestamp_ms"].copy()

    @property
    def duration_s(self) -> float:
        """Span of recording times (bag times) over all streams, in seconds: read from the index alone."""
        times = [self._data[key]["time"] for key in self.streams if self._data[key].size]
        if not times:
            return 0.0
        return (max(int(t.max()) for t in times) - min(int(t.min()) for t in times)) / 1e9

    def read_frame(self, stream: str, index: int) -> BagFrame:
        chunks = self._check_open()
        self.stream(stream)
        count = self._data[stream].size
        if not 0 <= index < count:
            raise RecordingError(f"frame {index} of stream {stream!r} does not exist ({count} frames)", self.path)
        try:
            visit = visit_one(chunks, self._data[stream], index, self._metadata_entries[stream])
        except CorruptMessage as err:
            raise self._bad_record(err) from err
        return self._frame(stream, visit)

    def iter_frames(self, streams: Iterable[str] | None = None, start_ms: float | None = None,
                    stop_ms: float | None = None) -> Iterator[BagFrame]:
        self._check_open()
        keys = list(self.streams) if streams is None else list(dict.fromkeys(streams))
        for key in keys:
            self.stream(key)
        chosen = []
        if start_ms is not None or stop_ms is not None:
            tables = self._frame_table(keys)
        for key in keys:
            positions = np.arange(self._data[key].size)
            if start_ms is not None or stop_ms is not None:
                stamps = tables[key]["timestamp_ms"]
                keep = np.ones(stamps.size, bool)
                if start_ms is not None:
                    keep &= stamps >= start_ms
                if stop_ms is not None:
                    keep &= stamps < stop_ms
                positions = positions[keep]
            chosen.append(positions)
        return self._stream(keys, chosen)

    def _release_before(self, offset: int) -> None:
        """Drop already-streamed file pages from this process (they stay in the page cache): keeps the
        resident size of a long sequential read flat. Views still held simply fault their pages back."""
        end = offset - offset % mmap.PAGESIZE
        if end - self._released >= _RELEASE_STEP and self._mm is not None:
            self._mm.madvise(mmap.MADV_DONTNEED, self._released, end - self._released)
            self._released = end

    def extrinsics(self, source: str, target: str) -> np.ndarray:
        self.stream(source)
        self.stream(target)
        if source == target:
            return np.eye(4)
        missing = [key for key in (source, target) if key not in self._tf]
        if missing:
            raise RecordingError(f"no extrinsics for stream {missing[0]!r} in this recording", self.path)
        (group_s, T_source_ref), (group_t, T_target_ref) = self._tf[source], self._tf[target]
        if group_s != group_t:
            raise RecordingError(f"streams {source!r} and {target!r} have extrinsics in different groups", self.path)
        return T_target_ref @ np.linalg.inv(T_source_ref)

    def topics(self) -> list[TopicInfo]:
        """Every topic of the bag with its message type and message count."""
        return [TopicInfo(topic, self._types.get(topic, ""), int(entries.size))
                for topic, entries in self._topics.items()]

    @property
    def size_bytes(self) -> int:
        return self._size

    def _check_open(self) -> ChunkStore:
        """The chunk store of the open recording; :class:`RecordingError` once it is closed."""
        if self._view is None or self._chunks is None:
            raise RecordingError("recording is closed", self.path)
        return self._chunks

    def close(self) -> None:
        """Stop the decoding workers and release the mapping. Frames still holding views keep their
        pages alive until collected."""
        if self._chunks is not None:
            self._chunks.close()
            self._chunks = None
        if self._view is not None:
            with contextlib.suppress(BufferError):
                self._view.release()
            self._view = None
        if self._mm is not None:
            with contextlib.suppress(BufferError):  # frame arrays still view the mapping; it goes with the last
                self._mm.close()
            self._mm = None

    def __repr__(self) -> str:
        return f"BagRecording({os.fspath(self.path)!r}, streams={list(self.streams)})"
