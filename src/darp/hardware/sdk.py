"""The vendor SDKs, found in one place: Unitree's ``unitree_arm_interface`` and Intel's ``pyrealsense2``.

Both are optional: darp imports them only when real hardware is used, through :func:`load_unitree_sdk`
and :func:`load_realsense`. A missing SDK is a :class:`~darp.errors.HardwareError` that says what to
install, never an ``ImportError`` from deep inside a survey.

Recording containers: pyrealsense2 <= 2.57 records ROS1 ``.bag`` files (the DARP survey format);
pyrealsense2 >= 2.58 records only ROS2 ``.db3`` files (its recorder refuses any other name).
:func:`recording_suffix` turns a policy (``auto``, ``bag``, ``db3``) and the installed version into
the suffix the camera will actually write, or a clear refusal.
"""

from __future__ import annotations

import importlib
import re
from importlib import metadata
from types import ModuleType

from darp.errors import HardwareError

UNITREE_MODULE = "unitree_arm_interface"
REALSENSE_MODULE = "pyrealsense2"
LAST_BAG_VERSION = (2, 57)  # the last pyrealsense2 whose recorder writes ROS1 .bag files
RECORDING_FORMATS = ("auto", "bag", "db3")

UNITREE_HINT = (
    "build it for this Python with scripts/build_z1_vendor.sh (pybind11 >= 2.13, darp's port patch; it puts the "
    "module on this venv's path); see docs/hardware.md"
)
REALSENSE_HINT = "install it with: pip install 'darp[realsense]' (or pip install pyrealsense2)"


def _import_sdk(module: str, what: str, hint: str) -> ModuleType:
    """Import ``module``, or raise a HardwareError naming ``what`` it is and the ``hint`` on getting it."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise HardwareError(f"{what} '{module}' cannot be imported ({err}): {hint}") from err


def load_unitree_sdk() -> ModuleType:
    """The ``unitree_arm_interface`` module, or a HardwareError telling how to get it."""
    return _import_sdk(UNITREE_MODULE, "the Unitree Z1 SDK binding", UNITREE_HINT)


def load_realsense() -> ModuleType:
    """The ``pyrealsense2`` module, or a HardwareError telling how to install it."""
    return _import_sdk(REALSENSE_MODULE, "Intel's RealSense SDK", REALSENSE_HINT)


def parse_version(text: str) -> tuple[int, int, int]:
    """``"2.59.1.10330"`` -> ``(2, 59, 1)``; a HardwareError for text that is not a version."""
    match = re.match(r"^\s*(\d+)\.(\d+)(?:\.(\d+))?", str(text))
    if match is None:
        raise HardwareError(f"cannot read the pyrealsense2 version {text!r}")
    return int(match.group(1)), int(match.group(2)), int(match.group(3) or 0)


def realsense_version(rs: ModuleType) -> tuple[int, int, int]:
    """Version of the given pyrealsense2 module (its ``__version__``, else the installed distribution)."""
    text = getattr(rs, "__version__", None)
    if text is None:
        try:
            text = metadata.version(REALSENSE_MODULE)
        except metadata.PackageNotFoundError as err:
            raise HardwareError("cannot tell which pyrealsense2 version is installed") from err
    return parse_version(text)


def native_suffix(version: tuple[int, int, int]) -> str:
    """The only container the given pyrealsense2 records: ``.bag`` up to 2.57, ``.db3`` from 2.58."""
    return ".bag" if version[:2] <= LAST_BAG_VERSION else ".db3"


def recording_suffix(policy: str, version: tuple[int, int, int]) -> str:
    """The suffix to record with ``policy`` (auto, bag, db3) on pyrealsense2 ``version``.

    ``auto`` takes what the SDK writes; ``bag``/``db3`` insist on one container and refuse, with the fix,
    when the installed SDK cannot write it.
    """
    if policy not in RECORDING_FORMATS:
        raise HardwareError(f"recording format must be one of {', '.join(RECORDING_FORMATS)}, got {policy!r}")
    native = native_suffix(version)
    shown = ".".join(map(str, version))
    if policy == "auto" or f".{policy}" == native:
        return native
    if policy == "bag":
        raise HardwareError(
            f"pyrealsense2 {shown} records only ROS2 .db3 files, so it cannot write the survey format's "
            f"cam<serial>.bag: install pyrealsense2 <= 2.57 (pip install 'pyrealsense2<2.58') or set "
            f"hardware.cameras.recording_format to auto (records cam<serial>.db3, which darp reads too)")
    raise HardwareError(f"pyrealsense2 {shown} records only ROS1 .bag files; .db3 needs pyrealsense2 >= 2.58 "
                        f"(or set hardware.cameras.recording_format to auto)")


def sdk_report() -> dict[str, str]:
    """Which SDKs this Python can use, for a first-run check: module name -> version or the problem."""
    report: dict[str, str] = {}
    try:
        rs = load_realsense()
        version = realsense_version(rs)
        report[REALSENSE_MODULE] = f"{'.'.join(map(str, version))} (records {native_suffix(version)})"
    except HardwareError as err:
        report[REALSENSE_MODULE] = f"unavailable: {err.message}"
    try:
        sdk = load_unitree_sdk()
        multi = all(hasattr(sdk, name) for name in MULTI_ARM_NAMES)
        report[UNITREE_MODULE] = "available" + (" (multi-arm binding)" if multi else " (stock binding: one arm)")
    except HardwareError as err:
        report[UNITREE_MODULE] = f"unavailable: {err.message}"
    return report


# What a binding must expose, beyond the stock one, to reach a controller on other ports (docs/hardware.md):
# darp's port patch (native/z1_sim/binding-ports.patch) marks itself with DARP_PORTS and adds
# ArmInterface(hasGripper, controllerIP, controllerPort, sdkPort), built in C++ like the SDK's multi-robot example.
MULTI_ARM_NAMES = ("DARP_PORTS",)


__all__ = [
    "LAST_BAG_VERSION",
    "MULTI_ARM_NAMES",
    "RECORDING_FORMATS",
    "load_realsense",
    "load_unitree_sdk",
    "native_suffix",
    "parse_version",
    "realsense_version",
    "recording_suffix",
    "sdk_report",
]
