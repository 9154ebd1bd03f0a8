"""RealSense recordings: the ROS1 ``.bag`` files librealsense writes (read and write) and the ROS2
``.db3`` files of librealsense >= 2.58 (read).

Layers, each a subpackage: :mod:`~darp.formats.realsense.rosbag1` is the ROS1 bag format 2.0 at the
record level (index, chunk scan, LZ4 chunks, record encoders); :mod:`~darp.formats.realsense.bag` is
librealsense's layout on top of it (description, frames, reader, writer); :mod:`~darp.formats.realsense.db3`
reads the sqlite recordings. :mod:`~darp.formats.realsense.ros_messages` serialises the few message
types; :mod:`~darp.formats.realsense.types` holds the plain data types every reader returns.

The contract is what this package exports: open any recording with :func:`open_recording`.
"""

from darp.formats.realsense.recording import Recording, open_recording
from darp.formats.realsense.types import (
    IMAGE_STREAMS,
    STREAM_KEYS,
    DeviceInfo,
    Frame,
    FrameInfo,
    FrameSet,
    Intrinsics,
    MotionIntrinsics,
    StreamProfile,
)

__all__ = [
    "IMAGE_STREAMS",
    "STREAM_KEYS",
    "DeviceInfo",
    "Frame",
    "FrameInfo",
    "FrameSet",
    "Intrinsics",
    "MotionIntrinsics",
    "Recording",
    "StreamProfile",
    "open_recording",
]
