"""Reader for the ROS1 ``.bag`` recordings librealsense writes (file_version 3 and 4).

Opening maps the file and parses its index and the small static messages (device, streams,
extrinsics, depth units); pixels are decoded on demand. Uncompressed chunks are read in place through
``mmap`` (frames are zero-copy views), LZ4 chunks are decompressed one at a time, so iterating a
recording uses memory that does not grow with its length. A bag without a usable index (an
interrupted write, a cut copy) is read by scanning up to its last complete chunk and flagged
``truncated``.

Frame arrays are read-only views (into the file or a decompressed chunk); copy one to modify it.
"""

from __future__ import annotations

import mmap
import os
import struct
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from darp.errors import RecordingError
from darp.formats import ros_messages as rm
from darp.formats.recording import Recording
from darp.formats.recording_types import (
    STREAM_KEYS,
    DeviceInfo,
    Frame,
    FrameInfo,
    Intrinsics,
    MotionIntrinsics,
    StreamProfile,
)
from darp.formats.rosbag1 import ENTRY_DTYPE, BagIndex, ByteSource, chunk_data, load_index

_KEY_OF = {rs: key for key, rs in STREAM_KEYS.items()}
_DEFAULT_DOMAIN = "Hardware Clock"  # what librealsense reports for a frame without metadata
_U32 = struct.Struct("<I")
_HEADER_START = struct.Struct("<III")  # std_msgs/Header: seq, stamp sec, stamp nsec
_RELEASE_STEP = 8 << 20  # drop streamed file pages in steps of this many bytes
_LOW_LEVEL = (struct.error, ValueError, KeyError, IndexError, UnicodeDecodeError)


def _advise(handle: BinaryIO, advice: str) -> None:
    """Read-ahead hint for the open file (POSIX only; a no-op elsewhere)."""
    if hasattr(os, advice):
        os.posix_fadvise(handle.fileno(), 0, 0, getattr(os, advice))


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int


class _Chunks:
    """Uncompressed chunk bytes by chunk number: views into the file, or a few cached LZ4 chunks."""

    def __init__(self, view: memoryview, index: BagIndex, path: Path, verify: bool, capacity: int = 4) -> None:
        self._view, self._chunks, self._path, self._verify, self._capacity = view, index.chunks, path, verify, capacity
        self._cache: OrderedDict[int, bytes | memoryview] = OrderedDict()

    def get(self, number: int) -> bytes | memoryview:
        chunk = self._chunks[number]
        if chunk.compression == "none":
            return self._view[chunk.data_start:chunk.data_start + chunk.data_len]
        data = self._cache.get(number)
        if data is None:
            data = self._cache[number] = chunk_data(self._view, chunk, self._path, self._verify)
            if len(self._cache) > self._capacity:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(number)
        return data


