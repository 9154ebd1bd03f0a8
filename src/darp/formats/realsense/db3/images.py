"""Pixels of the image messages in librealsense's ROS2 ``.db3`` recordings.

Frames are raw ``sensor_msgs/Image`` messages, or, with the recorder's default compression, PNG
``CompressedImage`` messages (depth as image_transport's ``compressedDepth``: a 12-byte header, then a
16-bit PNG). The PNG holds true colours, so BGR and RGB streams both come back in their own order.
Errors are ``ValueError``s with a short reason; the reader adds the file and frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from darp.errors import DecodeError
from darp.formats.io_input import native_stderr_silenced
from darp.formats.realsense.types import PIXEL_FORMATS, StreamProfile

# ROS image encodings librealsense writes -> (numpy dtype, channels).
ENCODINGS = {"mono16": ("<u2", 1), "16UC1": ("<u2", 1), "mono8": ("u1", 1), "8UC1": ("u1", 1),
             "bgr8": ("u1", 3), "rgb8": ("u1", 3), "bgra8": ("u1", 4), "rgba8": ("u1", 4),
             "yuv422": ("u1", 2), "yuyv": ("u1", 2), "uyvy": ("u1", 2)}
COMPRESSED_DEPTH_HEADER_BYTES = 12  # image_transport ConfigHeader: int32 format, float32 depthParam[2]
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def decode_raw_image(message: Any, profile: StreamProfile) -> np.ndarray:
    """H x W (x C) array of a ``sensor_msgs/Image``, honouring ``step`` padding and byte order."""
    if message.encoding not in ENCODINGS:
        raise DecodeError(f"unsupported image encoding {message.encoding!r}")
    dtype, channels = ENCODINGS[message.encoding]
    dt = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
    row_bytes = message.width * channels * dt.itemsize
    raw = np.asarray(message.data, dtype=np.uint8)
    if message.step < row_bytes or raw.size < message.step * message.height:
        raise DecodeError(f"image data too short ({raw.size} bytes for {message.height} rows of {message.step})")
    rows = raw[: message.step * message.height].reshape(message.height, message.step)[:, :row_bytes]
    image = np.ascontiguousarray(rows).view(dt).astype(dt.newbyteorder("="), copy=True)
    shape = (message.height, message.width) + ((channels,) if channels > 1 else ())
    return _checked(image.reshape(shape), profile)


def decode_compressed_image(message: Any, profile: StreamProfile) -> np.ndarray:
    """H x W (x C) array of a PNG ``CompressedImage`` (``compressed`` or ``compressedDepth``)."""
    import cv2

    payload = np.asarray(message.data, dtype=np.uint8)
    if "compresseddepth" in message.format.lower():
        payload = payload[COMPRESSED_DEPTH_HEADER_BYTES:]
    if payload[:8].tobytes() != _PNG_MAGIC:
        raise DecodeError(f"compressed frame ({message.format!r}) is not a PNG")
    with native_stderr_silenced():  # libpng's lines about a damaged image: the caller reports it
        image = cv2.imdecode(payload, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DecodeError(f"corrupt PNG in compressed frame ({message.format!r})")
    if profile.format in ("rgb8", "rgba8") and image.ndim == 3:  # OpenCV hands back BGR(A)
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB if image.shape[-1] == 3 else cv2.COLOR_BGRA2RGBA)
    return _checked(image, profile)


def _checked(image: np.ndarray, profile: StreamProfile) -> np.ndarray:
    """The image, if its size, type and channels are those of the stream's profile."""
    if profile.width and image.shape[:2] != (profile.height, profile.width):
        raise DecodeError(f"image is {image.shape[1]}x{image.shape[0]}, the stream is {profile.width}x{profile.height}")
    if profile.format in PIXEL_FORMATS:
        _, dtype, channels = PIXEL_FORMATS[profile.format]
        got = image.shape[2] if image.ndim == 3 else 1
        if image.dtype != np.dtype(dtype) or got != channels:
            raise DecodeError(f"image is {image.dtype} with {got} channels, a {profile.format} stream has "
                             f"{np.dtype(dtype)} with {channels}")
    return image
