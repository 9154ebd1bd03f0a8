"""ROS1 serialisation of the few message types in a librealsense ``.bag``, and its topic layout.

Messages are little-endian ROS1 wire format: strings and variable arrays carry a uint32 length, fixed
arrays do not, ``time`` is (uint32 sec, uint32 nsec). Two librealsense quirks matter:

* ``sensor_msgs/Image`` written with ``header.frame_id == "1"`` has a float32 ``depth_units`` trailer
  after ``data`` (2018 files use ``"0"`` and have none);
* extrinsics quaternions are stored with w <= 0 (identity reads ``w = -1``); see :func:`encode_transform`.

Definitions are the canonical texts (without comments), which give the standard ROS MD5 sums; librealsense
checks only the MD5. The test suite checks every sum against ``rosbags``.
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass

import numpy as np

from darp.errors import DecodeError

_SEP = "=" * 80 + "\n"
_HEADER_DEF = "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id\n"
_VECTOR3_DEF = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION_DEF = "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"


@dataclass(frozen=True)
class MessageType:
    """A ROS1 message type as a bag's connection record names it."""

    name: str  # e.g. sensor_msgs/Image
    md5sum: str
    definition: str


UINT32 = MessageType("std_msgs/UInt32", "304a39449588c7f8ce2df6e8001c5fce", "uint32 data\n")
FLOAT32 = MessageType("std_msgs/Float32", "73fcbf46b49191e672908e50842a83d4", "float32 data\n")
STRING = MessageType("std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1", "string data\n")
KEY_VALUE = MessageType("diagnostic_msgs/KeyValue", "cf57fdc6617a881a88c16e768132149c", "string key\nstring value\n")
STREAM_INFO = MessageType(
    "realsense_msgs/StreamInfo", "311d7e24eac31bb87271d041bf70ff7d",
    "uint32 fps\nstring encoding\nbool is_recommended\n",
)
IMU_INTRINSIC = MessageType(
    "realsense_msgs/ImuIntrinsic", "aebdc2f8f9726f1c3ca823ab56e47429",
    "float32[12] data\nfloat32[3] noise_variances\nfloat32[3] bias_variances\n",
)
CAMERA_INFO = MessageType(
    "sensor_msgs/CameraInfo", "c9a58c1b0b154e0e6da7578cb991d214",
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] D\n"
    "float64[9] K\nfloat64[9] R\nfloat64[12] P\nuint32 binning_x\nuint32 binning_y\n"
    "sensor_msgs/RegionOfInterest roi\n" + _SEP + _HEADER_DEF + _SEP
    + "MSG: sensor_msgs/RegionOfInterest\nuint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\n"
    "bool do_rectify\n",
)
IMAGE = MessageType(
    "sensor_msgs/Image", "060021388200f6f0f447d0fcd9c64743",
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
    "uint32 step\nuint8[] data\n" + _SEP + _HEADER_DEF,
)
IMU = MessageType(
    "sensor_msgs/Imu", "6a62c6daae103f4ff57a132d6f95cec2",
    "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance\n"
    + _SEP + _HEADER_DEF + _SEP + _QUATERNION_DEF + _SEP + _VECTOR3_DEF,
)
TRANSFORM = MessageType(
    "geometry_msgs/Transform", "ac9eff44abf714214112b05d54a3cf9b",
    "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
    + _SEP + _VECTOR3_DEF + _SEP + _QUATERNION_DEF,
)
ALL_TYPES = (UINT32, FLOAT32, STRING, KEY_VALUE, STREAM_INFO, IMU_INTRINSIC, CAMERA_INFO, IMAGE, IMU, TRANSFORM)

# -- librealsense topic layout (device index is always 0) -------------------------------------------
FILE_VERSION_TOPIC = "/file_version"
DEVICE_INFO_TOPIC = "/device_0/info"
STREAM_TOPIC = re.compile(r"^/device_0/sensor_(\d+)/([A-Za-z]+)_(\d+)/(.+)$")
SENSOR_INFO_TOPIC = re.compile(r"^/device_0/sensor_(\d+)/info$")
OPTION_VALUE_TOPIC = re.compile(r"^/device_0/sensor_(\d+)/option/(.+)/value$")
DEPTH_UNITS_OPTIONS = ("Depth_Units", "Depth Units")  # 2019+ spelling, then the pre-2019 one


