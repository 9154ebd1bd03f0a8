"""darp.hardware: the real rig behind the backend interface (Z1 arms via Unitree's SDK, RealSense cameras).

The rig as a backend (:mod:`.rig`), the Z1 arm (:mod:`.z1_arm`, Unitree's Python binding in :mod:`.z1_binding`, smooth
moves in :mod:`.trajectory`, the 33 Hz joint log in :mod:`.joint_logger`), the RealSense camera
(:mod:`.realsense_camera`), the rig file's ``hardware:`` section (:mod:`.settings`), the pre-flight check
(:mod:`.check`) and the vendor controllers with simulated motors (:mod:`.vendor_sim`).

Importing this package imports neither vendor SDK: names are resolved lazily, and the SDKs are loaded
(:mod:`darp.hardware.sdk`) only when an arm connects or a camera starts. See docs/hardware.md.
"""

from __future__ import annotations

from darp.lazy import LazyExports

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing

_lazy = LazyExports(__name__, {
    ".check": ("CheckReport", "check_rig"),
    ".joint_logger": ("JointLogger",),
    ".realsense_camera": ("CameraSettings", "RealSenseCamera"),
    ".rig": ("HardwareRig", "WallClock", "open_rig"),
    ".sdk": ("sdk_report",),
    ".settings": ("HardwareSettings", "load_hardware_settings"),
    ".z1_arm": ("ArmProbe", "MotionLimits", "Z1Arm", "Z1Connection", "probe_arm"),
})
__getattr__ = _lazy.attribute
__dir__ = _lazy.names

if TYPE_CHECKING:
    from darp.hardware.check import CheckReport, check_rig
    from darp.hardware.joint_logger import JointLogger
    from darp.hardware.realsense_camera import CameraSettings, RealSenseCamera
    from darp.hardware.rig import HardwareRig, WallClock, open_rig
    from darp.hardware.sdk import sdk_report
    from darp.hardware.settings import HardwareSettings, load_hardware_settings
    from darp.hardware.z1_arm import ArmProbe, MotionLimits, Z1Arm, Z1Connection, probe_arm


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
