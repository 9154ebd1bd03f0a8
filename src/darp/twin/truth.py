"""Ground truth of the twin: drawing the true rig from the nominal one, and the ``truth/`` folder.

The true rig differs from the nominal rig file by the errors of :mod:`darp.twin.settings`:

- kinematic parameter errors (joint origins and axes, :mod:`darp.twin.arm_errors`), when set;
- joint-zero offsets ``dq`` per arm (uniform per joint); the true link angles are ``q_sdk + dq``,
  the sign convention of eq. 1, so ``truth/calibration.json`` is exactly what a perfect calibration
  would find;
- each camera mount ``T_wrist_cam = T_wrist_cam_nominal @ T_err`` (the error expressed in the
  camera frame: a translation of fixed length and a rotation of fixed angle, random directions);
- the second arm's base moved in the table plane, turned about the vertical and tilted slightly about
  its own origin, relative to the first; then both bases are expressed in darp's world as the rig
  defines it (origin midway between the two true base origins, x from the first towards the second, z
  the table normal), which is also how a calibration realises the world from what it measures. Truth and
  a calibration therefore share one world frame: errors against truth are the calibration's, with no
  convention offset ("gauge") between them. With no base error the world is the nominal one.

``truth/`` (beside the survey files, never needed to read the survey)::

    calibration.json          the true calibration, darp's calibration format
    object.ply                the object's surface in the world frame (metres)
    object.json               name, T_world_object, placement, scale, centre/radius/height
    camera_poses_<arm>.npz    per recorded frame: frame_number, timestamp_ms, t_host_s, T_world_cam, q_true_rad
    settings.yaml             the twin settings (profile, seed, every magnitude)
    README.txt                this description
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.atomic import atomic_path, write_json_atomic, write_text_atomic
from darp.formats.calibration import ArmCalibration, Calibration, read_calibration, write_calibration
from darp.formats.io_input import LIMITS
from darp.formats.text import read_utf8_text
from darp.formats.truth import (
    CALIBRATION_FILE,
    OBJECT_JSON_FILE,
    OBJECT_MESH_FILE,
    README_FILE,
    README_TEXT,
    SETTINGS_FILE,
    TRUTH_DIR,
    read_camera_poses,
    save_npz_deterministic,
)
from darp.kinematics import z1
from darp.kinematics.rig import WORLD_FRAME_TEXT, Rig
from darp.kinematics.transforms import (
    axis_angle_to_rotation,
    compose,
    invert_transform,
    make_transform,
    rot_z,
    world_from_base_origins,
)
from darp.twin.arm_errors import KinematicErrors, fk_batch_with_errors
from darp.twin.settings import TwinSettings


@dataclass(frozen=True, eq=False)
class TrueArm:
    """One arm as it really is."""

    arm_id: str
    serial: str
    T_world_base: np.ndarray
    T_wrist_cam: np.ndarray
    joint_offsets_rad: np.ndarray  # dq: q_true = q_sdk + dq
    kinematic_errors: KinematicErrors | None = None  # link origin and axis errors (None: the nominal Z1)


@dataclass(frozen=True, eq=False)
class TrueRig:
    """Both arms as they really are, plus the nominal rig they were drawn from."""

    nominal: Rig
    arms: dict[str, TrueArm]

    def T_world_cam(self, arm_id: str, q_true_rad: np.ndarray) -> np.ndarray:
        """True camera pose(s) for true joint angles (6,) or (N, 6): (4, 4) or (N, 4, 4)."""
        arm = self.arms[arm_id]
        Q = np.atleast_2d(q_true_rad)
        T_base_wrist = (z1.fk_batch(Q, self.nominal.wrist_frame) if arm.kinematic_errors is None
                        else fk_batch_with_errors(Q, arm.kinematic_errors, self.nominal.wrist_frame))
        poses = compose(arm.T_world_base, T_base_wrist, arm.T_wrist_cam)
        return poses[0] if np.ndim(q_true_rad) == 1 else poses

    def calibration(self, settings: TwinSettings) -> Calibration:
        """The true calibration in darp's format (what a perfect calibration would find)."""
        date = dt.datetime.fromtimestamp(settings.timing.start_time_s, tz=dt.UTC).date().isoformat()
        arms = {
            arm_id: ArmCalibration(
                serial=arm.serial,
                T_world_base=arm.T_world_base.copy(),
                T_wrist_cam=arm.T_wrist_cam.copy(),
                joint_offsets_rad=arm.joint_offsets_rad.copy(),
                residuals={},
            )
            for arm_id, arm in self.arms.items()
        }
        return Calibration(
            epoch=f"twin-truth:{settings.profile}:seed{settings.seed}",
            date=date,
            arms=arms,
            world_frame=WORLD_FRAME_TEXT,
            report={"source": "darp digital twin ground truth", "profile": settings.profile,
                    "seed": settings.seed, "joint_offset_convention": "q_true = q_logged + joint_offsets_rad"},
        )


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    unit: np.ndarray = v / np.linalg.norm(v, axis=-1)  # axis=-1: no BLAS (see compose)
    return unit


