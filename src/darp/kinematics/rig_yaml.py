"""YAML plumbing for rig files: typed field access with dotted names in errors, transforms both ways.

A transform in a rig file is ``{xyz_m: [x, y, z], rpy_deg: [roll, pitch, yaw]}`` with
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the Z1 SDK's posture convention), or ``{matrix: 4x4 rows}``.
Every error is a :class:`ConfigError` naming the field (``arms.arm110.T_wrist_cam.rpy_deg``);
:func:`darp.kinematics.rig.load_rig` adds the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from darp.errors import ConfigError
from darp.formats.limits import ANGLE_ABS_MAX_DEG, JOINT_ABS_MAX_RAD, POSITION_ABS_MAX_M
from darp.formats.schema import refuse_unknown_keys
from darp.geometry.rigid import check_rigid
from darp.kinematics.transforms import make_transform, rotation_to_rpy, rpy_to_rotation

if TYPE_CHECKING:
    from darp.kinematics.rig import Rig


class FieldReader:
    """Typed access to a nested mapping; errors carry the dotted field name."""

    def __init__(self, data: Mapping[str, Any], prefix: str = "") -> None:
        self.data = data
        self.prefix = prefix

    def _name(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def get(self, key: str, types: type | tuple[type, ...], *, required: bool = True) -> Any:
        """The value at ``key`` (dotted paths allowed), checked against ``types``."""
        node: Any = self.data
        walked = []
        for part in key.split("."):
            walked.append(part)
            if not isinstance(node, Mapping) or part not in node:
                if not required:
                    return None
                raise ConfigError(f"{self._name('.'.join(walked))}: missing field")
            node = node[part]
        kinds = types if isinstance(types, tuple) else (types,)
        if isinstance(node, bool) and bool not in kinds or not isinstance(node, kinds):
            names = " or ".join(_type_word(k) for k in kinds)
            raise ConfigError(f"{self._name(key)}: expected {names}, got {_type_word(type(node))}")
        return node

    def sub(self, key: str) -> FieldReader:
        return FieldReader(self.get(key, dict), self._name(key))

    def only(self, *keys: str) -> None:
        """Refuse keys other than ``keys`` (a misspelt key would otherwise be ignored silently)."""
        refuse_unknown_keys(self.data, keys, self.prefix, error=ConfigError)

    def bounded(self, key: str, count: int, limit: float, unit: str) -> np.ndarray:
        """``count`` finite numbers with absolute values at most ``limit`` (docs/reliability.md)."""
        values = self.numbers(key, count)
        if np.any(np.abs(values) > limit):
            worst = float(values[np.argmax(np.abs(values))])
            raise ConfigError(f"{self._name(key)}: {worst!r} {unit} is beyond +-{limit:g} {unit}")
        return values

    def number(self, key: str) -> float:
        value = float(self.get(key, (int, float)))
        if not np.isfinite(value):
            raise ConfigError(f"{self._name(key)}: must be finite")
        return value

    def numbers(self, key: str, count: int) -> np.ndarray:
        return _numbers(self.get(key, list), count, self._name(key))

    def pair(self, key: str) -> tuple[float, float]:
        """Two finite numbers, such as a ``[min, max]`` range."""
        first, second = (float(v) for v in self.numbers(key, 2))
        return first, second

    def transform(self, key: str) -> np.ndarray:
        """A 4x4 rigid transform from ``{xyz_m, rpy_deg}`` or ``{matrix}``."""
        node = self.sub(key)
        name = node.prefix
        if "matrix" in node.data:
            extra = set(node.data) - {"matrix"}
            if extra:
                raise ConfigError(f"{name}: give either matrix or xyz_m/rpy_deg, not both "
                                  f"({', '.join(sorted(extra))})")
            rows = node.get("matrix", list)
            if len(rows) != 4:
                raise ConfigError(f"{name}.matrix: expected 4 rows, got {len(rows)}")
            matrix = np.stack([_numbers(row, 4, f"{name}.matrix[{i}]") for i, row in enumerate(rows)])
            return check_rigid(matrix, name, error=ConfigError)
        refuse_unknown_keys(node.data, ("xyz_m", "rpy_deg", "matrix"), name, error=ConfigError)
        return pose_from_xyz_rpy(node.bounded("xyz_m", 3, POSITION_ABS_MAX_M, "m"),
                                 np.radians(node.bounded("rpy_deg", 3, ANGLE_ABS_MAX_DEG, "deg")))


def _numbers(value: Any, count: int, name: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != count:
        got = f"{len(value)} values" if isinstance(value, list) else _type_word(type(value))
        raise ConfigError(f"{name}: expected a list of {count} numbers, got {got}")
    for item in value:
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise ConfigError(f"{name}: expected numbers, got {item!r}")
    array = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise ConfigError(f"{name}: values must be finite")
    return array


def _type_word(kind: type) -> str:
    return {
        dict: "a mapping",
        list: "a list",
        str: "a string",
        int: "an integer",
        float: "a number",
        bool: "a boolean",
        type(None): "nothing (null)",
    }.get(kind, kind.__name__)


def check_joints(values: np.ndarray, name: str) -> np.ndarray:
    """Joint angles in radians within +-JOINT_ABS_MAX_RAD."""
    if np.any(np.abs(values) > JOINT_ABS_MAX_RAD):
        raise ConfigError(f"{name}: {float(values[np.argmax(np.abs(values))])!r} rad is not a joint angle")
    return values


def pose_from_xyz_rpy(xyz_m: np.ndarray, rpy_rad: np.ndarray) -> np.ndarray:
    """4x4 pose with translation ``xyz_m`` and rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    roll, pitch, yaw = rpy_rad
    return make_transform(rpy_to_rotation(roll, pitch, yaw), xyz_m)