class BagRecording(Recording):
    """A librealsense ROS1 ``.bag`` opened for reading.

    Extras beyond :class:`Recording`: ``truncated`` (no usable index: frames were recovered by scanning
    complete chunks; ``truncation_note`` says what was found), ``depth_scale_source`` (``option``,
    ``frame`` or ``default``), ``compressions`` (chunk compressions present), ``sensor_names`` and
    :meth:`topics`. ``verify_checksums=False`` skips the LZ4 content checksum (about twice as fast on
    LZ4 bags; damage inside literal runs then goes unnoticed).
    """

    def __init__(self, path: str | Path, *, verify_checksums: bool = True) -> None:
        self.path = Path(path)
        self._view: memoryview | None = None
        self._mm: mmap.mmap | None = None
        try:
            self._size = self.path.stat().st_size
        except OSError as err:
            raise RecordingError(f"cannot open: {err.strerror}", self.path) from None
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
                self._chunks = _Chunks(self._view, self._index, self.path, verify_checksums)
                self._load_description()
            except BaseException as err:
                self.close()
                if isinstance(err, _LOW_LEVEL):
                    raise RecordingError(f"malformed recording: {err}", self.path) from err
                raise
        self._table: dict[str, dict[str, np.ndarray]] | None = None
        self._infos: dict[str, list[FrameInfo]] = {}

    # -- opening --------------------------------------------------------------------------------
    def _load_description(self) -> None:
        self.truncated = self._index.truncated
        self.truncation_note = self._index.note
        self.compressions = sorted({chunk.compression for chunk in self._index.chunks})
        by_topic: dict[str, list[int]] = {}
        for conn in self._index.connections.values():
            by_topic.setdefault(conn.topic, []).append(conn.conn_id)
        self._topics = {topic: self._merged(ids) for topic, ids in sorted(by_topic.items())}
        self._types = {c.topic: c.msgtype for c in self._index.connections.values()}
        if not self._index.chunks:
            raise RecordingError(f"no complete chunk to read ({self.truncation_note or 'empty bag'})", self.path)
        if rm.FILE_VERSION_TOPIC not in self._topics:
            raise RecordingError("not a RealSense recording: the bag has no /file_version topic", self.path)
        self.file_version = self._first(rm.FILE_VERSION_TOPIC, rm.decode_uint32)
        info = {k: v for k, v in self._all(rm.DEVICE_INFO_TOPIC, rm.decode_key_value)}
        self.device = DeviceInfo(info.get("Name", ""), info.get("Serial Number", ""),
                                 info.get("Firmware Version", ""), info.get("Product Id", ""), info)
        self.sensor_names: dict[int, str] = {}
        depth_units: dict[int, float] = {}
        found: dict[tuple[str, int], dict] = {}
        for topic in self._topics:
            if match := rm.SENSOR_INFO_TOPIC.match(topic):
                names = dict(self._all(topic, rm.decode_key_value))
                self.sensor_names[int(match[1])] = names.get("Name", "")
            elif (match := rm.OPTION_VALUE_TOPIC.match(topic)) and match[2] in rm.DEPTH_UNITS_OPTIONS:
                depth_units[int(match[1])] = self._first(topic, rm.decode_float32)
            elif match := rm.STREAM_TOPIC.match(topic):
                key = _KEY_OF.get((match[2], int(match[3])))
                if key is not None:
                    parts = found.setdefault((key, int(match[1])), {})
                    parts["tf" if match[4].startswith("tf/") else match[4]] = topic
        self._data: dict[str, np.ndarray] = {}
        self._metadata_entries: dict[str, np.ndarray] = {}
        self._tf: dict[str, tuple[str, np.ndarray]] = {}
        streams = {}
        for (key, sensor), parts in found.items():
            if "info" not in parts:
                continue
            streams[key] = self._profile(key, sensor, parts)
            kind = "image" if streams[key].is_image else "imu"
            self._data[key] = self._topics.get(parts.get(f"{kind}/data", ""), np.empty(0, ENTRY_DTYPE))
            self._metadata_entries[key] = self._topics.get(parts.get(f"{kind}/metadata", ""), np.empty(0, ENTRY_DTYPE))
            if "tf" in parts:
                self._tf[key] = (parts["tf"].rsplit("/", 1)[1], self._first(parts["tf"], rm.decode_transform))
        order = list(STREAM_KEYS)
        self.streams = {key: streams[key] for key in sorted(streams, key=order.index)}
        self.depth_scale, self.depth_scale_source = self._depth_scale(depth_units)

    def _profile(self, key: str, sensor: int, parts: dict[str, str]) -> StreamProfile:
        stream_type, index = STREAM_KEYS[key]
        fps, encoding = self._first(parts["info"], rm.decode_stream_info)
        fmt = rm.FORMAT_OF_ENCODING.get(encoding, encoding.lower())
        intrinsics = motion = None
        width = height = 0
        if "info/camera_info" in parts:
            ci = self._first(parts["info/camera_info"], rm.decode_camera_info)
            coeffs = tuple(float(c) for c in (tuple(ci.D) + (0.0,) * 5)[:5])
            width, height = ci.width, ci.height
            intrinsics = Intrinsics(ci.width, ci.height, ci.K[0], ci.K[4], ci.K[2], ci.K[5], ci.model, coeffs)
        if "imu_intrinsic" in parts:
            data, noise, bias = self._first(parts["imu_intrinsic"], rm.decode_imu_intrinsic)
            motion = MotionIntrinsics(tuple(data), tuple(noise), tuple(bias))
        return StreamProfile(key, stream_type, index, sensor, fmt, fps, width, height, intrinsics, motion)

    def _depth_scale(self, depth_units: dict[int, float]) -> tuple[float, str]:
        depth = self.streams.get("depth")
        if depth is not None and depth.sensor_index in depth_units:
            return float(depth_units[depth.sensor_index]), "option"
        if depth_units:
            return float(next(iter(depth_units.values()))), "option"
        if depth is not None and self._data["depth"].size:
            buf, start, end = self._entry(self._data["depth"][0])
            units = rm.decode_image_head(buf, start, end).depth_units
            if units > 0:
                return float(units), "frame"
        return 0.001, "default"

    def _merged(self, conn_ids: list[int]) -> np.ndarray:
        arrays = [self._index.entries[c] for c in conn_ids if c in self._index.entries]
        if not arrays:
            return np.empty(0, ENTRY_DTYPE)
        if len(arrays) == 1:
            return arrays[0]
        merged = np.concatenate(arrays)
        return merged[np.lexsort((merged["offset"], merged["chunk"], merged["time"]))]

    def _message(self, chunk: int, offset: int) -> tuple[bytes | memoryview, int, int]:
        """(chunk bytes, start, end) of the data of the message record at ``offset`` in chunk ``chunk``."""
        if self._chunks is None:
            raise RecordingError("recording is closed", self.path)
        buf = self._chunks.get(chunk)
        try:
            (header_len,) = _U32.unpack_from(buf, offset)
            start = offset + 8 + header_len
            (data_len,) = _U32.unpack_from(buf, start - 4)
        except struct.error:
            start, data_len = len(buf) + 1, 0
        if start + data_len > len(buf):
            raise RecordingError(f"corrupt message record at offset {offset} of the chunk at byte offset "
                                 f"{self._index.chunks[chunk].pos}", self.path)
        return buf, start, start + data_len

    def _entry(self, entry: np.void) -> tuple[bytes | memoryview, int, int]:
        return self._message(int(entry["chunk"]), int(entry["offset"]))

    def _first(self, topic: str, decode):
        entries = self._topics.get(topic)
        if entries is None or entries.size == 0:
            raise RecordingError(f"topic {topic} has no message", self.path)
        buf, start, _ = self._entry(entries[0])
        return decode(buf, start)

    def _all(self, topic: str, decode) -> list:
        out = []
        for entry in self._topics.get(topic, np.empty(0, ENTRY_DTYPE)):
            buf, start, _ = self._entry(entry)
            out.append(decode(buf, start))
        return out

    # -- frames ---------------------------------------------------------------------------------
    def _frame_metadata(self, key: str, time_ns: int, only: str | None = None) -> dict[str, str]:
        """The KeyValue metadata of ``key``'s frame at bag time ``time_ns`` (up to key ``only``)."""
        entries = self._metadata_entries[key]
        times = entries["time"]
        lo, hi = int(times.searchsorted(time_ns, "left")), int(times.searchsorted(time_ns, "right"))
        metadata: dict[str, str] = {}
        current, buf = -1, b""
        for chunk, offset in zip(entries["chunk"][lo:hi].tolist(), entries["offset"][lo:hi].tolist()):
            if chunk != current:
                current, buf = chunk, self._chunks.get(chunk)
            k, v = rm.decode_key_value_record(buf, offset)
            metadata[k] = v
            if k == only:
                break
        return metadata

    def _frame(self, key: str, index: int, time_ns: int, chunk: int, offset: int) -> Frame:
        try:
            metadata = self._frame_metadata(key, time_ns)
            buf, start, end = self._message(chunk, offset)
            if self.streams[key].is_image:
                head = rm.decode_image_head(buf, start, end)
                seq, stamp_ms, data = head.seq, head.timestamp_ms, rm.image_pixels(buf, head)
            else:
                seq, stamp_ms, gyro, accel = rm.decode_imu(buf, start)
                data = np.array(accel if key == "accel" else gyro, dtype=np.float32)
        except _LOW_LEVEL as err:
            raise RecordingError(f"corrupt {key} frame {index} in the chunk at byte offset "
                                 f"{self._index.chunks[chunk].pos}: {err}", self.path) from err
        info = FrameInfo(key, index, seq, stamp_ms, metadata.get("timestamp_domain", _DEFAULT_DOMAIN), time_ns)
        return Frame(info, data, metadata)

    def _frame_table(self) -> dict[str, dict[str, np.ndarray]]:
        """Frame number, timestamp and domain of every frame, read in one pass over the chunks (file order)."""
        if self._table is not None:
            return self._table
        keys = list(self.streams)
        columns: dict[str, tuple[list, list, list]] = {key: ([], [], []) for key in keys}
        codes, positions, entries = self._selection(keys, [np.arange(self._data[k].size) for k in keys])
        order = np.lexsort((entries["offset"], entries["chunk"]))
        rows = (codes[order], positions[order], entries["time"][order], entries["chunk"][order], entries["offset"][order])
        for code, position, time_ns, chunk, offset in zip(*(row.tolist() for row in rows)):
            key = keys[code]
            try:  # Image and Imu both start with a std_msgs/Header: seq, stamp
                buf, start, _ = self._message(chunk, offset)
                seq, sec, nsec = _HEADER_START.unpack_from(buf, start)
                domain = self._frame_metadata(key, time_ns, only="timestamp_domain").get("timestamp_domain",
                                                                                          _DEFAULT_DOMAIN)
            except _LOW_LEVEL as err:
                raise RecordingError(f"corrupt {key} frame {position} in the chunk at byte offset "
                                     f"{self._index.chunks[chunk].pos}: {err}", self.path) from err
            numbers, stamps, domains = columns[key]
            numbers.append((position, seq))
            stamps.append(rm.ms_from_stamp(sec, nsec))
            domains.append(domain)
        self._table = {}
        for key, (numbers, stamps, domains) in columns.items():
            order = np.argsort([p for p, _ in numbers], kind="stable")
            self._table[key] = {"frame_number": np.array([n for _, n in numbers], np.int64)[order],
                                "timestamp_ms": np.array(stamps, np.float64)[order],
                                "domain": np.array(domains, object)[order]}
        return self._table

    def _selection(self, keys: list[str], positions: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stream code, position in stream, index entry) of the chosen frames of several streams."""
        codes = [np.full(p.size, code) for code, p in enumerate(positions)]
        entries = [self._data[key][p] for key, p in zip(keys, positions)]
        if not keys:
            return np.empty(0, int), np.empty(0, int), np.empty(0, ENTRY_DTYPE)
        return np.concatenate(codes), np.concatenate(positions), np.concatenate(entries)

    # -- the Recording interface ----------------------------------------------------------------
    def frame_infos(self, stream: str) -> list[FrameInfo]:
        self.stream(stream)
        if stream not in self._infos:
            row, times = self._frame_table()[stream], self._data[stream]["time"]
            self._infos[stream] = [
                FrameInfo(stream, i, int(n), float(t), str(d), int(r))
                for i, (n, t, d, r) in enumerate(zip(row["frame_number"], row["timestamp_ms"], row["domain"], times))
            ]
        return list(self._infos[stream])

    def frame_count(self, stream: str) -> int:
        self.stream(stream)
        return int(self._data[stream].size)

    def timestamps_ms(self, stream: str) -> np.ndarray:
        self.stream(stream)
        return self._frame_table()[stream]["timestamp_ms"].copy()

    def read_frame(self, stream: str, index: int) -> Frame:
        self._check_open()
        self.stream(stream)
        count = self._data[stream].size
        if not 0 <= index < count:
            raise RecordingError(f"frame {index} of stream {stream!r} does not exist ({count} frames)", self.path)
        entry = self._data[stream][index]
        return self._frame(stream, int(index), int(entry["time"]), int(entry["chunk"]), int(entry["offset"]))

    def iter_frames(self, streams: Iterable[str] | None = None, start_ms: float | None = None,
                    stop_ms: float | None = None) -> Iterator[Frame]:
        self._check_open()
        keys = list(self.streams) if streams is None else list(dict.fromkeys(streams))
        for key in keys:
            self.stream(key)
        chosen = []
        for key in keys:
            positions = np.arange(self._data[key].size)
            if start_ms is not None or stop_ms is not None:
                stamps = self._frame_table()[key]["timestamp_ms"]
                keep = np.ones(stamps.size, bool)
                if start_ms is not None:
                    keep &= stamps >= start_ms
                if stop_ms is not None:
                    keep &= stamps < stop_ms
                positions = positions[keep]
            chosen.append(positions)
        return self._stream(keys, *self._selection(keys, chosen))

    def _stream(self, keys: list[str], codes: np.ndarray, positions: np.ndarray,
                entries: np.ndarray) -> Iterator[Frame]:
        starts = [chunk.data_start for chunk in self._index.chunks]
        order = np.lexsort((entries["offset"], entries["chunk"], entries["time"]))
        columns = (codes[order], positions[order], entries["time"][order], entries["chunk"][order],
                   entries["offset"][order])
        for code, position, time_ns, chunk, offset in zip(*(column.tolist() for column in columns)):
            self._check_open()
            self._release_before(starts[chunk])
            yield self._frame(keys[code], position, time_ns, chunk, offset)

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
        return [TopicInfo(topic, self._types.get(topic, ""), int(entries.size)) for topic, entries in self._topics.items()]

    @property
    def size_bytes(self) -> int:
        return self._size

    def _check_open(self) -> None:
        if self._view is None:
            raise RecordingError("recording is closed", self.path)

    def close(self) -> None:
        """Release the mapping. Frames still holding views keep their pages alive until collected."""
        self._chunks = None  # type: ignore[assignment]
        if self._view is not None:
            try:
                self._view.release()
            except BufferError:
                pass
            self._view = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:  # frame arrays still view the mapping; it goes with the last of them
                pass
            self._mm = None

    def __repr__(self) -> str:
        return f"BagRecording({os.fspath(self.path)!r}, streams={list(self.streams)})"
