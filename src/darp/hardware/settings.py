"""The optional ``hardware:`` section of a rig file: how to reach each arm's controller, motion limits,
camera streams and the joint-log rate (docs/hardware.md).

``darp.kinematics.rig.load_rig`` reads only the sections it knows, so the geometry loader ignores this
one; :func:`load_hardware_settings` reads it from the same file. Every field is optional: without the
section the first arm talks to ``z1_ctrl`` on 127.0.0.1:8071 from SDK port 8072 (the stock SDK ports)
and the second on 8073 from 8074 (the ports of Unitree's two-arm example), both without gripper.

Example::

    hardware:
      arms:
        arm110: {controller_port: 8071, sdk_port: 8072, arm_ip: 192.168.123.110}
        arm111: {controller_port: 8073, sdk_port: 8074, arm_ip: 192.168.123.111}
      motion: {max_speed_rad_s: 0.6, max_accel_rad_s2: 2.0}
      cameras: {width: 640, height: 480, fps: 30, imu: auto, recording_format: auto}
      joint_log_hz: 33
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from darp.errors import ConfigError
from darp.formats.schema import refuse_unknown_keys
from darp.formats.text import read_yaml_mapping
from darp.hardware.joint_logger import DEFAULT_RATE_HZ
from darp.hardware.realsense_camera import CameraSettings
from darp.hardware.z1_arm import DEFAULT_CONTROLLER_PORT, DEFAULT_SDK_PORT, MotionLimits, Z1Connection

SECTION = "hardware"
_WORDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string", dict: "a mapping"}
ARM_FIELDS = {"controller_ip": str, "controller_port": int, "sdk_port": int, "has_gripper": bool, "arm_ip": str}


@dataclass(frozen=True)
class HardwareSettings:
    """Connection per arm id, motion limits, camera settings, joint-log rate."""

    arms: Mapping[str, Z1Connection]
    motion: MotionLimits = field(default_factory=MotionLimits)
    cameras: CameraSettings = field(default_factory=CameraSettings)
    joint_log_hz: float = DEFAULT_RATE_HZ

    @classmethod
    def defaults(cls, arm_ids: Sequence[str]) -> HardwareSettings:
        return hardware_settings_from_dict(None, arm_ids)


def _default_connection(order: int) -> Z1Connection:
    return Z1Connection(controller_port=DEFAULT_CONTROLLER_PORT + 2 * order, sdk_port=DEFAULT_SDK_PORT + 2 * order)


def _typed(data: Mapping[str, Any], types: Mapping[str, type], where: str) -> dict[str, Any]:
    refuse_unknown_keys(data, types, where, error=ConfigError)
    out = {}
    for key, value in data.items():
        kind = types[key]
        ok = isinstance(value, kind) and not (kind in (int, float) and isinstance(value, bool))
        if kind is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok:
            raise ConfigError(f"{where}.{key}: expected {_WORDS[kind]}, got {value!r}")
        out[key] = float(value) if kind is float else value
    return out


def _connection(data: Any, order: int, where: str) -> Z1Connection:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping, got {data!r}")
    values = _typed(data, ARM_FIELDS, where)
    for key in ("controller_port", "sdk_port"):
        if key in values and not 1 <= values[key] <= 65535:
            raise ConfigError(f"{where}.{key}: must be a UDP port in 1..65535, got {values[key]}")
    for key in ("controller_ip", "arm_ip"):
        if key in values:
            try:
                ipaddress.ip_address(values[key])
            except ValueError:
                raise ConfigError(f"{where}.{key}: not an IP address: {values[key]!r}") from None
    base = _default_connection(order)
    return Z1Connection(**{f.name: values.get(f.name, getattr(base, f.name)) for f in fields(Z1Connection)})


def hardware_settings_from_dict(section: Mapping[str, Any] | None, arm_ids: Sequence[str]) -> HardwareSettings:
    """Settings from a parsed ``hardware:`` section (None: all defaults) for the rig's ``arm_ids``."""
    section = {} if section is None else section
    if not isinstance(section, Mapping):
        raise ConfigError(f"{SECTION}: expected a mapping, got {section!r}")
    top = _typed(section, {"arms": dict, "motion": dict, "cameras": dict, "joint_log_hz": float}, SECTION)
    arms_data = top.get("arms", {})
    unknown = sorted(map(str, set(arms_data) - set(arm_ids)))
    if unknown:
        raise ConfigError(f"{SECTION}.arms: no arm {', '.join(map(repr, unknown))} in the rig "
                          f"(arms: {', '.join(arm_ids)})")
    arms = {arm_id: _connection(arms_data.get(arm_id, {}), i, f"{SECTION}.arms.{arm_id}")
            for i, arm_id in enumerate(arm_ids)}
    _check_ports(arms)
    motion_types = {f.name: float for f in fields(MotionLimits)}
    motion_values = _typed(top.get("motion", {}), motion_types, f"{SECTION}.motion")
    try:
        motion = MotionLimits(**motion_values)
    except ConfigError as err:
        raise ConfigError(err.message if err.message.startswith(SECTION) else f"{SECTION}.{err.message}") from None
    kinds: dict[str, type] = {"int": int, "bool": bool, "str": str, "float": float}
    camera_types = {f.name: kinds[str(f.type)] for f in fields(CameraSettings)}
    camera_values = _typed(top.get("cameras", {}), camera_types, f"{SECTION}.cameras")
    try:
        cameras = CameraSettings(**camera_values)
    except ConfigError as err:
        raise ConfigError(err.message if err.message.startswith(SECTION) else f"{SECTION}.{err.message}") from None
    rate = top.get("joint_log_hz", DEFAULT_RATE_HZ)
    if not 0 < rate <= 500:
        raise ConfigError(f"{SECTION}.joint_log_hz: must be in (0, 500], got {rate}")
    return HardwareSettings(arms=arms, motion=motion, cameras=cameras, joint_log_hz=rate)


def _check_ports(arms: Mapping[str, Z1Connection]) -> None:
    """Each arm needs its own controller and its own SDK port; an SDK port cannot be a local controller's."""
    controllers: dict[tuple[str, int], str] = {}
    sdk_ports: dict[int, str] = {}
    for arm_id, c in arms.items():
        where = f"{SECTION}.arms.{arm_id}"
        other = controllers.get((c.controller_ip, c.controller_port))
        if other is not None:
            raise ConfigError(f"{where}: controller {c.controller_ip}:{c.controller_port} is already {other}'s "
                              f"(two arms need two z1_ctrl processes on distinct ports)")
        controllers[(c.controller_ip, c.controller_port)] = arm_id
        other = sdk_ports.get(c.sdk_port)
        if other is not None:
            raise ConfigError(f"{where}: sdk_port {c.sdk_port} is already {other}'s")
        sdk_ports[c.sdk_port] = arm_id
    for (ip, port), arm_id in controllers.items():
        if ip == "127.0.0.1" and port in sdk_ports:
            raise ConfigError(f"{SECTION}.arms.{sdk_ports[port]}: sdk_port {port} is the port of {arm_id}'s "
                              f"controller on this host")


def load_hardware_settings(path: str | Path, arm_ids: Sequence[str]) -> HardwareSettings:
    """The ``hardware:`` section of the rig file ``path`` (defaults when absent); errors name the file."""
    path = Path(path)
    data = read_yaml_mapping(path)
    try:
        return hardware_settings_from_dict(data.get(SECTION), arm_ids)
    except ConfigError as err:
        raise ConfigError(err.message, path) from None


__all__ = ["HardwareSettings", "hardware_settings_from_dict", "load_hardware_settings"]