def xyz_rpy_from_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pose_from_xyz_rpy`: ``(xyz_m, rpy_rad)``."""
    return np.asarray(T[:3, 3], dtype=np.float64), rotation_to_rpy(T[:3, :3])


def transform_to_yaml(T: np.ndarray) -> dict[str, list[float]]:
    """``{xyz_m, rpy_deg}`` for a rig file, rounded where rounding loses nothing measurable (1e-10)."""
    xyz, rpy = xyz_rpy_from_pose(T)
    return {"xyz_m": _clean(xyz), "rpy_deg": _clean(np.degrees(rpy))}


def _clean(values: np.ndarray) -> list[float]:
    return [float(round(float(v), 10)) + 0.0 for v in values]


def rig_to_dict(rig: Rig, rig_schema: str = "darp-rig/1") -> dict[str, Any]:
    """A rig as plain data for YAML, in the order of the packaged default file."""
    return {
        "schema": rig_schema,
        "name": rig.name,
        "wrist_frame": rig.wrist_frame,
        "arms": {
            arm_id: {
                "side": arm.side,
                "camera_serial": arm.camera_serial,
                "T_world_base": transform_to_yaml(arm.T_world_base),
                "T_flange_cam": transform_to_yaml(arm.T_wrist_cam),
                "park_q_rad": [float(v) for v in arm.park_q_rad],
            }
            for arm_id, arm in rig.arms.items()
        },
        "camera_body": {
            "size_m": [float(v) for v in rig.camera_body.size_m],
            "center_cam_m": [float(v) for v in rig.camera_body.center_cam_m],
        },
        "table": {
            "height_m": float(rig.table.height_m),
            "x_range_m": list(rig.table.x_range_m),
            "y_range_m": list(rig.table.y_range_m),
        },
        "workspace": {
            "x_range_m": list(rig.workspace.x_range_m),
            "y_range_m": list(rig.workspace.y_range_m),
            "z_range_m": list(rig.workspace.z_range_m),
        },
        "margins": {
            "table_clearance_m": rig.margins.table_clearance_m,
            "arm_arm_margin_m": rig.margins.arm_arm_margin_m,
            "joint_limit_margin_rad": rig.margins.joint_limit_margin_rad,
        },
    }


def dump(data: Mapping[str, Any]) -> str:
    """YAML text with short numeric lists inline, keys in the given order."""
    body = yaml.safe_dump(dict(data), sort_keys=False, default_flow_style=None, width=110)
    return "# darp rig file (docs/rig-and-poses.md). Units: m, rad; *_deg in degrees.\n" + body
