"""darp.hardware: the real rig behind the backend interface (Z1 arms via Unitree's SDK, RealSense cameras).

Importing this package imports neither vendor SDK: names are resolved lazily, and the SDKs are loaded
(:mod:`darp.hardware.sdk`) only when an arm connects or a camera starts. See docs/hardware.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "ArmProbe": "darp.hardware.z1_arm",
    "CameraSettings": "darp.hardware.realsense_camera",
    "CheckReport": "darp.hardware.check",
    "HardwareRig": "darp.hardware.rig",
    "HardwareSettings": "darp.hardware.settings",
    "JointLogger": "darp.hardware.joint_logger",
    "MotionLimits": "darp.hardware.z1_arm",
    "RealSenseCamera": "darp.hardware.realsense_camera",
    "check_rig": "darp.hardware.check",
    "WallClock": "darp.hardware.rig",
    "Z1Arm": "darp.hardware.z1_arm",
    "Z1Connection": "darp.hardware.z1_arm",
    "load_hardware_settings": "darp.hardware.settings",
    "open_rig": "darp.hardware.rig",
    "probe_arm": "darp.hardware.z1_arm",
    "sdk_report": "darp.hardware.sdk",
}

if TYPE_CHECKING:
    from darp.hardware.check import CheckReport, check_rig
    from darp.hardware.joint_logger import JointLogger
    from darp.hardware.realsense_camera import CameraSettings, RealSenseCamera
    from darp.hardware.rig import HardwareRig, WallClock, open_rig
    from darp.hardware.sdk import sdk_report
    from darp.hardware.settings import HardwareSettings, load_hardware_settings
    from darp.hardware.z1_arm import ArmProbe, MotionLimits, Z1Arm, Z1Connection, probe_arm


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'darp.hardware' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = [
    "ArmProbe",
    "CameraSettings",
    "CheckReport",
    "HardwareRig",
    "HardwareSettings",
    "JointLogger",
    "MotionLimits",
    "RealSenseCamera",
    "WallClock",
    "Z1Arm",
    "Z1Connection",
    "check_rig",
    "load_hardware_settings",
    "open_rig",
    "probe_arm",
    "sdk_report",
]
