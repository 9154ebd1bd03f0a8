"""Error profiles of the digital twin: every magnitude the twin perturbs or simulates is a named setting.

Two profiles ship: ``ideal`` (no error of any kind: the twin then writes exactly what eq. 1 predicts)
and ``realistic`` (the error sources that make calibration and fusion hard on the real rig, DESIGN.md
"Error model of the twin"). A profile is a plain frozen dataclass tree, saved beside every twin survey
as ``truth/settings.yaml`` and loadable from YAML, so a run can be repeated exactly.

How the magnitudes are used (see :mod:`darp.twin.truth`):

- joint-zero bias: per joint, uniform in ``[-zero_bias_max_deg, +zero_bias_max_deg]``;
- encoder noise: white Gaussian on every reported angle, ``encoder_noise_std_deg``;
- hand-eye mount error: a rigid perturbation of the nominal ``T_flange_cam`` whose translation has
  length exactly ``hand_eye_translation_mm`` and whose rotation has angle exactly
  ``hand_eye_rotation_deg``, both about random directions (so the error size is known);
- second base error: the second arm's base moves by ``base_translation_mm`` in the table plane,
  turns by ``base_yaw_deg`` about the vertical and tilts by ``base_tilt_deg`` (random signs and
  directions); the first base defines the world frame with the table and is exact;
- timing: the joint log runs at ``joint_log_rate_hz`` with Gaussian interval jitter, cameras at
  ``fps``; camera timestamps may carry a constant ``camera_clock_offset_ms``.

Every random draw takes a generator from :meth:`TwinSettings.rng` with a purpose name, so that
changing, say, the frame rate does not change the drawn rig.
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from darp.errors import ConfigError
from darp.formats.atomic import write_text_atomic
from darp.formats.text import read_yaml_mapping

SCHEMA = "darp-twin-settings/1"
PROFILES = ("ideal", "realistic")
DEPTH_NOISE_PROFILES = ("ideal", "realistic")
CAMERA_STREAMS = ("depth", "color", "ir1", "ir2")


def _check_nonneg(obj: Any, prefix: str, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
            raise ConfigError(f"{prefix}.{name}: must be a finite number >= 0, got {value!r}")


def _check_pos(obj: Any, prefix: str, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
            raise ConfigError(f"{prefix}.{name}: must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class JointErrorSettings:
    """Joint-zero bias and encoder noise of both arms."""

    zero_bias_max_deg: float = 1.0  # per joint, uniform in [-max, max]
    encoder_noise_std_deg: float = 0.005  # white noise on every reported angle

    def __post_init__(self) -> None:
        _check_nonneg(self, "joints", ("zero_bias_max_deg", "encoder_noise_std_deg"))


@dataclass(frozen=True)
class MountErrorSettings:
    """How far the true camera mounts and the second base are from their nominal (CAD) values."""

    hand_eye_translation_mm: float = 3.0  # length of the mount translation error (random direction)
    hand_eye_rotation_deg: float = 1.0  # angle of the mount rotation error (random axis)
    base_translation_mm: float = 4.0  # second base, in the table plane (random direction)
    base_yaw_deg: float = 0.3  # second base, about the vertical (random sign)
    base_tilt_deg: float = 0.05  # second base, about a random horizontal axis

    def __post_init__(self) -> None:
        _check_nonneg(self, "mounts", tuple(f.name for f in dataclasses.fields(self)))


@dataclass(frozen=True)
class TimingSettings:
    """Host clock, joint-log rate and jitter, camera clock offset."""

    start_time_s: float = 1_700_000_000.0  # host clock at the start of the simulation (Unix seconds)
    joint_log_rate_hz: float = 33.0  # nominal logger rate (the paper: about 33 Hz)
    joint_log_jitter_ms: float = 2.0  # std of each logger interval (clipped to +-40% of the period)
    camera_clock_offset_ms: float = 0.0  # camera timestamp = host time + offset (optional error)
    camera_stagger_ms: float = 7.0  # second camera's frames start this much after the first's

    def __post_init__(self) -> None:
        _check_pos(self, "timing", ("start_time_s", "joint_log_rate_hz"))
        _check_nonneg(self, "timing", ("joint_log_jitter_ms", "camera_stagger_ms"))
        if not np.isfinite(self.camera_clock_offset_ms):
            raise ConfigError("timing.camera_clock_offset_ms: must be finite")


@dataclass(frozen=True)
class CameraSettings:
    """Stream modes and the camera noise model (passed to the twin camera)."""

    width: int = 640
    height: int = 480
    fps: int = 30  # depth, both infrared and colour
    accel_hz: int = 250
    gyro_hz: int = 200
    imu: bool = True  # record accel/gyro samples
    depth_noise: str = "realistic"  # noise profile name of the twin camera: ideal | realistic
    imu_noise: str = "realistic"  # IMU white noise and per-unit biases: ideal | realistic
    unit_variation: bool = True  # draw per-unit intrinsics within the D435's factory spread
    dropout_dark: float = 0.6  # depth dropout probability on object parts marked dark
    dropout_specular: float = 0.4  # ... marked specular (highlights, mirror-like metal)
    dropout_transparent: float = 0.9  # ... marked transparent
    # bag chunk compression: none | lz4. The DARP release's bags are uncompressed (137.94 GB for 63,600
    # depth frames: 2.17 MB per 640x480 frame set, the raw size), so the twin writes them that way too; lz4
    # saves about a quarter of the disk on the twin's noisy images for ~7 ms of CPU per frame set.
    compression: str = "none"

    def __post_init__(self) -> None:
        _check_pos(self, "camera", ("width", "height", "fps", "accel_hz", "gyro_hz"))
        if self.depth_noise not in DEPTH_NOISE_PROFILES:
            raise ConfigError(f"camera.depth_noise: must be one of {', '.join(DEPTH_NOISE_PROFILES)}, "
                              f"got {self.depth_noise!r}")
        for name in ("dropout_dark", "dropout_specular", "dropout_transparent"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
                raise ConfigError(f"camera.{name}: must be a probability in [0, 1], got {value!r}")
        if self.imu_noise not in DEPTH_NOISE_PROFILES:
            raise ConfigError(f"camera.imu_noise: must be ideal or realistic, got {self.imu_noise!r}")
        if self.compression not in ("lz4", "none"):
            raise ConfigError(f"camera.compression: must be lz4 or none, got {self.compression!r}")


@dataclass(frozen=True)
class MotionSettings:
    """Simulated arm motion (Z1 MoveJ-like) and the collision monitor."""

    max_speed_rad_s: float = 0.6  # default joint speed of a move (Z1 limit: pi rad/s)
    max_accel_rad_s2: float = 2.0
    settle_s: float = 0.1  # after a move, reported as moving for this long (controller settling)
    collision_check_hz: float = 60.0  # contact checks per simulated second while an arm moves

    def __post_init__(self) -> None:
        _check_pos(self, "motion", ("max_speed_rad_s", "max_accel_rad_s2", "collision_check_hz"))
        _check_nonneg(self, "motion", ("settle_s",))
        if self.max_speed_rad_s > np.pi:
            raise ConfigError(f"motion.max_speed_rad_s: above the Z1 limit of pi rad/s ({self.max_speed_rad_s})")


@dataclass(frozen=True)
class TwinSettings:
    """One complete twin configuration: profile name, seed and every error magnitude."""

    profile: str = "realistic"
    seed: int = 0
    joints: JointErrorSettings = field(default_factory=JointErrorSettings)
    mounts: MountErrorSettings = field(default_factory=MountErrorSettings)
    timing: TimingSettings = field(default_factory=TimingSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    motion: MotionSettings = field(default_factory=MotionSettings)

    def __post_init__(self) -> None:
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ConfigError(f"seed: must be an integer >= 0, got {self.seed!r}")

    @classmethod
    def from_profile(cls, name: str = "realistic", seed: int = 0, **overrides: Any) -> TwinSettings:
        """The named profile with ``seed``; ``overrides`` replace whole groups or top-level fields."""
        if name == "realistic":
            base = cls(profile="realistic", seed=seed)
        elif name == "ideal":
            base = cls(
                profile="ideal",
                seed=seed,
                joints=JointErrorSettings(zero_bias_max_deg=0.0, encoder_noise_std_deg=0.0),
                mounts=MountErrorSettings(0.0, 0.0, 0.0, 0.0, 0.0),
                timing=TimingSettings(joint_log_jitter_ms=0.0, camera_clock_offset_ms=0.0),
                camera=CameraSettings(depth_noise="ideal", imu_noise="ideal", unit_variation=False, dropout_dark=0.0,
                                      dropout_specular=0.0, dropout_transparent=0.0),
            )
        else:
            raise ConfigError(f"unknown twin profile {name!r} (profiles: {', '.join(PROFILES)})")
        return dataclasses.replace(base, **overrides) if overrides else base

    def with_camera(self, **changes: Any) -> TwinSettings:
        """A copy with camera settings changed (resolution, fps, noise...)."""
        return dataclasses.replace(self, camera=dataclasses.replace(self.camera, **changes))

    def with_timing(self, **changes: Any) -> TwinSettings:
        """A copy with timing settings changed."""
        return dataclasses.replace(self, timing=dataclasses.replace(self.timing, **changes))

    def rng(self, purpose: str) -> np.random.Generator:
        """A generator for one purpose (``"rig"``, ``"encoder:arm110"``...), stable across settings changes."""
        return np.random.default_rng([self.seed, zlib.crc32(purpose.encode("utf-8"))])

    # -- YAML ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, **dataclasses.asdict(self)}

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def save(self, path: str | Path) -> None:
        """Write the settings as YAML, atomically."""
        write_text_atomic(path, self.to_yaml())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TwinSettings:
        """Settings from parsed YAML; groups not given keep the named profile's values."""
        data = dict(data)
        schema = data.pop("schema", SCHEMA)
        if schema != SCHEMA:
            raise ConfigError(f"schema: expected {SCHEMA!r}, got {schema!r}")
        profile = data.pop("profile", "realistic")
        seed = data.pop("seed", 0)
        base = cls.from_profile(str(profile), seed=seed) if isinstance(seed, int) else cls(seed=seed)
        groups = {f.name: f.type for f in dataclasses.fields(cls) if f.name not in ("profile", "seed")}
        changes: dict[str, Any] = {}
        for key, value in data.items():
            if key not in groups:
                raise ConfigError(f"unknown settings group {key!r} (groups: {', '.join(groups)})")
            if not isinstance(value, dict):
                raise ConfigError(f"{key}: expected a mapping of settings")
            current = getattr(base, key)
            names = {f.name for f in dataclasses.fields(current)}
            unknown = sorted(map(str, set(value) - names))
            if unknown:
                raise ConfigError(f"{key}: unknown setting(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
            try:
                changes[key] = dataclasses.replace(current, **value)
            except TypeError as err:
                raise ConfigError(f"{key}: {err}") from None
        return dataclasses.replace(base, **changes)

    @classmethod
    def load(cls, path: str | Path) -> TwinSettings:
        """Read settings YAML; every problem is a ConfigError naming the file."""
        path = Path(path)
        data = read_yaml_mapping(path)
        try:
            return cls.from_dict(data)
        except ConfigError as err:
            raise ConfigError(err.message, path) from None


__all__ = [
    "CAMERA_STREAMS", "PROFILES", "CameraSettings", "JointErrorSettings", "MotionSettings",
    "MountErrorSettings", "TimingSettings", "TwinSettings",
]
