"""The dual-arm rig: two Z1 arms with wrist cameras, a table, a shared workspace, park poses, margins.

A rig file (YAML, see ``darp/data/rig_default.yaml`` and docs/rig-and-poses.md) holds the *nominal*
geometry. A calibration (``darp.formats.calibration``) replaces the base and hand-eye transforms and
adds joint-zero offsets; every pose method takes it as an optional argument so that the same code
runs nominal and calibrated.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import ConfigError, KinematicsError
from darp.formats.calibration import ArmCalibration, Calibration
from darp.formats.text import read_yaml_mapping
from darp.geometry.rigid import check_rigid
from darp.kinematics import collision, rig_yaml, z1
from darp.kinematics.camera_poses import compose_world_cam

SCHEMA = "darp-rig/1"
NOMINAL_DATE = "1970-01-01"  # a nominal calibration was never measured: a fixed date keeps outputs deterministic
WORLD_FRAME_TEXT = (
    "origin on the table surface midway between the base origins, x from arm110's base towards arm111's, z up"
)
ARM_SIDES = ("left", "right")
WRIST_FRAMES = tuple(z1.WRIST_FRAMES)


def _frozen_array(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.array(value, dtype=np.float64)
    if array.shape != shape:
        raise ConfigError(f"{name}: expected shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ConfigError(f"{name}: values must be finite")
    array.setflags(write=False)
    return array


def _range(value: Any, name: str) -> tuple[float, float]:
    lo, hi = (float(v) for v in _frozen_array(value, (2,), name))
    if not lo < hi:
        raise ConfigError(f"{name}: expected [min, max] with min < max, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True, eq=False)
class ArmConfig:
    """One arm: its id, side, camera serial, nominal base pose and camera mount, park joints."""

    arm_id: str
    side: str
    camera_serial: str
    T_world_base: np.ndarray
    T_wrist_cam: np.ndarray
    park_q_rad: np.ndarray

    def __post_init__(self) -> None:
        if not self.arm_id:
            raise ConfigError("arm id must not be empty")
        if self.side not in ARM_SIDES:
            raise ConfigError(f"arms.{self.arm_id}.side: must be one of {', '.join(ARM_SIDES)}, got {self.side!r}")
        if not (isinstance(self.camera_serial, str) and self.camera_serial.isdigit()):
            raise ConfigError(f"arms.{self.arm_id}.camera_serial: must be a string of digits, "
                              f"got {self.camera_serial!r}")
        for name, key in (("T_world_base", "T_world_base"), ("T_wrist_cam", "T_flange_cam")):  # rig YAML keys
            matrix = check_rigid(getattr(self, name), f"arms.{self.arm_id}.{key}", error=ConfigError)
            object.__setattr__(self, name, _frozen_array(matrix, (4, 4), f"arms.{self.arm_id}.{key}"))
        park = _frozen_array(self.park_q_rad, (6,), f"arms.{self.arm_id}.park_q_rad")
        _check_within_limits(park, f"arms.{self.arm_id}.park_q_rad")
        object.__setattr__(self, "park_q_rad", park)


def _check_within_limits(q: np.ndarray, name: str) -> None:
    outside = np.flatnonzero((q < z1.JOINT_LOWER) | (q > z1.JOINT_UPPER))
    if outside.size:
        j = int(outside[0])
        raise ConfigError(
            f"{name}: joint{j + 1} = {q[j]:.4f} rad is outside the Z1 limits "
            f"[{z1.JOINT_LOWER[j]:.4f}, {z1.JOINT_UPPER[j]:.4f}]"
        )


@dataclass(frozen=True)
class Table:
    """The table top: a horizontal rectangle at world z = ``height_m``."""

    height_m: float
    x_range_m: tuple[float, float]
    y_range_m: tuple[float, float]

    def __post_init__(self) -> None:
        if not np.isfinite(self.height_m):
            raise ConfigError("table.height_m: must be finite")
        object.__setattr__(self, "x_range_m", _range(self.x_range_m, "table.x_range_m"))
        object.__setattr__(self, "y_range_m", _range(self.y_range_m, "table.y_range_m"))

    def corners(self) -> np.ndarray:
        """(4, 3) corners in world coordinates, counter-clockwise seen from above."""
        (x0, x1), (y0, y1), z = self.x_range_m, self.y_range_m, self.height_m
        return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


@dataclass(frozen=True)
class Workspace:
    """The box (world frame) in which objects may be placed for a survey."""

    x_range_m: tuple[float, float]
    y_range_m: tuple[float, float]
    z_range_m: tuple[float, float]

    def __post_init__(self) -> None:
        for axis in "xyz":
            name = f"{axis}_range_m"
            object.__setattr__(self, name, _range(getattr(self, name), f"workspace.{name}"))

    def contains(self, points_world: np.ndarray) -> np.ndarray:
        """Boolean mask of the (N, 3) points inside the box (borders included)."""
        p = np.atleast_2d(np.asarray(points_world, dtype=np.float64))
        inside = np.ones(p.shape[0], dtype=bool)
        for i, (lo, hi) in enumerate((self.x_range_m, self.y_range_m, self.z_range_m)):
            inside &= (p[:, i] >= lo) & (p[:, i] <= hi)
        return inside

    @property
    def center_m(self) -> np.ndarray:
        return np.array([np.mean(self.x_range_m), np.mean(self.y_range_m), np.mean(self.z_range_m)])


@dataclass(frozen=True, eq=False)
class CameraBody:
    """The camera housing as a box in the camera optical frame (for collision checks)."""

    size_m: np.ndarray  # (3,) extent along camera x, y, z
    center_cam_m: np.ndarray  # (3,) box centre in the optical frame

    def __post_init__(self) -> None:
        size = _frozen_array(self.size_m, (3,), "camera_body.size_m")
        if np.any(size <= 0):
            raise ConfigError("camera_body.size_m: every extent must be positive")
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "center_cam_m", _frozen_array(self.center_cam_m, (3,), "camera_body.center_cam_m"))


@dataclass(frozen=True)
class Margins:
    """Clearances enforced by planning."""

    table_clearance_m: float
    arm_arm_margin_m: float
    joint_limit_margin_rad: float

    def __post_init__(self) -> None:
        for name in ("table_clearance_m", "arm_arm_margin_m", "joint_limit_margin_rad"):
            value = float(getattr(self, name))
            if not (np.isfinite(value) and value >= 0):
                raise ConfigError(f"margins.{name}: must be a finite value >= 0, got {value}")
            object.__setattr__(self, name, value)


@dataclass(frozen=True, eq=False)
class Rig:
    """Two arms (ordered, left first by convention), table, workspace, camera body and margins."""

    arms: Mapping[str, ArmConfig]
    table: Table
    workspace: Workspace
    camera_body: CameraBody
    margins: Margins
    wrist_frame: str = "flange"
    name: str = "rig"
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if len(self.arms) != 2:
            raise ConfigError(f"arms: a rig has exactly two arms, got {len(self.arms)}")
        for arm_id, arm in self.arms.items():
            if arm.arm_id != arm_id:
                raise ConfigError(f"arms.{arm_id}: arm id {arm.arm_id!r} differs from its key")
        sides = sorted(arm.side for arm in self.arms.values())
        if sides != ["left", "right"]:
            raise ConfigError(f"arms: need one left and one right arm, got sides {sides}")
        serials = [arm.camera_serial for arm in self.arms.values()]
        if len(set(serials)) != 2:
            raise ConfigError(f"arms: both arms name camera {serials[0]}")
        if self.wrist_frame not in WRIST_FRAMES:
            raise ConfigError(f"wrist_frame: must be one of {', '.join(WRIST_FRAMES)}, got {self.wrist_frame!r}")
        if self.base_separation_m < 0.1:
            raise ConfigError(f"arms: the two bases are only {self.base_separation_m:.3f} m apart")
        object.__setattr__(self, "arms", dict(self.arms))

    # -- lookup -------------------------------------------------------------------------------
    @property
    def arm_ids(self) -> tuple[str, ...]:
        return tuple(self.arms)

    def arm(self, arm_id: str) -> ArmConfig:
        """The arm ``arm_id``, or a KinematicsError listing the rig's arms."""
        try:
            return self.arms[arm_id]
        except KeyError:
            raise KinematicsError(f"no arm {arm_id!r} in the rig (arms: {', '.join(self.arms)})") from None

    def arm_for_serial(self, serial: str) -> ArmConfig:
        """The arm carrying camera ``serial``."""
        for arm in self.arms.values():
            if arm.camera_serial == str(serial):
                return arm
        known = ", ".join(f"{a.camera_serial} ({a.arm_id})" for a in self.arms.values())
        raise KinematicsError(f"no arm carries camera {serial} (cameras: {known})")

    # -- geometry -----------------------------------------------------------------------------
    @property
    def base_separation_m(self) -> float:
        """Distance between the two base origins (the paper: about 1.3986 m)."""
        a, b = (arm.T_world_base[:3, 3] for arm in self.arms.values())
        return float(np.linalg.norm(b - a))

    @property
    def relative_yaw_deg(self) -> float:
        """Rotation about world z from the first arm's base to the second's, in (-180, 180]."""
        a, b = (arm.T_world_base for arm in self.arms.values())
        R_rel = a[:3, :3].T @ b[:3, :3]
        yaw = float(np.degrees(np.arctan2(R_rel[1, 0], R_rel[0, 0])))
        return 180.0 if yaw == -180.0 else yaw

    def extrinsics(
        self, arm_id: str, calibration: Calibration | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(T_world_base, T_wrist_cam, joint_offsets_rad)``: calibrated if given, else nominal."""
        arm = self.arm(arm_id)
        if calibration is None:
            return arm.T_world_base, arm.T_wrist_cam, np.zeros(6)
        try:
            cal = calibration.arms[arm_id]
        except KeyError:
            raise KinematicsError(
                f"the calibration has no arm {arm_id!r} (arms: {', '.join(calibration.arms)})"
            ) from None
        dq = np.zeros(6) if cal.joint_offsets_rad is None else np.asarray(cal.joint_offsets_rad, dtype=np.float64)
        return np.asarray(cal.T_world_base, dtype=np.float64), np.asarray(cal.T_wrist_cam, dtype=np.float64), dq

    def T_world_wrist(self, arm_id: str, q: np.ndarray, *, calibration: Calibration | None = None) -> np.ndarray:
        """World pose of the wrist (flange) for joints ``q`` (6,) or (N, 6): (4, 4) or (N, 4, 4)."""
        T_world_base, _, dq = self.extrinsics(arm_id, calibration)
        Q = _joints(q)
        poses = T_world_base @ z1.fk_batch(Q + dq, frame=self.wrist_frame)
        return poses[0] if np.ndim(q) == 1 else poses

    def T_world_cam(self, arm_id: str, q: np.ndarray, *, calibration: Calibration | None = None) -> np.ndarray:
        """Eq. 1 for joints ``q`` (6,) or (N, 6), nominal or calibrated: (4, 4) or (N, 4, 4)."""
        T_world_base, T_wrist_cam, dq = self.extrinsics(arm_id, calibration)
        Q = _joints(q)
        poses = compose_world_cam(T_world_base, z1.fk_batch(Q + dq, frame=self.wrist_frame), T_wrist_cam)
        return poses[0] if np.ndim(q) == 1 else poses

    def camera_positions(
        self, arm_id: str, q: np.ndarray, *, calibration: Calibration | None = None
    ) -> np.ndarray:
        """Camera optical centres in the world for joints (N, 6): (N, 3) (or (3,) for one q)."""
        poses = self.T_world_cam(arm_id, q, calibration=calibration)
        return poses[..., :3, 3]

    def T_world_camera_body(self, arm_id: str, q: np.ndarray, *, calibration: Calibration | None = None) -> np.ndarray:
        """World pose of the camera body box centre (box axes = optical axes)."""
        T_cam_body = np.eye(4)
        T_cam_body[:3, 3] = self.camera_body.center_cam_m
        return self.T_world_cam(arm_id, q, calibration=calibration) @ T_cam_body

    def camera_mount(self, arm_id: str, calibration: Calibration | None = None) -> collision.CameraMount:
        """The collision model of ``arm_id``'s camera: the rig's body box at the (calibrated) mount."""
        _, T_wrist_cam, _ = self.extrinsics(arm_id, calibration)
        body = self.camera_body
        return collision.CameraMount(T_wrist_cam=T_wrist_cam, body_size_m=tuple(body.size_m.tolist()),
                                     body_center_cam_m=tuple(body.center_cam_m.tolist()))

    def arm_primitives(self, arm_id: str, q: np.ndarray, *, calibration: Calibration | None = None
                       ) -> collision.PrimitiveSet:
        """World-frame collision shapes of an arm and its camera at joints ``q`` (6,)."""
        T_world_base, _, dq = self.extrinsics(arm_id, calibration)
        return collision.arm_primitives(np.asarray(q, dtype=np.float64) + dq, T_world_base,
                                        self.camera_mount(arm_id, calibration))

    def clearances(self, q_by_arm: Mapping[str, np.ndarray], *, calibration: Calibration | None = None
                   ) -> dict[str, collision.DistanceResult]:
        """Signed distances (m) for joints of both arms: ``<arm>.table``, ``<arm>.self``, ``arm_arm``.

        Compare with :attr:`margins` (table_clearance_m, arm_arm_margin_m); negative = collision.
        """
        out: dict[str, collision.DistanceResult] = {}
        shapes = {}
        for arm_id, q in q_by_arm.items():
            T_world_base, _, dq = self.extrinsics(arm_id, calibration)
            mount = self.camera_mount(arm_id, calibration)
            q_model = np.asarray(q, dtype=np.float64) + dq
            out[f"{arm_id}.table"] = collision.arm_table_distance(q_model, T_world_base, self.table.height_m, mount)
            out[f"{arm_id}.self"] = collision.self_collision_distance(q_model, mount)
            shapes[arm_id] = collision.arm_primitives(q_model, T_world_base, mount)
        if len(shapes) == 2:
            out["arm_arm"] = collision.min_distance(*shapes.values())
        return out

    def nominal_calibration(self) -> Calibration:
        """A :class:`Calibration` holding the rig's nominal transforms and zero joint offsets.

        For processing without a measured calibration; its epoch says ``nominal`` so that outputs
        made from it are recognisable.
        """
        arms = {
            arm_id: ArmCalibration(
                serial=arm.camera_serial,
                T_world_base=arm.T_world_base.copy(),
                T_wrist_cam=arm.T_wrist_cam.copy(),
                joint_offsets_rad=np.zeros(6),
            )
            for arm_id, arm in self.arms.items()
        }
        return Calibration(
            epoch=f"nominal:{self.name}",
            date=NOMINAL_DATE,
            arms=arms,
            world_frame=WORLD_FRAME_TEXT,
            report={"source": str(self.source) if self.source else None, "nominal": True},
        )

    # -- serialisation --------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The rig as plain YAML-ready data (transforms as xyz_m / rpy_deg)."""
        return rig_yaml.rig_to_dict(self, SCHEMA)

    def to_yaml(self) -> str:
        """The rig as YAML text that :func:`load_rig` reads back to an equal rig."""
        return rig_yaml.dump(self.to_dict())


def _joints(q: np.ndarray) -> np.ndarray:
    Q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    if Q.ndim != 2 or Q.shape[1] != 6:
        raise KinematicsError(f"joint vector must have 6 values (or shape (N, 6)), got shape {np.shape(q)}")
    return Q


def default_rig_path() -> Path:
    """Path of the packaged default rig file."""
    return Path(str(resources.files("darp") / "data" / "rig_default.yaml"))


def rig_from_dict(data: Mapping[str, Any], source: Path | None = None) -> Rig:
    """Build a :class:`Rig` from parsed YAML; errors name the field (the caller adds the file)."""
    reader = rig_yaml.FieldReader(data)
    reader.only("schema", "name", "wrist_frame", "arms", "camera_body", "table", "workspace", "margins",
                "hardware")  # hardware: the real rig's section, read by darp.hardware.settings
    schema = reader.get("schema", str, required=False)
    if schema is not None and schema != SCHEMA:
        raise ConfigError(f"schema: expected {SCHEMA!r}, got {schema!r}")
    arms_data = reader.get("arms", dict)
    arms = {}
    for arm_id in arms_data:
        arm = reader.sub(f"arms.{arm_id}")
        arm.only("side", "camera_serial", "T_world_base", "T_flange_cam", "park_q_rad")
        arms[str(arm_id)] = ArmConfig(
            arm_id=str(arm_id),
            side=arm.get("side", str),
            camera_serial=str(arm.get("camera_serial", (str, int))),
            T_world_base=arm.transform("T_world_base"),
            T_wrist_cam=arm.transform("T_flange_cam"),
            park_q_rad=rig_yaml.check_joints(arm.numbers("park_q_rad", 6), f"arms.{arm_id}.park_q_rad"),
        )
    body, table, ws, margins = (reader.sub(k) for k in ("camera_body", "table", "workspace", "margins"))
    body.only("size_m", "center_cam_m")
    table.only("height_m", "x_range_m", "y_range_m")
    ws.only("x_range_m", "y_range_m", "z_range_m")
    margins.only("table_clearance_m", "arm_arm_margin_m", "joint_limit_margin_rad")
    return Rig(
        arms=arms,
        table=Table(
            height_m=table.number("height_m"),
            x_range_m=table.pair("x_range_m"),
            y_range_m=table.pair("y_range_m"),
        ),
        workspace=Workspace(
            x_range_m=ws.pair("x_range_m"), y_range_m=ws.pair("y_range_m"), z_range_m=ws.pair("z_range_m")
        ),
        camera_body=CameraBody(size_m=body.numbers("size_m", 3), center_cam_m=body.numbers("center_cam_m", 3)),
        margins=Margins(
            table_clearance_m=margins.number("table_clearance_m"),
            arm_arm_margin_m=margins.number("arm_arm_margin_m"),
            joint_limit_margin_rad=margins.number("joint_limit_margin_rad"),
        ),
        wrist_frame=reader.get("wrist_frame", str),
        name=str(reader.get("name", str, required=False) or (source.stem if source else "rig")),
        source=source,
    )


def load_rig(path: str | Path | None = None) -> Rig:
    """Load a rig YAML file (None: the packaged default). Errors are ConfigErrors naming the file."""
    path = default_rig_path() if path is None else Path(path)
    data = read_yaml_mapping(path)
    try:
        return rig_from_dict(data, source=path)
    except ConfigError as err:
        raise ConfigError(err.message, path) from None


__all__ = [
    "ArmConfig",
    "CameraBody",
    "Margins",
    "Rig",
    "Table",
    "Workspace",
    "default_rig_path",
    "load_rig",
    "rig_from_dict",
]