def sensor_prefix(sensor_index: int) -> str:
    return f"/device_0/sensor_{sensor_index}"


def stream_prefix(sensor_index: int, stream_type: str, stream_index: int) -> str:
    """``/device_0/sensor_N/<Type>_<i>``, the prefix of every topic of one stream."""
    return f"{sensor_prefix(sensor_index)}/{stream_type}_{stream_index}"


# -- ROS time ---------------------------------------------------------------------------------------
def stamp_from_ms(timestamp_ms: float) -> tuple[int, int]:
    """(sec, nsec) for a frame timestamp in ms, rounded the way librealsense's recorder does."""
    seconds = timestamp_ms / 1000.0
    sec = math.floor(seconds)
    nsec = round((seconds - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), int(nsec)


def ms_from_stamp(sec: int, nsec: int) -> float:
    """Frame timestamp in ms from a header stamp, computed exactly as librealsense's player does."""
    return (float(sec) + 1e-9 * float(nsec)) * 1000.0


# -- serialisation ----------------------------------------------------------------------------------
def _string(text: str) -> bytes:
    raw = text.encode("utf-8")
    return struct.pack("<I", len(raw)) + raw


def _header(seq: int, sec: int, nsec: int, frame_id: str) -> bytes:
    return struct.pack("<III", seq, sec, nsec) + _string(frame_id)


def encode_uint32(value: int) -> bytes:
    return struct.pack("<I", value)


def encode_float32(value: float) -> bytes:
    return struct.pack("<f", value)


def encode_string(text: str) -> bytes:
    return _string(text)


def encode_key_value(key: str, value: str) -> bytes:
    return _string(key) + _string(value)


def encode_stream_info(fps: int, encoding: str, is_recommended: bool = True) -> bytes:
    return struct.pack("<I", fps) + _string(encoding) + struct.pack("<B", int(is_recommended))


def encode_imu_intrinsic(data: tuple[float, ...], noise: tuple[float, ...], bias: tuple[float, ...]) -> bytes:
    if len(data) != 12 or len(noise) != 3 or len(bias) != 3:
        raise DecodeError("IMU intrinsics need 12 data values and 3 noise and 3 bias variances")
    return struct.pack("<18f", *data, *noise, *bias)


def encode_camera_info(width: int, height: int, fx: float, fy: float, ppx: float, ppy: float,
                       model: str, coeffs: tuple[float, ...]) -> bytes:
    """CameraInfo as librealsense writes it: K and D filled in, R and P left at zero."""
    K = (fx, 0.0, ppx, 0.0, fy, ppy, 0.0, 0.0, 1.0)
    return b"".join((
        _header(0, 0, 0, ""), struct.pack("<II", height, width), _string(model),
        struct.pack(f"<I{len(coeffs)}d", len(coeffs), *coeffs), struct.pack("<9d", *K),
        bytes(8 * 9 + 8 * 12), struct.pack("<IIIIIIB", 0, 0, 0, 0, 0, 0, 0),
    ))


def encode_image_head(seq: int, timestamp_ms: float, width: int, height: int, encoding: str, step: int,
                      data_len: int) -> bytes:
    """Everything of an Image message before its pixel bytes (frame_id "1": a trailer follows them)."""
    sec, nsec = stamp_from_ms(timestamp_ms)
    return (_header(seq, sec, nsec, "1") + struct.pack("<II", height, width) + _string(encoding)
            + struct.pack("<BII", 0, step, data_len))


def encode_imu(seq: int, timestamp_ms: float, angular_velocity: tuple[float, float, float],
               linear_acceleration: tuple[float, float, float]) -> bytes:
    sec, nsec = stamp_from_ms(timestamp_ms)
    zeros9 = bytes(72)
    return b"".join((
        _header(seq, sec, nsec, "1"), bytes(32), zeros9, struct.pack("<3d", *angular_velocity), zeros9,
        struct.pack("<3d", *linear_acceleration), zeros9,
    ))


def encode_transform(T_target_source: np.ndarray) -> bytes:
    """geometry_msgs/Transform of the librealsense extrinsic ``T_target_source``.

    librealsense builds the quaternion from its column-major rotation array read row-major (the
    transpose) and negates w, which amounts to the rotation's own quaternion with w <= 0 (identity:
    w = -1). Readers must accept either sign."""
    x, y, z, w = matrix_to_quaternion(np.asarray(T_target_source, dtype=np.float64)[:3, :3])
    t = np.asarray(T_target_source, dtype=np.float64)[:3, 3]
    return struct.pack("<7d", t[0], t[1], t[2], -x, -y, -z, -w)


# -- deserialisation (buffer, offset of the message data, end of the message data) --------------------
_LENGTH = struct.Struct("<I")


def _read_string(buf: bytes | memoryview, pos: int) -> tuple[str, int]:
    (length,) = _LENGTH.unpack_from(buf, pos)
    end = pos + 4 + length
    if end > len(buf):
        raise DecodeError(f"string of {length} bytes runs past its buffer")
    return str(buf[pos + 4:end], "utf-8", "replace"), end


def decode_uint32(buf: bytes | memoryview, pos: int) -> int:
    (value,) = _LENGTH.unpack_from(buf, pos)
    return int(value)


def decode_float32(buf: bytes | memoryview, pos: int) -> float:
    (value,) = struct.unpack_from("<f", buf, pos)
    return float(value)


def decode_key_value(buf: bytes | memoryview, pos: int) -> tuple[str, str]:
    key, pos = _read_string(buf, pos)
    value, _ = _read_string(buf, pos)
    return key, value


def decode_stream_info(buf: bytes | memoryview, pos: int) -> tuple[int, str]:
    (fps,) = struct.unpack_from("<I", buf, pos)
    encoding, _ = _read_string(buf, pos + 4)
    return fps, encoding


def decode_imu_intrinsic(buf: bytes | memoryview, pos: int) -> tuple[tuple[float, ...], tuple[float, float, float],
                                                                    tuple[float, float, float]]:
    """(data: 12 values of the 3x4 matrix, noise variances, bias variances)."""
    values = struct.unpack_from("<18f", buf, pos)
    return values[:12], values[12:15], values[15:18]


@dataclass(frozen=True)
class CameraInfoMessage:
    width: int
    height: int
    model: str
    D: tuple[float, ...]
    K: tuple[float, ...]


def decode_camera_info(buf: bytes | memoryview, pos: int) -> CameraInfoMessage:
    _, pos = _read_string(buf, pos + 12)  # header: seq, stamp, frame_id
    height, width = struct.unpack_from("<II", buf, pos)
    model, pos = _read_string(buf, pos + 8)
    (count,) = struct.unpack_from("<I", buf, pos)
    D = struct.unpack_from(f"<{count}d", buf, pos + 4)
    K = struct.unpack_from("<9d", buf, pos + 4 + 8 * count)
    return CameraInfoMessage(width, height, model, D, K)


@dataclass(frozen=True)
class ImageHead:
    """An Image message without its pixels: where they are and how to view them."""

    seq: int
    timestamp_ms: float
    height: int
    width: int
    encoding: str
    is_bigendian: bool
    step: int
    data_start: int  # offset of the pixel bytes in the buffer
    data_len: int
    depth_units: float  # 0.0 when the message has no trailer


_IMAGE_DIMS = struct.Struct("<II")
_IMAGE_LAYOUT = struct.Struct("<BII")
_HEADER_STRUCT = struct.Struct("<IIII")


def decode_image_head(buf: bytes | memoryview, pos: int, end: int) -> ImageHead:
    """Parse an Image message spanning ``buf[pos:end]`` without touching its pixels."""
    seq, sec, nsec, id_len = _HEADER_STRUCT.unpack_from(buf, pos)
    pos += 16 + id_len
    height, width = _IMAGE_DIMS.unpack_from(buf, pos)
    encoding, pos = _read_string(buf, pos + 8)
    bigendian, step, data_len = _IMAGE_LAYOUT.unpack_from(buf, pos)
    data_start = pos + 9
    tail = end - (data_start + data_len)
    if tail < 0:
        raise DecodeError(f"image data ({data_len} bytes) runs past the end of its message")
    depth_units = struct.unpack_from("<f", buf, data_start + data_len)[0] if tail >= 4 else 0.0
    return ImageHead(seq, ms_from_stamp(sec, nsec), height, width, encoding, bool(bigendian), step,
                     data_start, data_len, depth_units)


# ROS image encodings -> (numpy dtype, channels); librealsense formats z16, y8, y16, rgb8, ... map here.
IMAGE_ENCODINGS: dict[str, tuple[str, int]] = {
    "mono16": ("<u2", 1), "16UC1": ("<u2", 1), "mono8": ("u1", 1), "8UC1": ("u1", 1), "bgr8": ("u1", 3),
    "rgb8": ("u1", 3), "bgra8": ("u1", 4), "rgba8": ("u1", 4), "yuv422": ("u1", 2),
}
# ROS encoding -> librealsense format name (StreamProfile.format); others are lower-cased as is.
FORMAT_OF_ENCODING = {"mono16": "z16", "16UC1": "y16", "8UC1": "y8", "mono8": "raw8", "yuv422": "uyvy"}


def image_pixels(buf: bytes | memoryview, head: ImageHead) -> np.ndarray:
    """The pixels of an Image as a read-only array viewing ``buf`` (no copy): H x W or H x W x C.

    Unknown encodings come back as the raw H x step bytes.
    """
    dtype_name, channels = IMAGE_ENCODINGS.get(head.encoding, ("u1", 0))
    dtype = np.dtype(dtype_name).newbyteorder(">" if head.is_bigendian else "<")
    if head.step * head.height > head.data_len:
        raise DecodeError(f"image data has {head.data_len} bytes, {head.height} rows of {head.step} need more")
    if channels == 0:
        return np.frombuffer(buf, np.uint8, head.step * head.height, head.data_start).reshape(head.height, head.step)
    row_bytes = head.width * channels * dtype.itemsize
    shape = (head.height, head.width, channels) if channels > 1 else (head.height, head.width)
    if head.step == row_bytes:
        return np.frombuffer(buf, dtype, head.height * head.width * channels, head.data_start).reshape(shape)
    if head.step < row_bytes:
        raise DecodeError(f"image step {head.step} is shorter than a row of {row_bytes} bytes")
    rows = np.frombuffer(buf, np.uint8, head.step * head.height, head.data_start).reshape(head.height, head.step)
    return rows[:, :row_bytes].view(dtype).reshape(shape)


def decode_imu(buf: bytes | memoryview, pos: int) -> tuple[int, float, tuple[float, ...], tuple[float, ...]]:
    """(seq, timestamp_ms, angular_velocity xyz, linear_acceleration xyz) of an Imu message."""
    seq, sec, nsec, id_len = _HEADER_STRUCT.unpack_from(buf, pos)
    pos += 16 + id_len + 32 + 72  # orientation and its covariance
    gyro = struct.unpack_from("<3d", buf, pos)
    accel = struct.unpack_from("<3d", buf, pos + 24 + 72)
    return seq, ms_from_stamp(sec, nsec), gyro, accel


def decode_transform(buf: bytes | memoryview, pos: int) -> np.ndarray:
    """4x4 ``T_target_source`` from a librealsense extrinsics Transform."""
    tx, ty, tz, x, y, z, w = struct.unpack_from("<7d", buf, pos)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(x, y, z, w)
    T[:3, 3] = (tx, ty, tz)
    return T


# -- quaternions ----------------------------------------------------------------------------------
def matrix_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)
    x, y, z, w = q
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    sign = -1.0 if w < 0 else 1.0
    return (sign * x / norm, sign * y / norm, sign * z / norm, sign * w / norm)


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """3x3 rotation of a quaternion (x, y, z, w); insensitive to the overall sign and to scale."""
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        raise DecodeError("zero quaternion")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
