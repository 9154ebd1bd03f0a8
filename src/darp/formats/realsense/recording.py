"""The recording interface shared by the ROS1 ``.bag`` and ROS2 ``.db3`` readers, and ``open_recording``.

A concrete reader parses the file's index on open (cheap: no pixels are decoded) and decodes frames
on demand. Everything generic (nearest-frame lookup, frame sets, time windows) lives here once.
"""

from __future__ import annotations

import bisect
import os
import stat
import warnings
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

import numpy as np

from darp.errors import RecordingError, SalvagedRecordingWarning
from darp.formats.realsense.types import (
    IMAGE_STREAMS,
    DeviceInfo,
    Frame,
    FrameInfo,
    FrameSet,
    Salvage,
    StreamProfile,
)


class Recording(ABC):
    """A RealSense recording opened for reading. Use as a context manager or call :meth:`close`."""

    path: Path
    device: DeviceInfo
    streams: dict[str, StreamProfile]  # by darp stream key
    depth_scale: float  # metres per depth unit
    file_version: int | None  # /file_version stored in the recording (3 or 4), None if absent
    salvage: Salvage | None = None  # set when the file is damaged and was read as far as it goes

    # -- what a concrete reader provides -------------------------------------------------------
    @abstractmethod
    def frame_infos(self, stream: str) -> list[FrameInfo]:
        """Every frame of ``stream`` in recording order, without pixels."""

    @abstractmethod
    def read_frame(self, stream: str, index: int) -> Frame:
        """Decode frame ``index`` (0-based, recording order) of ``stream``."""

    @abstractmethod
    def iter_frames(
        self,
        streams: Iterable[str] | None = None,
        start_ms: float | None = None,
        stop_ms: float | None = None,
    ) -> Iterator[Frame]:
        """Stream frames of ``streams`` (all by default) in recording order, with bounded memory.

        ``start_ms``/``stop_ms`` bound the frame timestamp (inclusive start, exclusive stop).
        """

    @abstractmethod
    def extrinsics(self, source: str, target: str) -> np.ndarray:
        """4x4 ``T_target_source``: maps points in stream ``source``'s frame to stream ``target``'s."""

    @abstractmethod
    def close(self) -> None:
        """Release the file."""

    @property
    @abstractmethod
    def size_bytes(self) -> int:
        """Size of the file on disk."""

    # -- generic conveniences -------------------------------------------------------------------
    def stream(self, key: str) -> StreamProfile:
        """The profile of stream ``key``, or a clear error listing the streams that exist."""
        try:
            return self.streams[key]
        except KeyError:
            raise RecordingError(
                f"no stream {key!r} in this recording (streams: {', '.join(self.streams) or 'none'})",
                self.path,
            ) from None

    def frame_count(self, stream: str) -> int:
        return len(self.frame_infos(stream))

    def timestamps_ms(self, stream: str) -> np.ndarray:
        """Frame timestamps of ``stream`` in milliseconds, recording order."""
        return np.array([info.timestamp_ms for info in self.frame_infos(stream)], dtype=np.float64)

    @property
    def duration_s(self) -> float:
        """Span of recording times over all streams, in seconds.

        Recording time is one clock for the whole file, whereas frame timestamps may use different
        domains per stream (images on global time, IMU on the hardware clock).
        """
        first, last = [], []
        for key in self.streams:
            infos = self.frame_infos(key)
            if infos:
                first.append(min(info.recording_time_ns for info in infos))
                last.append(max(info.recording_time_ns for info in infos))
        return (max(last) - min(first)) / 1e9 if first else 0.0

    def nearest_index(self, stream: str, timestamp_ms: float) -> int:
        """Index of the frame of ``stream`` whose timestamp is nearest ``timestamp_ms``."""
        stamps = self.timestamps_ms(stream)
        if stamps.size == 0:
            raise RecordingError(f"stream {stream!r} has no frames", self.path)
        order = np.argsort(stamps, kind="stable")
        sorted_stamps = stamps[order]
        pos = bisect.bisect_left(sorted_stamps.tolist(), timestamp_ms)
        candidates = [c for c in (pos - 1, pos) if 0 <= c < sorted_stamps.size]
        best = min(candidates, key=lambda c: abs(sorted_stamps[c] - timestamp_ms))
        return int(order[best])

    def frame_at(self, stream: str, timestamp_ms: float) -> Frame:
        """The frame of ``stream`` nearest in time to ``timestamp_ms``."""
        return self.read_frame(stream, self.nearest_index(stream, timestamp_ms))

    def framesets(self, start_ms: float | None = None, stop_ms: float | None = None) -> Iterator[FrameSet]:
        """Group frames into sets keyed on depth: depth, IR1 and IR2 with the same frame number
        (or timestamp), and the colour frame nearest in time. Memory stays bounded."""
        present = [key for key in IMAGE_STREAMS if key in self.streams]
        if "depth" not in present:
            raise RecordingError("no depth stream to group frame sets on", self.path)
        colour_stamps = self.timestamps_ms("color") if "color" in present else np.empty(0)
        colour_order = np.argsort(colour_stamps, kind="stable")
        colour_sorted = colour_stamps[colour_order]
        ir_keys = [k for k in ("ir1", "ir2") if k in present]
        buffers: dict[str, deque[Frame]] = {k: deque(maxlen=_FRAMESET_BUFFER) for k in ir_keys}
        waiting: deque[Frame] = deque()

        def complete(depth: Frame) -> bool:
            return all(_match(buffers[k], depth.info) is not None for k in ir_keys)

        def emit(depth: Frame) -> FrameSet:
            ir = {k: (_match(buffers[k], depth.info) if k in buffers else None) for k in ("ir1", "ir2")}
            color = None
            if colour_sorted.size:
                pos = int(np.searchsorted(colour_sorted, depth.info.timestamp_ms))
                cands = [c for c in (pos - 1, pos) if 0 <= c < colour_sorted.size]
                best = min(cands, key=lambda c: abs(colour_sorted[c] - depth.info.timestamp_ms))
                color = self.read_frame("color", int(colour_order[best]))
            return FrameSet(depth=depth, ir1=ir["ir1"], ir2=ir["ir2"], color=color)

        # IR frames may be stored before or after their depth frame: hold a few depth frames back
        # until their IR partners arrive (or can no longer arrive), so memory stays bounded.
        for frame in self.iter_frames(["depth", *ir_keys], start_ms=start_ms, stop_ms=stop_ms):
            if frame.info.stream == "depth":
                waiting.append(frame)
            else:
                buffers[frame.info.stream].append(frame)
            while waiting and (complete(waiting[0]) or len(waiting) > _FRAMESET_LOOKAHEAD):
                yield emit(waiting.popleft())
        while waiting:
            yield emit(waiting.popleft())

    # -- context manager ------------------------------------------------------------------------
    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


