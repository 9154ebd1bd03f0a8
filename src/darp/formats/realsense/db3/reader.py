"""Reader for the ROS2 sqlite recordings (``.db3``) that librealsense >= 2.58 writes.

The layout (documented in ``docs/recordings-db3.md``) is a rosbag2 sqlite file whose messages are CDR:
static description messages at time 0 are ``std_msgs/String`` holding ``key=value;...`` text; frames
are ``sensor_msgs/Image`` (or PNG ``CompressedImage``) and ``sensor_msgs/Imu``; each frame's number,
device timestamp and domain live in a ``.../metadata`` string at the same recording time. Opening a
file reads only the small messages; pixels are read and decoded on demand, one row at a time.
"""

from __future__ import annotations

import functools
import os
import re
import sqlite3
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import DecodeError, RecordingError
from darp.formats.realsense.db3.images import decode_compressed_image, decode_raw_image
from darp.formats.realsense.recording import Recording, require_regular_file
from darp.formats.realsense.types import (
    STREAM_KEYS,
    DeviceInfo,
    Frame,
    FrameInfo,
    Intrinsics,
    MotionIntrinsics,
    StreamProfile,
)

_KEY_OF = {rs: key for key, rs in STREAM_KEYS.items()}
_STREAM = r"/device_0/sensor_(\d+)/([A-Za-z]+)_(\d+)"
_TOPIC_PATTERNS: list[tuple[str, re.Pattern[str]]] = [
    ("stream_info", re.compile(_STREAM + r"/info$")),
    ("intrinsics", re.compile(_STREAM + r"/camera_info$")),
    ("imu_intrinsics", re.compile(_STREAM + r"/imu_intrinsic$")),
    ("extrinsics", re.compile(_STREAM + r"/tf/(.+)$")),
    ("data", re.compile(_STREAM + r"/(?:image/data(?:/compressed|/compressedDepth)?|imu/data)$")),
    ("metadata", re.compile(_STREAM + r"/(?:image|imu)/metadata$")),
    ("option", re.compile(r"/device_0/sensor_(\d+)/option/(.+)/value$")),
    ("sensor_info", re.compile(r"/device_0/sensor_(\d+)/info$")),
    ("device_info", re.compile(r"/device_0/info$")),
    ("file_version", re.compile(r"/file_version$")),
]
_STATIC_KINDS = ("stream_info", "intrinsics", "imu_intrinsics", "extrinsics", "option", "sensor_info",
                 "device_info", "file_version")


@functools.lru_cache(maxsize=1)
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def parse_key_values(text: str) -> dict[str, str]:
    """Split librealsense's ``key=value;key=value;`` strings (values may contain ``=``)."""
    pairs: dict[str, str] = {}
    for item in text.split(";"):
        if item:
            key, sep, value = item.partition("=")
            pairs[key] = value if sep else ""
    return pairs


def _f32(text: str) -> float:
    """librealsense stores these numbers as float32; widen them the same way it does."""
    return float(np.float32(float(text)))


def _f32s(text: str) -> list[float]:
    return [_f32(v) for v in text.split(",") if v != ""]


@dataclass
class _StreamIndex:
    """Where the frames of one stream are: data/metadata message ids and their infos."""

    topic_id: int
    topic_type: str
    first_metadata: dict[str, str] = field(default_factory=dict)
    data_ids: list[int] = field(default_factory=list)
    meta_ids: list[int | None] = field(default_factory=list)
    infos: list[FrameInfo] = field(default_factory=list)