def perturbation(rng: np.random.Generator, translation_m: float, rotation_rad: float) -> np.ndarray:
    """A rigid transform whose translation has length ``translation_m`` and rotation angle ``rotation_rad``."""
    R = axis_angle_to_rotation(_random_unit(rng), rotation_rad) if rotation_rad > 0 else np.eye(3)
    t = _random_unit(rng) * translation_m if translation_m > 0 else np.zeros(3)
    return make_transform(R, t)


def draw_true_rig(rig: Rig, settings: TwinSettings) -> TrueRig:
    """Draw the true rig (joint-zero offsets, camera mounts, second base) for ``settings``' seed."""
    j, m = settings.joints, settings.mounts
    arms: dict[str, TrueArm] = {}
    for index, (arm_id, nominal) in enumerate(rig.arms.items()):
        g_joint = settings.rng(f"joint_zero:{arm_id}")
        bias = np.deg2rad(j.zero_bias_max_deg)
        dq = g_joint.uniform(-bias, bias, 6) if bias > 0 else np.zeros(6)
        g_mount = settings.rng(f"mount:{arm_id}")
        T_err = perturbation(g_mount, m.hand_eye_translation_mm * 1e-3, np.deg2rad(m.hand_eye_rotation_deg))
        T_wrist_cam = compose(nominal.T_wrist_cam, T_err)
        T_world_base = np.array(nominal.T_world_base, dtype=float)
        if index > 0:
            g_base = settings.rng(f"base:{arm_id}")
            phi = g_base.uniform(0.0, 2 * np.pi)
            yaw = np.deg2rad(m.base_yaw_deg) * g_base.choice([-1.0, 1.0])
            psi = g_base.uniform(0.0, 2 * np.pi)
            tilt_axis = np.array([np.cos(psi), np.sin(psi), 0.0])
            R_err = compose(rot_z(yaw), axis_angle_to_rotation(tilt_axis, np.deg2rad(m.base_tilt_deg)))
            T_world_base = make_transform(compose(R_err, T_world_base[:3, :3]),
                                          T_world_base[:3, 3] + m.base_translation_mm * 1e-3
                                          * np.array([np.cos(phi), np.sin(phi), 0.0]))
        kin = KinematicErrors.draw(settings.arm_errors, settings.rng(f"kinematics:{arm_id}"))
        arms[arm_id] = TrueArm(arm_id, nominal.camera_serial, T_world_base, T_wrist_cam, dq, kin)
    return TrueRig(nominal=rig, arms=_in_rig_world(arms))


def _in_rig_world(arms: dict[str, TrueArm]) -> dict[str, TrueArm]:
    """The arms with their bases re-expressed in the world defined by their true base origins and the
    table normal (:func:`~darp.kinematics.transforms.world_from_base_origins`); a single arm is left as is."""
    if len(arms) != 2:
        return arms
    first, second = arms.values()
    T_nominal_world = world_from_base_origins(first.T_world_base[:3, 3], second.T_world_base[:3, 3],
                                              np.array([0.0, 0.0, 1.0]))
    T_world_nominal = invert_transform(T_nominal_world)
    return {arm_id: replace(arm, T_world_base=compose(T_world_nominal, arm.T_world_base))
            for arm_id, arm in arms.items()}


# -- per-frame camera poses -----------------------------------------------------------------------

