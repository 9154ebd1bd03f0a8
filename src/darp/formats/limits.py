"""Physically plausible ranges checked where values enter darp (files, not code): a value outside them
is a corrupt or mis-scaled file, refused with a :class:`darp.errors.FormatError` naming the file and field.

The ranges are deliberately loose (a real rig is well inside them); docs/reliability.md lists them.
"""

from __future__ import annotations

import math

JOINT_ABS_MAX_RAD = 4.0 * math.pi  # any logged / planned Z1 joint angle (two turns; the Z1 stays within +-2.9 rad)
TIME_MIN_S = 0.0  # host-clock seconds: never negative
TIME_MAX_S = 1.0e11  # year ~5100: a Unix time in milliseconds (1.7e12) is beyond it
POSITION_ABS_MAX_M = 10.0  # any world coordinate of a base, an envelope centre
ENVELOPE_SIZE_MAX_M = 5.0  # envelope radius, height, standoff
JOINT_OFFSET_ABS_MAX_RAD = 0.5  # a joint-zero correction dq (about 29 degrees)
HAND_EYE_MAX_M = 0.5  # camera origin to flange distance in T_wrist_cam
ANGLE_ABS_MAX_DEG = 360.0  # roll, pitch, yaw in a rig file
DWELL_MAX_S = 600.0  # a waypoint's pause
JOINT_LOG_RATE_MAX_HZ = 1000.0  # a joint logger's rate (the Z1 SDK runs at 500 Hz, the paper logs at 33 Hz)
CAMERA_FPS_MAX = 300.0  # a RealSense D4xx stream's rate (its fastest depth mode is 300 fps)
IMAGE_SIDE_MAX_PX = 16384  # one side of an image (a D4xx's colour is at most 1920 px wide)
DEPTH_SCALE_MAX_M = 1.0  # metres per depth unit (RealSense 0.001, TUM 0.0002; 1 m per unit is already absurd)
MAX_JSON_BYTES = 256 * 1024 * 1024  # a JSON file larger than this is not one of darp's


def out_of_range(value: float, low: float, high: float) -> bool:
    """True when ``value`` is not a finite number within ``[low, high]``."""
    return not (math.isfinite(value) and low <= value <= high)


__all__ = [
    "ANGLE_ABS_MAX_DEG", "CAMERA_FPS_MAX", "DEPTH_SCALE_MAX_M", "DWELL_MAX_S", "IMAGE_SIDE_MAX_PX",
    "JOINT_LOG_RATE_MAX_HZ", "ENVELOPE_SIZE_MAX_M", "HAND_EYE_MAX_M", "JOINT_ABS_MAX_RAD",
    "JOINT_OFFSET_ABS_MAX_RAD", "MAX_JSON_BYTES", "POSITION_ABS_MAX_M", "TIME_MAX_S", "TIME_MIN_S",
    "out_of_range",
]
