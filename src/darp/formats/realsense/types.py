"""Plain data types shared by every RealSense recording reader and writer (.bag and .db3).

They mirror what librealsense stores in a recording, in darp's conventions: stream keys instead of
sensor/stream indices, 4x4 transforms named ``T_to_from``, timestamps in milliseconds as librealsense
reports them, recording time in nanoseconds since the start of the recording.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from darp.errors import DecodeError

# darp's short stream keys and the librealsense stream they stand for: (stream type, stream index).
STREAM_KEYS: dict[str, tuple[str, int]] = {
    "depth": ("Depth", 0),
    "color": ("Color", 0),
    "ir1": ("Infrared", 1),
    "ir2": ("Infrared", 2),
    "accel": ("Accel", 0),
    "gyro": ("Gyro", 0),
}
IMAGE_STREAMS = ("depth", "color", "ir1", "ir2")
MOTION_STREAMS = ("accel", "gyro")

# Pixel formats: librealsense name -> (ROS encoding, numpy dtype, channels).
PIXEL_FORMATS: dict[str, tuple[str, str, int]] = {
    "z16": ("mono16", "<u2", 1),
    "y8": ("8UC1", "u1", 1),
    "y16": ("16UC1", "<u2", 1),
    "bgr8": ("bgr8", "u1", 3),
    "rgb8": ("rgb8", "u1", 3),
    "bgra8": ("bgra8", "u1", 4),
    "rgba8": ("rgba8", "u1", 4),
}

TIMESTAMP_DOMAINS = ("Hardware Clock", "System Time", "Global Time")


@dataclass(frozen=True)
class DeviceInfo:
    """The camera that made a recording."""

    name: str
    serial: str
    firmware: str = ""
    product_id: str = ""
    info: dict[str, str] = field(default_factory=dict)  # every key/value librealsense stored


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image stream, librealsense style (pixel centres at integers)."""

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float
    model: str = "Brown Conrady"
    coeffs: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:  # the conventional name
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.ppx], [0.0, self.fy, self.ppy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class MotionIntrinsics:
    """IMU intrinsics: 3x4 scale/bias matrix and noise/bias variances."""

    data: tuple[float, ...]  # 12 values, row-major 3x4
    noise_variances: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_variances: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class StreamProfile:
    """One stream of a recording."""

    key: str  # darp key: depth, color, ir1, ir2, accel, gyro
    stream_type: str  # librealsense type: Depth, Color, Infrared, Accel, Gyro
    index: int  # librealsense stream index (Infrared 1 and 2)
    sensor_index: int  # device_0/sensor_N
    format: str  # z16, bgr8, y8, ... or motion_xyz32f
    fps: int
    width: int = 0
    height: int = 0
    intrinsics: Intrinsics | None = None
    motion_intrinsics: MotionIntrinsics | None = None

    @property
    def is_image(self) -> bool:
        return self.stream_type not in ("Accel", "Gyro")

    @property
    def rs_name(self) -> str:
        """librealsense topic name of the stream, e.g. ``Depth_0`` or ``Infrared_1``."""
        return f"{self.stream_type}_{self.index}"


@dataclass(frozen=True)
class FrameInfo:
    """Everything about a frame except its pixels (cheap to list for a whole recording)."""

    stream: str  # darp stream key
    index: int  # 0-based position within its stream in the recording
    frame_number: int  # device frame counter (header.seq)
    timestamp_ms: float  # frame timestamp as librealsense reports it
    timestamp_domain: str  # Hardware Clock, System Time or Global Time
    recording_time_ns: int  # time since the start of the recording


@dataclass
class Frame:
    """A decoded frame: an image (H x W or H x W x C) or an IMU sample (3 floats)."""

    info: FrameInfo
    data: np.ndarray
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass
class FrameSet:
    """Frames that belong together: depth, both infrared images and the nearest colour frame."""

    depth: Frame | None
    ir1: Frame | None
    ir2: Frame | None
    color: Frame | None

    @property
    def timestamp_ms(self) -> float:
        for frame in (self.depth, self.ir1, self.ir2, self.color):
            if frame is not None:
                return frame.info.timestamp_ms
        raise DecodeError("empty frame set")


@dataclass(frozen=True)
class Salvage:
    """What a reader recovered from a damaged recording instead of refusing it (``Recording.salvage``;
    None for an intact file). A ROS1 bag without a usable index (an interrupted recording, a cut copy)
    is read up to its last complete chunk."""

    missing: tuple[str, ...]  # what is missing or damaged, one phrase each
    frames: dict[str, int]  # frames recovered, per stream
    duration_s: float  # span of the recovered frames' recording times
    chunks: int | None = None  # complete chunks recovered (ROS1 bags)
    truncated_at: int | None = None  # byte offset of the first incomplete or unreadable record, if any

    @property
    def recovered(self) -> str:
        """``recovered 40 depth, 80 accel frames (1.333 s) from 5 complete chunks``."""
        frames = ", ".join(f"{count} {key}" for key, count in self.frames.items()) or "no"
        chunks = "" if self.chunks is None else f" from {self.chunks} complete chunk{'s' * (self.chunks != 1)}"
        return f"recovered {frames} frames ({self.duration_s:.3f} s){chunks}"

    def summary(self) -> str:
        """One line: what is missing, then what was recovered."""
        return "; ".join([*self.missing, self.recovered])

    def as_dict(self) -> dict[str, object]:
        """JSON-ready form (``darp recording info --json``)."""
        return {"missing": list(self.missing), "truncated_at_byte": self.truncated_at, "chunks": self.chunks,
                "frames": dict(self.frames), "duration_s": self.duration_s, "recovered": self.recovered,
                "summary": self.summary()}