@dataclass
class CameraPoseTruth:
    """True pose of one camera at every recorded frame (appended while recording)."""

    frame_number: list[int] = field(default_factory=list)
    timestamp_ms: list[float] = field(default_factory=list)  # as written in the bag
    t_host_s: list[float] = field(default_factory=list)  # host-clock instant of the exposure
    T_world_cam: list[np.ndarray] = field(default_factory=list)
    q_true_rad: list[np.ndarray] = field(default_factory=list)

    def append(self, frame_number: int, timestamp_ms: float, t_host_s: float, T_world_cam: np.ndarray,
               q_true_rad: np.ndarray) -> None:
        self.frame_number.append(int(frame_number))
        self.timestamp_ms.append(float(timestamp_ms))
        self.t_host_s.append(float(t_host_s))
        self.T_world_cam.append(np.asarray(T_world_cam, dtype=np.float64))
        self.q_true_rad.append(np.asarray(q_true_rad, dtype=np.float64))

    def __len__(self) -> int:
        return len(self.frame_number)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self)
        return {
            "frame_number": np.asarray(self.frame_number, dtype=np.int64),
            "timestamp_ms": np.asarray(self.timestamp_ms, dtype=np.float64),
            "t_host_s": np.asarray(self.t_host_s, dtype=np.float64),
            "T_world_cam": np.asarray(self.T_world_cam, dtype=np.float64).reshape(n, 4, 4),
            "q_true_rad": np.asarray(self.q_true_rad, dtype=np.float64).reshape(n, 6),
        }


# -- the truth folder ------------------------------------------------------------------------------

def write_truth(
    folder: str | Path,
    *,
    true_rig: TrueRig,
    settings: TwinSettings,
    camera_poses: dict[str, CameraPoseTruth],
    object_info: dict[str, Any] | None = None,
    object_mesh_world: Any | None = None,
) -> Path:
    """Write ``folder/truth/``; ``object_mesh_world`` is a trimesh mesh in the world frame. Returns the path."""
    truth = Path(folder) / TRUTH_DIR
    truth.mkdir(parents=True, exist_ok=True)
    write_calibration(truth / CALIBRATION_FILE, true_rig.calibration(settings))
    settings.save(truth / SETTINGS_FILE)
    for arm_id, poses in camera_poses.items():
        save_npz_deterministic(truth / f"camera_poses_{arm_id}.npz", poses.arrays())
    if object_info is not None:
        write_json_atomic(truth / OBJECT_JSON_FILE, object_info)
    if object_mesh_world is not None:
        with atomic_path(truth / OBJECT_MESH_FILE) as tmp:
            tmp.write_bytes(object_mesh_world.export(file_type="ply", encoding="binary"))
    write_text_atomic(truth / README_FILE, README_TEXT)
    return truth


@dataclass
class SurveyTruth:
    """What ``read_truth`` returns."""

    calibration: Calibration
    settings: TwinSettings
    camera_poses: dict[str, dict[str, np.ndarray]]
    object_info: dict[str, Any] | None
    object_mesh_path: Path | None


def read_truth(survey_folder: str | Path) -> SurveyTruth:
    """Read ``<survey>/truth/`` (or the truth folder itself)."""
    folder = Path(survey_folder)
    truth = folder if folder.name == TRUTH_DIR else folder / TRUTH_DIR
    if not truth.is_dir():
        raise FormatError("no truth/ folder (only twin surveys have one)", folder)
    poses = {p.stem.removeprefix("camera_poses_"): read_camera_poses(p)
             for p in sorted(truth.glob("camera_poses_*.npz"))}
    object_info = None
    if (truth / OBJECT_JSON_FILE).is_file():
        try:
            object_info = json.loads(read_utf8_text(truth / OBJECT_JSON_FILE, "a JSON file", limit=LIMITS["json"]))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise FormatError(f"invalid JSON: {err}", truth / OBJECT_JSON_FILE) from err
    mesh = truth / OBJECT_MESH_FILE
    return SurveyTruth(
        calibration=read_calibration(truth / CALIBRATION_FILE),
        settings=TwinSettings.load(truth / SETTINGS_FILE),
        camera_poses=poses,
        object_info=object_info,
        object_mesh_path=mesh if mesh.is_file() else None,
    )


__all__ = [
    "TRUTH_DIR",
    "CameraPoseTruth",
    "SurveyTruth",
    "TrueArm",
    "TrueRig",
    "draw_true_rig",
    "perturbation",
    "read_truth",
    "write_truth",
]
