"""Writer of ROS1 ``.bag`` recordings in librealsense's layout, playable by pyrealsense2.

What is written (device index 0): at bag time 1 ns ``/file_version`` (4), the device and sensor info,
the ``Depth_Units`` option, and per stream its StreamInfo, CameraInfo or ImuIntrinsic and its extrinsics
from depth (``tf/0``); then per frame an Image (with librealsense's ``depth_units`` trailer) or an Imu
message at its recording time, followed by KeyValue metadata at the same time (``system_time``,
``timestamp_domain``, ``Frame Counter``, ``Frame Timestamp``, plus any given).

Interrupted writes: data goes to ``<name>.bag.partial``; only :meth:`BagWriter.close` writes the index and
renames the file to ``<name>.bag``. An exception inside ``with BagWriter(...)`` (or :meth:`abort`) leaves
the ``.partial`` file, without an index, holding every frame written so far in complete chunks; darp's
reader opens it by scanning (``truncated`` is set). Memory stays at one open chunk. Identical inputs give
byte-identical files (nothing depends on the wall clock).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Self, cast

import lz4.frame
import numpy as np

from darp.errors import RecordingError
from darp.formats.realsense import ros_messages as rm
from darp.formats.realsense.rosbag1 import index as bag
from darp.formats.realsense.types import (
    PIXEL_FORMATS,
    STREAM_KEYS,
    TIMESTAMP_DOMAINS,
    DeviceInfo,
    MotionIntrinsics,
    StreamProfile,
)
from darp.geometry.rigid import check_rigid

FILE_VERSION = 4
STATIC_TIME_NS = 1  # librealsense drops static messages at 0 ns and ignores them at any other time
DEFAULT_LEAD_MS = 100.0  # default recording start: this long before the first frame written
SENSOR_NAMES = {"depth": "Stereo Module", "ir1": "Stereo Module", "ir2": "Stereo Module",
                "color": "RGB Camera", "accel": "Motion Module", "gyro": "Motion Module"}
MOTION_FORMAT = "motion_xyz32f"
_IDENTITY_IMU = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
_DEPTH_UNITS_DESCRIPTION = "Number of meters represented by a single depth unit"


class BagWriter:
    """Write one camera's recording, frame by frame, with bounded memory.

    ``extrinsics`` maps a stream key to ``T_stream_depth`` (4x4, maps depth-frame points into that
    stream's frame); depth itself is the identity. Recording times default to the frame timestamp minus
    an origin (``start_ms``, by default 100 ms before the first frame written). Use as a context manager.
    """

    def __init__(self, path: str | Path, device: DeviceInfo, streams: Sequence[StreamProfile], *,
                 depth_scale: float = 0.001, extrinsics: Mapping[str, np.ndarray] | None = None,
                 compression: str = "lz4", chunk_threshold: int = 768 * 1024, start_ms: float | None = None,
                 sensor_names: Mapping[int, str] | None = None, overwrite: bool = False,
                 lz4_acceleration: int = 1) -> None:
        self.path = Path(path)
        self.partial_path = self.path.with_name(self.path.name + ".partial")
        self._handle = None
        self._check_setup(streams, depth_scale, extrinsics or {}, compression, chunk_threshold)
        if not (isinstance(lz4_acceleration, int | np.integer) and 1 <= lz4_acceleration <= 65537):
            raise RecordingError(f"lz4_acceleration must be an integer in [1, 65537], not {lz4_acceleration!r}",
                                 self.path)
        for target in (self.path, self.partial_path):
            if target.exists() and not overwrite:
                raise RecordingError("already exists (pass overwrite=True to replace it)", target)
        self.streams = {profile.key: profile for profile in streams}
        self.depth_scale = float(depth_scale)
        self._origin_ms = start_ms
        self._last: dict[str, tuple[float, int]] = {}
        self.frames_written = dict.fromkeys(self.streams, 0)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._handle = open(self.partial_path, "wb")  # noqa: SIM115 (closed in close/abort)
            self._bag = _ChunkedBag(self._handle, compression, chunk_threshold, int(lz4_acceleration))
            self._write_description(device, extrinsics or {}, sensor_names or {})
        except OSError as err:
            self._fail()
            raise RecordingError(f"cannot write: {err.strerror or err}", self.partial_path) from err

    # -- validation -----------------------------------------------------------------------------
    def _check_setup(self, streams: Sequence[StreamProfile], depth_scale: float,
                     extrinsics: Mapping[str, np.ndarray], compression: str, chunk_threshold: int) -> None:
        def bad(message: str) -> RecordingError:
            return RecordingError(message, self.path)

        if self.path.suffix != ".bag":
            raise bad("a ROS1 recording must have the .bag extension (librealsense picks its reader by it)")
        if not streams:
            raise bad("no streams to record")
        keys = [profile.key for profile in streams]
        if len(set(keys)) != len(keys):
            raise bad(f"duplicate stream keys in {keys}")
        for p in streams:
            if STREAM_KEYS.get(p.key) != (p.stream_type, p.index):
                raise bad(f"stream {p.key!r} must be {STREAM_KEYS.get(p.key, 'a known stream key')}, "
                          f"not ({p.stream_type!r}, {p.index})")
            if p.fps <= 0:
                raise bad(f"stream {p.key!r}: fps must be positive, not {p.fps}")
            if p.is_image:
                if p.format not in PIXEL_FORMATS:
                    raise bad(f"stream {p.key!r}: format {p.format!r} is not one of {sorted(PIXEL_FORMATS)}")
                if p.intrinsics is None or (p.intrinsics.width, p.intrinsics.height) != (p.width, p.height):
                    raise bad(f"stream {p.key!r}: needs intrinsics of its own size {p.width}x{p.height}")
                if p.width <= 0 or p.height <= 0:
                    raise bad(f"stream {p.key!r}: width and height must be positive")
            elif p.format != MOTION_FORMAT:
                raise bad(f"stream {p.key!r}: motion streams have format {MOTION_FORMAT!r}, not {p.format!r}")
        if not (math.isfinite(depth_scale) and depth_scale > 0):
            raise bad(f"depth_scale must be a positive number of metres, not {depth_scale}")
        for key, T in extrinsics.items():
            if key not in keys:
                raise bad(f"extrinsics given for {key!r}, which is not a recorded stream ({', '.join(keys)})")
            check_rigid(T, f"extrinsics of {key!r}", self.path, error=RecordingError)
        if extrinsics and "depth" not in keys:
            raise bad("extrinsics are relative to the depth stream, which is not recorded")
        if compression not in ("lz4", "none"):
            raise bad(f"compression must be 'lz4' or 'none', not {compression!r}")
        if chunk_threshold < 1:
            raise bad(f"chunk_threshold must be positive, not {chunk_threshold}")

    def _stream_for(self, key: str, image: bool) -> StreamProfile:
        if self._handle is None:
            raise RecordingError("writer is closed", self.path)
        profile = self.streams.get(key)
        if profile is None:
            raise RecordingError(f"no stream {key!r} in this recording (streams: {', '.join(self.streams)})", self.path)
        if profile.is_image != image:
            kind = "write_image" if profile.is_image else "write_motion"
            raise RecordingError(f"stream {key!r} takes {kind}()", self.path)
        return profile

    def _times(self, key: str, timestamp_ms: float, frame_number: int, domain: str,
               recording_time_ns: int | None) -> int:
        """Validate a frame's clocks; return its recording time in ns."""
        if not math.isfinite(timestamp_ms):
            raise RecordingError(f"{key}: timestamp {timestamp_ms} is not finite", self.path)
        if not (isinstance(frame_number, int | np.integer) and 0 <= frame_number < 2**32):
            raise RecordingError(f"{key}: frame number {frame_number!r} is not an unsigned 32-bit integer", self.path)
        if domain not in TIMESTAMP_DOMAINS:
            raise RecordingError(f"{key}: timestamp domain {domain!r} is not one of {TIMESTAMP_DOMAINS}", self.path)
        if recording_time_ns is None:
            if self._origin_ms is None:
                self._origin_ms = timestamp_ms - DEFAULT_LEAD_MS
            recording_time_ns = round((timestamp_ms - self._origin_ms) * 1e6)
        if recording_time_ns <= STATIC_TIME_NS:
            raise RecordingError(f"{key}: recording time {recording_time_ns} ns must be after the description "
                                 f"at {STATIC_TIME_NS} ns (frame earlier than the recording start; pass start_ms)",
                                 self.path)
        last = self._last.get(key)
        if last is not None and not (timestamp_ms > last[0] and recording_time_ns > last[1]):
            raise RecordingError(f"{key}: frame at {timestamp_ms} ms / {recording_time_ns} ns does not come after "
                                 f"the previous one at {last[0]} ms / {last[1]} ns", self.path)
        self._last[key] = (timestamp_ms, int(recording_time_ns))
        return int(recording_time_ns)

    # -- writing --------------------------------------------------------------------------------
    def _static(self, topic: str, msgtype: rm.MessageType, payload: bytes) -> None:
        self._bag.write(self._bag.connection(topic, msgtype), STATIC_TIME_NS, payload)

    def _write_description(self, device: DeviceInfo, extrinsics: Mapping[str, np.ndarray],
                           sensor_names: Mapping[int, str]) -> None:
        self._static(rm.FILE_VERSION_TOPIC, rm.UINT32, rm.encode_uint32(FILE_VERSION))
        info = {"Name": device.name, "Serial Number": device.serial, "Firmware Version": device.firmware,
                "Product Id": device.product_id}
        info = {k: v for k, v in info.items() if v} | {k: v for k, v in device.info.items() if k not in info}
        for key, value in info.items():
            self._static(rm.DEVICE_INFO_TOPIC, rm.KEY_VALUE, rm.encode_key_value(key, str(value)))
        sensors: dict[int, str] = {}
        for p in self.streams.values():
            sensors.setdefault(p.sensor_index, sensor_names.get(p.sensor_index, SENSOR_NAMES[p.key]))
        for index, name in sorted(sensors.items()):
            self._static(f"{rm.sensor_prefix(index)}/info", rm.KEY_VALUE, rm.encode_key_value("Name", name))
        if "depth" in self.streams:
            option = f"{rm.sensor_prefix(self.streams['depth'].sensor_index)}/option/Depth_Units"
            self._static(f"{option}/value", rm.FLOAT32, rm.encode_float32(self.depth_scale))
            self._static(f"{option}/description", rm.STRING, rm.encode_string(_DEPTH_UNITS_DESCRIPTION))
        for p in self.streams.values():
            prefix = rm.stream_prefix(p.sensor_index, p.stream_type, p.index)
            encoding = PIXEL_FORMATS[p.format][0] if p.is_image else MOTION_FORMAT.upper()
            self._static(f"{prefix}/info", rm.STREAM_INFO, rm.encode_stream_info(p.fps, encoding))
            if p.is_image:
                k = p.intrinsics
                assert k is not None  # _check_setup requires intrinsics of image streams
                payload = rm.encode_camera_info(k.width, k.height, k.fx, k.fy, k.ppx, k.ppy, k.model, k.coeffs)
                self._static(f"{prefix}/info/camera_info", rm.CAMERA_INFO, payload)
            else:
                m = p.motion_intrinsics or MotionIntrinsics(_IDENTITY_IMU)
                payload = rm.encode_imu_intrinsic(m.data, m.noise_variances, m.bias_variances)
                self._static(f"{prefix}/imu_intrinsic", rm.IMU_INTRINSIC, payload)
            if p.key == "depth" or p.key in extrinsics:
                T = np.eye(4) if p.key == "depth" else np.asarray(extrinsics[p.key], dtype=np.float64)
                self._static(f"{prefix}/tf/0", rm.TRANSFORM, rm.encode_transform(T))

    def write_image(self, stream_key: str, image: np.ndarray, timestamp_ms: float, frame_number: int, *,
                    timestamp_domain: str = "Global Time", recording_time_ns: int | None = None,
                    system_time_ms: float | None = None, metadata: Mapping[str, int] | None = None) -> None:
        """Append an image frame: H x W (z16 uint16, y8 uint8, y16 uint16) or H x W x C (rgb8, bgr8, ...)."""
        p = self._stream_for(stream_key, image=True)
        encoding, dtype, channels = PIXEL_FORMATS[p.format]
        shape = (p.height, p.width) if channels == 1 else (p.height, p.width, channels)
        pixels = np.asarray(image)
        if pixels.shape != shape or pixels.dtype != np.dtype(dtype):
            raise RecordingError(f"{stream_key}: image is {pixels.dtype} {pixels.shape}, the {p.format} stream "
                                 f"takes {np.dtype(dtype)} {shape}", self.path)
        time_ns = self._times(stream_key, timestamp_ms, frame_number, timestamp_domain, recording_time_ns)
        flat = np.ascontiguousarray(pixels).reshape(-1).view(np.uint8).data  # a memoryview of the pixels
        head = rm.encode_image_head(int(frame_number), timestamp_ms, p.width, p.height, encoding,
                                    p.width * channels * pixels.itemsize, flat.nbytes)
        trailer = rm.encode_float32(self.depth_scale if stream_key == "depth" else 0.0)
        prefix = rm.stream_prefix(p.sensor_index, p.stream_type, p.index)
        self._frame(f"{prefix}/image", rm.IMAGE, time_ns, (head, flat, trailer), timestamp_ms, frame_number,
                    timestamp_domain, system_time_ms, metadata)
        self.frames_written[stream_key] += 1

    def write_motion(self, stream_key: str, xyz: Sequence[float] | np.ndarray, timestamp_ms: float,
                     frame_number: int, *, timestamp_domain: str = "Global Time",
                     recording_time_ns: int | None = None, system_time_ms: float | None = None,
                     metadata: Mapping[str, int] | None = None) -> None:
        """Append an IMU sample: accel in m/s^2 or gyro in rad/s, stored as float32 like librealsense."""
        p = self._stream_for(stream_key, image=False)
        values = np.asarray(xyz, dtype=np.float64).reshape(-1)
        if values.shape != (3,) or not np.isfinite(values).all():
            raise RecordingError(f"{stream_key}: a motion sample is 3 finite numbers, not {values.tolist()}", self.path)
        time_ns = self._times(stream_key, timestamp_ms, frame_number, timestamp_domain, recording_time_ns)
        x, y, z = (float(v) for v in values.astype(np.float32))
        sample = (x, y, z)
        zero = (0.0, 0.0, 0.0)
        payload = rm.encode_imu(int(frame_number), timestamp_ms, sample if p.key == "gyro" else zero,
                                sample if p.key == "accel" else zero)
        prefix = rm.stream_prefix(p.sensor_index, p.stream_type, p.index)
        self._frame(f"{prefix}/imu", rm.IMU, time_ns, (payload,), timestamp_ms, frame_number, timestamp_domain,
                    system_time_ms, metadata)
        self.frames_written[stream_key] += 1

    def _frame(self, base: str, msgtype: rm.MessageType, time_ns: int, parts: tuple[bytes | memoryview, ...],
               timestamp_ms: float, frame_number: int, domain: str, system_time_ms: float | None,
               metadata: Mapping[str, int] | None) -> None:
        """The frame's data message, then its metadata KeyValues at the same bag time."""
        items = {"system_time": f"{timestamp_ms if system_time_ms is None else system_time_ms:.6f}",
                 "timestamp_domain": domain, "Frame Counter": str(int(frame_number)),
                 "Frame Timestamp": str(round(timestamp_ms * 1000.0))}  # microseconds, like the device's
        items |= {str(k): str(int(v)) for k, v in (metadata or {}).items()}
        try:
            self._bag.write(self._bag.connection(f"{base}/data", msgtype), time_ns, *parts)
            conn = self._bag.connection(f"{base}/metadata", rm.KEY_VALUE)
            for key, value in items.items():
                self._bag.write(conn, time_ns, rm.encode_key_value(key, value))
        except OSError as err:
            self.abort()
            raise RecordingError(f"cannot write: {err.strerror or err}", self.partial_path) from err

    # -- finishing ------------------------------------------------------------------------------
    def close(self) -> None:
        """Write the index, make the file durable and rename it to its final name."""
        if self._handle is None:
            return
        try:
            self._bag.finish()
            self._handle.flush()
            os.fsync(self._handle.fileno())
            self._handle.close()
            self._handle = None
            os.replace(self.partial_path, self.path)
            with contextlib.suppress(OSError):
                directory = os.open(self.path.parent, os.O_RDONLY)
                try:
                    os.fsync(directory)
                finally:
                    os.close(directory)
        except OSError as err:
            self._fail()
            raise RecordingError(f"cannot finish the recording: {err.strerror or err}", self.partial_path) from err

    def abort(self) -> None:
        """Stop without an index: keep the ``.partial`` file with every complete chunk written so far."""
        if self._handle is None:
            return
        with contextlib.suppress(OSError):
            self._bag.flush_chunk()
        self._fail()

    def _fail(self) -> None:
        if self._handle is not None:
            with contextlib.suppress(OSError):
                self._handle.close()
            self._handle = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _compress_lz4_fast(raw: bytes | bytearray, level: int) -> bytes:
    """An LZ4 frame in LZ4's fast mode (``level`` < 0), with the frame options librealsense reads (as in
    ``rosbag1.compress_lz4``: independent blocks of at most 4 MiB, which the LZ4 library shrinks to the
    smallest size that holds the chunk; content checksum; no stored size)."""
    return cast(bytes, lz4.frame.compress(raw, block_size=lz4.frame.BLOCKSIZE_MAX4MB, block_linked=False,
                                          content_checksum=True, store_size=False,
                                          compression_level=level))  # python-lz4 has no type information


class _ChunkedBag:
    """Writes messages into chunks, each followed by its index-data records, and the index on
    :meth:`finish`. Until then the bag header says ``index_pos = 0``: the file is recognisably unfinished
    and readable by scanning. Memory: one open chunk (``chunk_threshold`` plus one message)."""

    def __init__(self, handle: BinaryIO, compression: str, chunk_threshold: int, lz4_acceleration: int = 1) -> None:
        self._handle, self._compression, self._threshold = handle, compression, chunk_threshold
        # LZ4 "fast" mode: acceleration a > 1 is LZ4 frame compression level -a (same frame format, any
        # LZ4 decoder reads it; faster, slightly larger). 1 is the default level.
        self._lz4_level = 0 if lz4_acceleration <= 1 else -int(lz4_acceleration)
        self._connections: list[tuple[str, rm.MessageType]] = []
        self._conn_ids: dict[str, int] = {}
        self._chunk = bytearray()
        self._chunk_index: dict[int, list[tuple[int, int]]] = {}  # conn -> (time ns, offset in chunk)
        self._chunk_infos: list[tuple[int, int, int, dict[int, int]]] = []
        self._pos = 0
        self._emit(bag.MAGIC + bag.bag_header_record(0, 0, 0))

    def connection(self, topic: str, msgtype: rm.MessageType) -> int:
        """The connection id of ``topic``; its record goes into the chunk where it is first used."""
        conn_id = self._conn_ids.get(topic)
        if conn_id is None:
            conn_id = self._conn_ids[topic] = len(self._connections)
            self._connections.append((topic, msgtype))
            self._chunk += bag.connection_record(conn_id, topic, msgtype)
        return conn_id

    def write(self, conn_id: int, time_ns: int, *payload: bytes | bytearray | memoryview) -> None:
        """Append one message, its bytes given in pieces so that pixels are copied only once."""
        self._chunk_index.setdefault(conn_id, []).append((time_ns, len(self._chunk)))
        self._chunk += bag.message_head(conn_id, time_ns, sum(len(part) for part in payload))
        for part in payload:
            self._chunk += part
        if len(self._chunk) >= self._threshold:
            self.flush_chunk()

    def flush_chunk(self) -> None:
        """Close the open chunk: write it and its index-data records."""
        if not self._chunk_index:
            return
        data: bytes | bytearray
        if self._compression != "lz4":
            data = self._chunk
        elif self._lz4_level == 0:
            data = bag.compress_lz4(self._chunk)
        else:
            data = _compress_lz4_fast(self._chunk, self._lz4_level)
        times = [t for items in self._chunk_index.values() for t, _ in items]
        self._chunk_infos.append((self._pos, min(times), max(times),
                                  {conn: len(items) for conn, items in self._chunk_index.items()}))
        self._emit(bag.chunk_head(self._compression, len(self._chunk), len(data)))
        self._emit(data)
        for conn, items in sorted(self._chunk_index.items()):
            self._emit(bag.index_data_record(conn, items))
        self._chunk, self._chunk_index = bytearray(), {}

    def finish(self) -> None:
        """Flush the last chunk, write the connection and chunk-info records, then the real bag header."""
        self.flush_chunk()
        index_pos = self._pos
        for conn_id, (topic, msgtype) in enumerate(self._connections):
            self._emit(bag.connection_record(conn_id, topic, msgtype))
        for info in self._chunk_infos:
            self._emit(bag.chunk_info_record(*info))
        self._handle.flush()
        self._handle.seek(len(bag.MAGIC))
        self._handle.write(bag.bag_header_record(index_pos, len(self._connections), len(self._chunk_infos)))
        self._handle.seek(0, 2)

    def _emit(self, data: bytes | bytearray) -> None:
        self._handle.write(data)
        self._pos += len(data)
