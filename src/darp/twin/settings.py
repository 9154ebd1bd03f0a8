"""Error profiles of the digital twin: every magnitude the twin perturbs or simulates is a named setting.

Two profiles ship: ``ideal`` (no error of any kind: the twin then writes exactly what eq. 1 predicts)
and ``realistic`` (the error sources that make calibration and fusion hard on the real rig, DESIGN.md
"Error model of the twin"). A profile is a plain frozen dataclass tree, saved beside every twin survey
as ``truth/settings.yaml`` and loadable from YAML, so a run can be repeated exactly.

How the magnitudes are used (see :mod:`darp.twin.truth`):

- joint-zero bias: per joint, uniform in ``[-zero_bias_max_deg, +zero_bias_max_deg]``;
- encoder noise: white Gaussian on every reported angle, ``encoder_noise_std_deg``;
- hand-eye mount error: a rigid perturbation of the nominal ``T_wrist_cam`` whose translation has
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
from darp.formats.limits import CAMERA_FPS_MAX, IMAGE_SIDE_MAX_PX, JOINT_LOG_RATE_MAX_HZ, TIME_MAX_S
from darp.formats.schema import dataclass_from_mapping, refuse_unknown_keys
from darp.formats.text import read_yaml_mapping

SCHEMA = "darp-twin-settings/1"
PROFILES = ("ideal", "realistic", "paper")
DEPTH_NOISE_PROFILES = ("ideal", "realistic", "paper")


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
        if self.start_time_s > TIME_MAX_S:  # past year 5100: a time in milliseconds, or a corrupt value
            raise ConfigError(f"timing.start_time_s: at most {TIME_MAX_S:.0e} s (Unix seconds), "
                              f"got {self.start_time_s!r}")
        if self.joint_log_rate_hz > JOINT_LOG_RATE_MAX_HZ:  # a simulated logger faster than any arm's
            raise ConfigError(f"timing.joint_log_rate_hz: at most {JOINT_LOG_RATE_MAX_HZ:.0f} Hz, "
                              f"got {self.joint_log_rate_hz!r}")
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
        for name, high in (("width", IMAGE_SIDE_MAX_PX), ("height", IMAGE_SIDE_MAX_PX), ("fps", CAMERA_FPS_MAX),
                           ("accel_hz", JOINT_LOG_RATE_MAX_HZ), ("gyro_hz", JOINT_LOG_RATE_MAX_HZ)):
            if getattr(self, name) > high:
                raise ConfigError(f"camera.{name}: at most {high:g}, got {getattr(self, name)!r}")
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
class ArmErrorSettings:
    """Arm errors that joint-zero, mount and base calibration cannot absorb (all zero: a rigid, exact arm).

    - ``link_origin_std_mm``: each joint origin (link length / offset) off its nominal value by a vector of
      length ``sqrt(3)`` x this (the RMS per axis) in a random direction, per arm;
    - ``axis_tilt_std_deg``: each joint axis tilted by ``sqrt(2)`` x this (the RMS per perpendicular axis)
      about a random axis perpendicular to it;
    - ``joint_stiffness_nm_per_rad``: torsional stiffness of joints 2-4 (the ones that carry the arm
      against gravity); 0 = rigid. Sag = gravity torque (links and ``payload_kg`` at the flange) / stiffness,
      on the link side, so the encoders do not see it;
    - ``backlash_deg``: dead band per joint; the link sits half of it behind in the direction of the last move;
    - ``repeatability_mm``: the flange arrives within about this of the same target (per move, Gaussian on the
      joints scaled by the reach);
    - ``unabsorbed_mm``: when > 0, the origin and tilt directions are drawn again (their sizes unchanged)
      until the part of the geometry that darp's calibration model cannot absorb, at typical calibration
      configurations, is this size (median, points 0.4 m in front of the camera; within 5 %;
      :func:`darp.twin.arm_errors.unabsorbable_mm`); 0 = the first draw, whatever its size.
    """

    link_origin_std_mm: float = 0.0
    axis_tilt_std_deg: float = 0.0
    joint_stiffness_nm_per_rad: float = 0.0
    payload_kg: float = 0.0
    backlash_deg: float = 0.0
    repeatability_mm: float = 0.0
    unabsorbed_mm: float = 0.0

    def __post_init__(self) -> None:
        _check_nonneg(self, "arm_errors", tuple(f.name for f in dataclasses.fields(self)))


@dataclass(frozen=True)
class DepthErrorSettings:
    """Per-unit depth and intrinsics errors of the cameras (all zero: depth and intrinsics exact).

    Measured depth ``z' = z * (1 + s + d(t)) + o + b * z^2`` on valid pixels, with per-unit scale
    ``s = +-scale_std_pct %``, offset ``o = +-offset_std_mm``, distance bias ``b = +-bias_std_mm_per_m2`` and
    thermal drift ``d(t) = +-thermal_drift_pct % * (1 - exp(-t / tau))`` of the session time ``t``. The
    recording's (factory) intrinsics differ from the rendering's true ones by ``+-focal_std_pct %`` in fx, fy
    and by ``sqrt(2) x centre_std_px`` in a random direction in cx, cy, per stream.
    ``frame_field_px``: std of a smooth, low-frequency disparity error field drawn anew for every frame
    (the D400 depth "breathing" and waves that differ between frames; depth error ``z^2 e / (fx B)``).
    ``static_field_px``: std of a smooth disparity error field fixed to each sensor (drawn once per unit: the
    non-flatness a D400 shows on a flat wall, the same in every frame, so a surface point's depth error
    changes as it moves across the image between views).
    Each sign is drawn per unit: a unit's errors are one draw of exactly the stated sizes.
    """

    scale_std_pct: float = 0.0
    offset_std_mm: float = 0.0
    bias_std_mm_per_m2: float = 0.0
    thermal_drift_pct: float = 0.0
    thermal_tau_s: float = 600.0
    focal_std_pct: float = 0.0
    centre_std_px: float = 0.0
    frame_field_px: float = 0.0
    static_field_px: float = 0.0

    def __post_init__(self) -> None:
        _check_nonneg(self, "depth_errors", tuple(f.name for f in dataclasses.fields(self)))
        _check_pos(self, "depth_errors", ("thermal_tau_s",))


@dataclass(frozen=True)
class SyncSettings:
    """Camera-to-joint-log timing errors and motion during exposure (all zero: exact stamps, no blur).

    Camera frame stamps = exposure instant + ``latency_ms`` + ``N(0, jitter_ms)`` per frame; the colour
    image is smeared over the image motion during ``exposure_ms`` (blur while an arm moves).
    """

    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    exposure_ms: float = 0.0

    def __post_init__(self) -> None:
        _check_nonneg(self, "sync", ("jitter_ms", "exposure_ms"))
        if not np.isfinite(self.latency_ms):
            raise ConfigError("sync.latency_ms: must be finite")


@dataclass(frozen=True)
class ImageErrorSettings:
    """Photographic errors of the colour images the board is detected on (all zero: clean renders).

    Gaussian blur of ``blur_sigma_px``, uneven light (a linear gradient across the image plus vignetting,
    each up to ``shading_pct`` % of the brightness, random direction per frame) and extra sensor noise
    ``noise_dn`` (8-bit numbers).
    """

    blur_sigma_px: float = 0.0
    shading_pct: float = 0.0
    noise_dn: float = 0.0

    def __post_init__(self) -> None:
        _check_nonneg(self, "images", tuple(f.name for f in dataclasses.fields(self)))


@dataclass(frozen=True)
class LightingSettings:
    """The scene's lights (the defaults are the twin's fixed studio lighting).

    ``ambient``: grey level of the headlight's ambient and diffuse terms; ``key`` / ``fill``: diffuse
    intensity of the two directional lights; ``key_yaw_deg``: the key light's direction turned about the
    vertical. ``darp twin generate`` draws these per survey to vary the lighting.
    """

    ambient: float = 0.35
    key: float = 0.45
    fill: float = 0.25
    key_yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        _check_nonneg(self, "lighting", ("ambient", "key", "fill"))
        for name in ("ambient", "key", "fill"):
            if getattr(self, name) > 1.0:
                raise ConfigError(f"lighting.{name}: must be at most 1, got {getattr(self, name)!r}")
        if not (isinstance(self.key_yaw_deg, (int, float)) and np.isfinite(self.key_yaw_deg)
                and abs(self.key_yaw_deg) <= 360.0):
            raise ConfigError(f"lighting.key_yaw_deg: must be a finite angle within +-360, got {self.key_yaw_deg!r}")


# Groups added after the first profiles: omitted from the YAML while they hold their defaults, so that
# ``ideal`` and ``realistic`` settings files, and every file that records them, stay as they were.
OPTIONAL_GROUPS = ("arm_errors", "depth_errors", "sync", "images", "lighting")


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
    arm_errors: ArmErrorSettings = field(default_factory=ArmErrorSettings)
    depth_errors: DepthErrorSettings = field(default_factory=DepthErrorSettings)
    sync: SyncSettings = field(default_factory=SyncSettings)
    images: ImageErrorSettings = field(default_factory=ImageErrorSettings)
    lighting: LightingSettings = field(default_factory=LightingSettings)

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
        elif name == "paper":
            base = paper_profile(seed)
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
        data = {"schema": SCHEMA, **dataclasses.asdict(self)}
        for name in OPTIONAL_GROUPS:
            if getattr(self, name) == type(getattr(self, name))():
                del data[name]
        return data

    def scaled(self, factor: float) -> TwinSettings:
        """A copy with every error magnitude multiplied by ``factor`` (robustness sweeps).

        Scaled: joint bias and encoder noise, mount and base errors, joint-log jitter and camera clock
        offset, every arm, depth, sync and image error (stiffness divided, so that sag scales too).
        Not scaled: rates, resolution, dropout probabilities, the depth noise model, the thermal time constant,
        the lighting.
        """
        if not (np.isfinite(factor) and factor >= 0):
            raise ConfigError(f"scale factor must be a finite number >= 0, got {factor!r}")

        def times(group: Any, skip: tuple[str, ...] = ()) -> Any:
            return dataclasses.replace(group, **{f.name: getattr(group, f.name) * factor
                                                 for f in dataclasses.fields(group) if f.name not in skip})

        arm = times(self.arm_errors, ("joint_stiffness_nm_per_rad", "payload_kg"))
        if self.arm_errors.joint_stiffness_nm_per_rad > 0:
            arm = dataclasses.replace(arm, joint_stiffness_nm_per_rad=(
                self.arm_errors.joint_stiffness_nm_per_rad / factor if factor > 0 else 0.0))
        return dataclasses.replace(
            self,
            joints=times(self.joints),
            mounts=times(self.mounts),
            timing=dataclasses.replace(self.timing, joint_log_jitter_ms=self.timing.joint_log_jitter_ms * factor,
                                       camera_clock_offset_ms=self.timing.camera_clock_offset_ms * factor),
            arm_errors=arm,
            depth_errors=times(self.depth_errors, ("thermal_tau_s",)),
            sync=times(self.sync),
            images=times(self.images),
        )

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
        groups = [f.name for f in dataclasses.fields(cls) if f.name not in ("profile", "seed")]
        refuse_unknown_keys(data, groups, error=ConfigError)
        changes: dict[str, Any] = {}
        for key, value in data.items():
            if value is None:
                raise ConfigError(f"{key}: expected a mapping of settings, got nothing")
            current = getattr(base, key)
            changes[key] = dataclass_from_mapping(type(current), value, key, base=current, error=ConfigError)
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


def paper_profile(seed: int = 0) -> TwinSettings:
    """The ``paper`` profile: real-rig error levels, each inside the range docs/twin.md cites for it.

    Tuned toward the paper's real-rig figures (:mod:`darp.paper`: hand-eye held-out, held-out point-to-mesh
    median ...). Kinematic and per-unit camera errors are drawn at exactly their stated size in a
    random direction or sign; the kinematic directions are chosen so that the part darp's calibration model
    cannot absorb is 2.5 mm (``unabsorbed_mm``: which unit of those sizes, not a larger size); part of the
    smooth depth error is fixed to each sensor (``static_field_px``). Per-seed tables and the demo's figures
    are in docs/twin.md.
    """
    return TwinSettings(
        profile="paper",
        seed=seed,
        joints=JointErrorSettings(zero_bias_max_deg=1.0, encoder_noise_std_deg=0.01),
        mounts=MountErrorSettings(hand_eye_translation_mm=3.0, hand_eye_rotation_deg=1.0, base_translation_mm=4.0,
                                  base_yaw_deg=0.3, base_tilt_deg=0.05),
        timing=TimingSettings(),
        camera=CameraSettings(),
        motion=MotionSettings(),
        arm_errors=PAPER_ARM_ERRORS,
        depth_errors=PAPER_DEPTH_ERRORS,
        sync=PAPER_SYNC,
        images=PAPER_IMAGES,
    )


# The paper profile's non-absorbable errors (sources and ranges: docs/twin.md, "Error sources").
PAPER_ARM_ERRORS = ArmErrorSettings(link_origin_std_mm=1.0, axis_tilt_std_deg=0.2, joint_stiffness_nm_per_rad=1000.0,
                                    payload_kg=0.2, backlash_deg=0.22, repeatability_mm=0.1, unabsorbed_mm=2.5)
PAPER_DEPTH_ERRORS = DepthErrorSettings(scale_std_pct=1.0, offset_std_mm=2.0, bias_std_mm_per_m2=4.0,
                                        thermal_drift_pct=0.4, thermal_tau_s=600.0, focal_std_pct=0.3,
                                        centre_std_px=1.0, frame_field_px=0.1, static_field_px=0.15)
PAPER_SYNC = SyncSettings(latency_ms=5.0, jitter_ms=1.0, exposure_ms=8.0)
PAPER_IMAGES = ImageErrorSettings(blur_sigma_px=0.8, shading_pct=20.0, noise_dn=2.0)


__all__ = [
    "OPTIONAL_GROUPS", "PROFILES", "ArmErrorSettings", "CameraSettings", "DepthErrorSettings",
    "ImageErrorSettings", "JointErrorSettings", "LightingSettings", "MotionSettings", "MountErrorSettings",
    "SyncSettings",
    "TimingSettings", "TwinSettings", "paper_profile",
]