_FRAMESET_LOOKAHEAD = 4  # depth frames held back while waiting for their infrared partners
_FRAMESET_BUFFER = 16  # recent infrared frames kept per stream for matching


def _match(candidates: Iterable[Frame], depth: FrameInfo) -> Frame | None:
    """The buffered IR frame with the depth frame's frame number, else the nearest in time (<= 1 ms)."""
    candidates = list(candidates)
    for frame in reversed(candidates):
        if frame.info.frame_number == depth.frame_number:
            return frame
    close = [f for f in candidates if abs(f.info.timestamp_ms - depth.timestamp_ms) <= 1.0]
    return close[-1] if close else None


_SPECIAL_FILES = ((stat.S_ISFIFO, "named pipe (FIFO)"), (stat.S_ISCHR, "character device"),
                  (stat.S_ISBLK, "block device"), (stat.S_ISSOCK, "socket"))


def require_regular_file(path: Path) -> os.stat_result:
    """``path``'s stat, refusing anything but a regular file before it is opened: reading a FIFO or a
    device named ``x.bag`` would block, or never end."""
    try:
        info = path.stat()
    except FileNotFoundError:
        raise RecordingError("no such file", path) from None
    except OSError as err:
        raise RecordingError(f"cannot open: {err.strerror}", path) from None
    if stat.S_ISDIR(info.st_mode):
        raise RecordingError("is a folder, not a recording", path)
    if not stat.S_ISREG(info.st_mode):
        kind = next((name for test, name in _SPECIAL_FILES if test(info.st_mode)), "special file")
        raise RecordingError(f"is a {kind}, not a regular file: not a recording", path)
    return info


def open_recording(path: str | Path) -> Recording:
    """Open a RealSense recording, choosing the reader from the file's magic bytes.

    ROS1 bags start with ``#ROSBAG V2.0``; ROS2 recordings are SQLite files (``.db3``). Anything but a
    regular file is refused before it is opened. A damaged file that could be read in part (a bag
    without an index) opens with ``salvage`` set and issues a :class:`SalvagedRecordingWarning`.
    """
    path = Path(path)
    require_regular_file(path)
    with open(path, "rb") as handle:
        magic = handle.read(16)
    if not magic:
        raise RecordingError("empty file (0 bytes): not a RealSense recording", path)
    recording: Recording
    if magic.startswith(b"#ROSBAG V2.0"):
        from darp.formats.realsense.bag.reader import BagRecording

        recording = BagRecording(path)
    elif magic.startswith(b"SQLite format 3"):
        from darp.formats.realsense.db3.reader import Db3Recording

        recording = Db3Recording(path)
    else:
        raise RecordingError("not a RealSense recording (neither a ROS1 bag nor a ROS2 .db3 file)", path)
    if recording.salvage is not None:
        warnings.warn(SalvagedRecordingWarning(recording.salvage.summary(), path), stacklevel=2)
    return recording
