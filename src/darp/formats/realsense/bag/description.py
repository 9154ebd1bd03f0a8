"""The description of a librealsense ``.bag`` recording, from its static messages (bag time 1 ns):
file version, device, sensor names, stream profiles (StreamInfo, CameraInfo, ImuIntrinsic), extrinsics,
depth units, and which index entries hold each stream's frames and metadata.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from darp.errors import RecordingError
from darp.formats.realsense import ros_messages as rm
from darp.formats.realsense.rosbag1.index import ENTRY_DTYPE, BagIndex
from darp.formats.realsense.types import STREAM_KEYS, DeviceInfo, Intrinsics, MotionIntrinsics, StreamProfile

_KEY_OF = {rs: key for key, rs in STREAM_KEYS.items()}
Message = Callable[[np.void], tuple[Any, int, int]]  # index entry -> (chunk bytes, data start, data end)
_T = TypeVar("_T")


@dataclass
class BagDescription:
    """What a bag says about itself, and where each stream's messages are."""

    file_version: int
    device: DeviceInfo
    sensor_names: dict[int, str]
    streams: dict[str, StreamProfile]  # in darp's stream order
    depth_scale: float
    depth_scale_source: str  # option, frame or default
    topics: dict[str, np.ndarray]  # index entries per topic (all connections of it merged)
    types: dict[str, str]  # message type per topic
    data: dict[str, np.ndarray] = field(default_factory=dict)  # index entries of each stream's frames
    metadata: dict[str, np.ndarray] = field(default_factory=dict)  # ... and of its metadata KeyValues
    tf: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)  # group, T_stream_reference


def describe(index: BagIndex, message: Message, path: Path) -> BagDescription:
    """Read the description of a bag whose index is ``index``; ``message`` fetches a message's bytes."""
    return _Reader(index, message, path).read()


class _Reader:
    """Reads the static messages one topic at a time (they all sit in the first chunk or two)."""

    def __init__(self, index: BagIndex, message: Message, path: Path) -> None:
        self._index, self._message, self.path = index, message, path

    def read(self) -> BagDescription:
        by_topic: dict[str, list[int]] = {}
        for conn in self._index.connections.values():
            by_topic.setdefault(conn.topic, []).append(conn.conn_id)
        self._topics = {topic: self._merged(ids) for topic, ids in sorted(by_topic.items())}
        self._types = {c.topic: c.msgtype for c in self._index.connections.values()}
        if not self._index.chunks:
            raise RecordingError(f"no complete chunk to read ({self._index.note or 'empty bag'})", self.path)
        if rm.FILE_VERSION_TOPIC not in self._topics:
            raise RecordingError("not a RealSense recording: the bag has no /file_version topic", self.path)
        file_version = self._first(rm.FILE_VERSION_TOPIC, rm.decode_uint32)
        info = dict(self._all(rm.DEVICE_INFO_TOPIC, rm.decode_key_value))
        device = DeviceInfo(info.get("Name", ""), info.get("Serial Number", ""), info.get("Firmware Version", ""),
                            info.get("Product Id", ""), info)
        sensor_names: dict[int, str] = {}
        depth_units: dict[int, float] = {}
        found: dict[tuple[str, int], dict[str, str]] = {}  # (stream key, sensor) -> part of the topic -> topic
        for topic in self._topics:
            if match := rm.SENSOR_INFO_TOPIC.match(topic):
                names = dict(self._all(topic, rm.decode_key_value))
                sensor_names[int(match[1])] = names.get("Name", "")
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
        depth_scale, source = self._depth_scale(depth_units)
        return BagDescription(file_version, device, sensor_names, self.streams, depth_scale, source, self._topics,
                              self._types, self._data, self._metadata_entries, self._tf)

    def _profile(self, key: str, sensor: int, parts: dict[str, str]) -> StreamProfile:
        stream_type, index = STREAM_KEYS[key]
        fps, encoding = self._first(parts["info"], rm.decode_stream_info)
        fmt = rm.FORMAT_OF_ENCODING.get(encoding, encoding.lower())
        intrinsics = motion = None
        width = height = 0
        if "info/camera_info" in parts:
            ci = self._first(parts["info/camera_info"], rm.decode_camera_info)
            d = [float(c) for c in (*ci.D, 0.0, 0.0, 0.0, 0.0, 0.0)[:5]]
            coeffs = (d[0], d[1], d[2], d[3], d[4])
            width, height = ci.width, ci.height
            intrinsics = Intrinsics(ci.width, ci.height, ci.K[0], ci.K[4], ci.K[2], ci.K[5], ci.model, coeffs)
        if "imu_intrinsic" in parts:
            data, noise, bias = self._first(parts["imu_intrinsic"], rm.decode_imu_intrinsic)
            motion = MotionIntrinsics(data, noise, bias)
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

    def _entry(self, entry: np.void) -> tuple[Any, int, int]:
        return self._message(entry)

    def _first(self, topic: str, decode: Callable[[Any, int], _T]) -> _T:
        entries = self._topics.get(topic)
        if entries is None or entries.size == 0:
            raise RecordingError(f"topic {topic} has no message", self.path)
        buf, start, _ = self._entry(entries[0])
        return decode(buf, start)

    def _all(self, topic: str, decode: Callable[[Any, int], _T]) -> list[_T]:
        out = []
        for entry in self._topics.get(topic, np.empty(0, ENTRY_DTYPE)):
            buf, start, _ = self._entry(entry)
            out.append(decode(buf, start))
        return out