class Db3Recording(Recording):
    """A librealsense ROS2 ``.db3`` recording opened read-only."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.file_version = None
        self.sensor_names: dict[int, str] = {}
        self.options: dict[int, dict[str, str]] = {}
        self._con: sqlite3.Connection | None = None
        require_regular_file(self.path)  # sqlite would block on a FIFO named x.db3
        try:
            self._con = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True)
            self._load()
        except sqlite3.Error as err:
            self.close()
            raise RecordingError(f"cannot read as a ROS2 .db3 recording: {err}", self.path) from err
        except BaseException:
            self.close()
            raise

    # -- loading ---------------------------------------------------------------------------------
    def _load(self) -> None:
        tables = {row[0] for row in self._sql("SELECT name FROM sqlite_master WHERE type='table'")}
        if not {"topics", "messages"} <= tables:
            raise RecordingError("not a ROS2 .db3 recording (no topics/messages tables)", self.path)
        topics: dict[int, tuple[str, str, str, re.Match[str]]] = {}
        for topic_id, name, msg_type in self._sql("SELECT id, name, type FROM topics"):
            for kind, pattern in _TOPIC_PATTERNS:
                match = pattern.match(name)
                if match:
                    topics[topic_id] = (kind, name, msg_type, match)
                    break
        if not any(kind == "file_version" for kind, *_ in topics.values()):
            raise RecordingError("no /file_version topic: not a RealSense recording", self.path)
        static = {tid: t for tid, t in topics.items() if t[0] in _STATIC_KINDS}
        infos: dict[str, dict[str, str]] = {}  # stream key -> stream info
        intrinsics: dict[str, dict[str, str]] = {}
        imu_intrinsics: dict[str, dict[str, str]] = {}
        self._tf: dict[str, tuple[str, np.ndarray]] = {}
        sensor_of: dict[str, int] = {}
        device_info: dict[str, str] = {}
        seen: set[int] = set()
        marks = ",".join("?" * len(static))
        query = f"SELECT id, topic_id, data FROM messages WHERE topic_id IN ({marks}) ORDER BY timestamp, id"
        for msg_id, topic_id, blob in self._sql(query, tuple(static)):
            if topic_id in seen:  # the first message of a static topic is the recorded state
                continue
            seen.add(topic_id)
            kind, name, msg_type, match = static[topic_id]
            message = self._decode(blob, msg_type, f"{name} (message {msg_id})")
            if kind == "file_version":
                self.file_version = int(message.data)
                continue
            text = str(message.data)
            if kind == "device_info":
                device_info = parse_key_values(text)
            elif kind == "sensor_info":
                self.sensor_names[int(match.group(1))] = parse_key_values(text).get("Name", "")
            elif kind == "option":
                self.options.setdefault(int(match.group(1)), {})[match.group(2)] = text
            else:
                key = _KEY_OF.get((match.group(2), int(match.group(3))))
                if key is None:
                    continue  # a stream darp has no key for (fisheye, pose, ...)
                sensor_of[key] = int(match.group(1))
                pairs = parse_key_values(text)
                if kind == "stream_info":
                    infos[key] = pairs
                elif kind == "intrinsics":
                    intrinsics[key] = pairs
                elif kind == "imu_intrinsics":
                    imu_intrinsics[key] = pairs
                else:
                    self._tf[key] = (match.group(4), self._parse_tf(pairs, name))
        self.device = DeviceInfo(
            name=device_info.get("Name", ""), serial=device_info.get("Serial Number", ""),
            firmware=device_info.get("Firmware Version", ""), product_id=device_info.get("Product Id", ""),
            info=device_info,
        )
        self.streams = {}
        for key in sorted(infos, key=list(STREAM_KEYS).index):
            self.streams[key] = self._profile(key, sensor_of[key], infos[key], intrinsics.get(key),
                                              imu_intrinsics.get(key))
        self._index = self._index_frames(topics)
        self.depth_scale = self._depth_scale()

    def _profile(self, key: str, sensor: int, info: dict[str, str], intr: dict[str, str] | None,
                 imu: dict[str, str] | None) -> StreamProfile:
        stream_type, index = STREAM_KEYS[key]
        try:
            fmt, fps = info["encoding"].lower(), int(info["fps"])
            intrinsics = motion = None
            width = height = 0
            if intr is not None:
                coeffs = _f32s(intr.get("coeffs", "")) + [0.0] * 5
                width, height = int(intr["width"]), int(intr["height"])
                intrinsics = Intrinsics(
                    width=width, height=height, fx=_f32(intr["fx"]), fy=_f32(intr["fy"]),
                    ppx=_f32(intr["ppx"]), ppy=_f32(intr["ppy"]), model=intr.get("model", "None"),
                    coeffs=tuple(coeffs[:5]),  # type: ignore[arg-type]
                )
            if imu is not None:
                motion = MotionIntrinsics(
                    data=tuple(_f32s(imu["data"])),
                    noise_variances=tuple(_f32s(imu.get("noise_variances", "0,0,0"))),  # type: ignore[arg-type]
                    bias_variances=tuple(_f32s(imu.get("bias_variances", "0,0,0"))),  # type: ignore[arg-type]
                )
        except (KeyError, ValueError) as err:
            raise RecordingError(f"stream {stream_type}_{index}: bad stream description ({err})", self.path) from err
        return StreamProfile(key=key, stream_type=stream_type, index=index, sensor_index=sensor, format=fmt,
                             fps=fps, width=width, height=height, intrinsics=intrinsics,
                             motion_intrinsics=motion)

    def _parse_tf(self, pairs: dict[str, str], topic: str) -> np.ndarray:
        """``T_stream_ref`` from ``rotation=`` (column-major 3x3) and ``translation=`` text."""
        try:
            rotation, translation = _f32s(pairs["rotation"]), _f32s(pairs["translation"])
            if len(rotation) != 9 or len(translation) != 3:
                raise DecodeError("wrong number of values")
        except (KeyError, ValueError) as err:
            raise RecordingError(f"{topic}: bad extrinsics ({err})", self.path) from err
        T = np.eye(4)
        T[:3, :3] = np.array(rotation).reshape(3, 3).T
        T[:3, 3] = translation
        return T

    def _depth_scale(self) -> float:
        """Depth_Units of the depth stream's sensor; else the first depth frame's ``depth_units``;
        else the D400 default of 1 mm. 0.0 when there is no depth stream."""
        depth = self.streams.get("depth")
        if depth is None:
            return 0.0
        value = self.options.get(depth.sensor_index, {}).get("Depth_Units")
        if value is None and "depth" in self._index:
            value = self._index["depth"].first_metadata.get("depth_units")
        try:
            return _f32(value if value is not None else "0.001")
        except ValueError as err:
            raise RecordingError(f"bad Depth_Units value {value!r}", self.path) from err

    def _index_frames(self, topics: dict[int, tuple[str, str, str, re.Match[str]]]) -> dict[str, _StreamIndex]:
        """One pass over the frame rows: data ids per stream, paired with the metadata at the same time."""
        data_topics: dict[int, tuple[str, str]] = {}
        meta_topics: dict[int, str] = {}
        for topic_id, (kind, _name, msg_type, match) in topics.items():
            key = _KEY_OF.get((match.group(2), int(match.group(3)))) if kind in ("data", "metadata") else None
            if key is None or key not in self.streams:
                continue
            if kind == "data":
                data_topics[topic_id] = (key, msg_type)
            else:
                meta_topics[topic_id] = key
        index = {key: _StreamIndex(topic_id=tid, topic_type=t) for tid, (key, t) in data_topics.items()}
        rows: dict[str, list[tuple[int, int]]] = {key: [] for key in index}
        # per stream: recording time -> (metadata id, frame number, timestamp ms, domain), parsed on arrival
        meta: dict[str, dict[int, tuple[int, int, float, str]]] = {key: {} for key in index}
        first_meta: dict[str, tuple[int, dict[str, str]]] = {}
        wanted = tuple(data_topics) + tuple(meta_topics)
        query = (f"SELECT id, topic_id, timestamp, CASE WHEN topic_id IN ({','.join('?' * len(meta_topics))}) "
                 f"THEN data END FROM messages WHERE topic_id IN ({','.join('?' * len(wanted))}) ORDER BY id")
        for msg_id, topic_id, stamp_ns, blob in self._sql(query, tuple(meta_topics) + wanted):
            if topic_id in data_topics:
                rows[data_topics[topic_id][0]].append((stamp_ns, msg_id))
                continue
            key = meta_topics[topic_id]
            if key not in meta or stamp_ns in meta[key]:
                continue
            pairs = self._metadata(blob, msg_id)
            try:  # librealsense's defaults when an item is missing
                meta[key][stamp_ns] = (msg_id, int(pairs.get("Frame number", 0)),
                                       float(pairs.get("timestamp", 0.0)),
                                       pairs.get("timestamp_domain", "Hardware Clock"))
            except ValueError as err:
                raise RecordingError(f"frame metadata (message {msg_id}): {err}", self.path) from err
            if key not in first_meta or stamp_ns < first_meta[key][0]:
                first_meta[key] = (stamp_ns, pairs)
        for key, stream_rows in rows.items():
            stream_rows.sort()
            entry = index[key]
            entry.first_metadata = first_meta.get(key, (0, {}))[1]
            for position, (stamp_ns, msg_id) in enumerate(stream_rows):
                meta_id, number, stamp_ms, domain = meta[key].get(stamp_ns, (None, 0, 0.0, "Hardware Clock"))
                entry.data_ids.append(msg_id)
                entry.meta_ids.append(meta_id)
                entry.infos.append(FrameInfo(stream=key, index=position, frame_number=number, timestamp_ms=stamp_ms,
                                             timestamp_domain=domain, recording_time_ns=int(stamp_ns)))
        return index

    # -- low level -------------------------------------------------------------------------------
    def _sql(self, query: str, args: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
        """Run a query and yield its rows one at a time, turning sqlite failures into RecordingError."""
        if self._con is None:
            raise RecordingError("recording is closed", self.path)
        try:
            cursor = self._con.execute(query, args)
            while (row := cursor.fetchone()) is not None:
                yield row
        except sqlite3.Error as err:
            raise RecordingError(f"corrupt ROS2 .db3 recording: {err}", self.path) from err

    def _decode(self, blob: bytes, msg_type: str, where: str) -> Any:
        try:
            return _typestore().deserialize_cdr(blob, msg_type)
        except Exception as err:  # the CDR decoder raises many kinds of errors on bad bytes
            raise RecordingError(f"{where}: cannot decode {msg_type} ({err})", self.path) from err

    def _metadata(self, blob: bytes, msg_id: int | None) -> dict[str, str]:
        message = self._decode(blob, "std_msgs/msg/String", f"frame metadata (message {msg_id})")
        return parse_key_values(str(message.data))

    def _blob(self, msg_id: int) -> bytes:
        for (blob,) in self._sql("SELECT data FROM messages WHERE id = ?", (msg_id,)):
            return bytes(blob)
        raise RecordingError(f"message {msg_id} vanished from the file", self.path)

    def _frame(self, key: str, position: int, blob: bytes) -> Frame:
        entry = self._index[key]
        msg_id, meta_id = entry.data_ids[position], entry.meta_ids[position]
        where = f"{self.streams[key].rs_name} frame {position} (message {msg_id})"
        message = self._decode(blob, entry.topic_type, where)
        try:
            data = self._pixels(key, message, entry.topic_type)
        except (ValueError, TypeError) as err:
            raise RecordingError(f"{where}: {err}", self.path) from err
        metadata = self._metadata(self._blob(meta_id), meta_id) if meta_id is not None else {}
        return Frame(info=entry.infos[position], data=data, metadata=metadata)

    def _pixels(self, key: str, message: Any, topic_type: str) -> np.ndarray:
        profile = self.streams[key]
        if topic_type == "sensor_msgs/msg/Imu":
            vec = message.linear_acceleration if profile.stream_type == "Accel" else message.angular_velocity
            return np.array([vec.x, vec.y, vec.z], dtype=np.float32)
        if topic_type == "sensor_msgs/msg/CompressedImage":
            return decode_compressed_image(message, profile)
        if topic_type == "sensor_msgs/msg/Image":
            return decode_raw_image(message, profile)
        raise DecodeError(f"unsupported frame message type {topic_type}")

    # -- the Recording interface -----------------------------------------------------------------
    def frame_infos(self, stream: str) -> list[FrameInfo]:
        self.stream(stream)
        entry = self._index.get(stream)
        return list(entry.infos) if entry else []

    def read_frame(self, stream: str, index: int) -> Frame:
        self.stream(stream)
        entry = self._index.get(stream)
        count = len(entry.infos) if entry else 0
        if not 0 <= index < count:
            raise RecordingError(f"stream {stream!r} has no frame {index} ({count} frames)", self.path)
        assert entry is not None
        return self._frame(stream, index, self._blob(entry.data_ids[index]))

    def iter_frames(
        self,
        streams: Iterable[str] | None = None,
        start_ms: float | None = None,
        stop_ms: float | None = None,
    ) -> Iterator[Frame]:
        keys = list(self.streams) if streams is None else list(streams)
        wanted: dict[int, tuple[str, int]] = {}
        for key in keys:
            self.stream(key)
            entry = self._index.get(key)
            for position, info in enumerate(entry.infos if entry else []):
                if (start_ms is None or info.timestamp_ms >= start_ms) and (
                    stop_ms is None or info.timestamp_ms < stop_ms
                ):
                    wanted[entry.data_ids[position]] = (key, position)  # type: ignore[union-attr]
        if not wanted:
            return
        times = [self._index[k].infos[p].recording_time_ns for k, p in wanted.values()]
        topic_ids = sorted({self._index[k].topic_id for k, _ in wanted.values()})
        query = ("SELECT id, data FROM messages WHERE timestamp BETWEEN ? AND ? "
                 f"AND topic_id IN ({','.join('?' * len(topic_ids))}) ORDER BY timestamp, id")
        rows = self._sql(query, (min(times), max(times), *topic_ids))
        for msg_id, blob in rows:
            if msg_id in wanted:
                key, position = wanted[msg_id]
                yield self._frame(key, position, bytes(blob))

    def extrinsics(self, source: str, target: str) -> np.ndarray:
        self.stream(source)
        self.stream(target)
        if source == target:
            return np.eye(4)
        if source not in self._tf or target not in self._tf or self._tf[source][0] != self._tf[target][0]:
            raise RecordingError(f"no extrinsics between {source!r} and {target!r} in this recording", self.path)
        T_source_ref, T_target_ref = self._tf[source][1], self._tf[target][1]
        T_ref_source = np.eye(4)
        T_ref_source[:3, :3] = T_source_ref[:3, :3].T
        T_ref_source[:3, 3] = -T_source_ref[:3, :3].T @ T_source_ref[:3, 3]
        return T_target_ref @ T_ref_source

    @property
    def compression(self) -> str:
        """How image frames are stored: ``png``, ``none`` or ``mixed``."""
        kinds = {e.topic_type for k, e in self._index.items() if self.streams[k].is_image}
        if not kinds:
            return "none"
        if kinds == {"sensor_msgs/msg/CompressedImage"}:
            return "png"
        return "none" if kinds == {"sensor_msgs/msg/Image"} else "mixed"

    @property
    def size_bytes(self) -> int:
        return os.path.getsize(self.path)

    def close(self) -> None:
        if self._con is not None:
            self._con.close()
            self._con = None

    def __repr__(self) -> str:
        return f"Db3Recording({str(self.path)!r}, streams={list(self.streams)})"

