"""Geometry of a simulated D435-class camera: intrinsics, extrinsics, stream profiles, per-unit variation.

Frames (all OpenCV optical frames, x right, y down, z forward):

- ``depth``: the left IR imager; depth, ``ir1`` and the IMU axes are expressed in it. The twin's
  ``T_world_cam`` is this frame.
- ``ir2``: the right IR imager, ``baseline_m`` along +x of depth (librealsense reports depth -> ir2 as a
  translation of about -50 mm along x: ``T_ir2_depth``).
- ``color``: the RGB imager. librealsense's "extrinsic depth -> colour" maps depth points into the
  colour frame (``T_color_depth``); its translation is about (+15, 0, +0.4) mm, so the colour camera
  sits about 15 mm along -x of the left imager (D435 layout seen from the front: right IR, projector,
  left IR, RGB).

A unit's factory calibration is stored at 640x480 (where the facts give typical ranges) and scaled to
other resolutions the way the D4 derives them from the full sensor: scale ``s = max(W / W_full,
H / H_full)`` then a centred crop. Focal lengths scale by ``s``; the principal point keeps its scaled
offset from the image centre ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integer coordinates).
Full sensors: IR 1280x800, colour 1920x1080. Source: docs/twin-camera.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from darp.errors import ConfigError
from darp.formats.realsense.types import Intrinsics, MotionIntrinsics, StreamProfile
from darp.geometry.transforms import skew
from darp.kinematics.transforms import compose, invert_transform

DEPTH_FULL_SENSOR = (1280, 800)
COLOUR_FULL_SENSOR = (1920, 1080)
DEPTH_RESOLUTIONS = ((1280, 720), (848, 480), (640, 480), (640, 360), (480, 270), (424, 240))
COLOUR_RESOLUTIONS = (
    (1920, 1080),
    (1280, 720),
    (960, 540),
    (848, 480),
    (640, 480),
    (640, 360),
    (424, 240),
    (320, 240),
    (320, 180),
)
DEPTH_FPS = (6, 15, 30, 60, 90)
COLOUR_FPS = (6, 15, 30, 60)
ACCEL_HZ = (63, 100, 200, 250)
GYRO_HZ = (200, 400)
REFERENCE_RESOLUTION = (640, 480)
DEPTH_UNIT_M = 0.001
MAX_DISPARITY_PX = 126  # D4 disparity search range at disparity shift 0 (sets the minimum depth)


@dataclass(frozen=True)
class UnitCalibration:
    """One camera unit's factory calibration at 640x480 (depth and colour) plus its stereo/colour geometry."""

    depth_fx: float = 383.5
    depth_fy: float = 383.5
    depth_ppx: float = 320.5
    depth_ppy: float = 241.0
    colour_fx: float = 610.5
    colour_fy: float = 609.5
    colour_ppx: float = 318.5
    colour_ppy: float = 242.5
    baseline_m: float = 0.050
    t_color_depth_m: tuple[float, float, float] = (0.015, 0.0, 0.0004)
    rotvec_color_depth_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    projector_x_m: float = 0.025  # projector position along +x of the left imager (between the imagers)


def draw_unit(rng: np.random.Generator | int) -> UnitCalibration:
    """A plausible unit: every value drawn uniformly within the facts' typical ranges."""
    g = np.random.default_rng(rng)
    fx = g.uniform(382.0, 385.0)
    rot_axis = g.normal(size=3)
    rot_axis /= np.linalg.norm(rot_axis, axis=-1)  # axis=-1: no BLAS (see T_depth_stream)
    rot_angle = np.deg2rad(g.uniform(0.0, 0.4))
    rx, ry, rz = (float(x) for x in rot_axis * rot_angle)
    return UnitCalibration(
        depth_fx=fx,
        depth_fy=float(np.clip(fx + g.uniform(-0.5, 0.5), 382.0, 385.0)),
        depth_ppx=g.uniform(319.0, 322.0),
        depth_ppy=g.uniform(236.0, 246.0),
        colour_fx=g.uniform(606.0, 615.0),
        colour_fy=g.uniform(606.0, 613.0),
        colour_ppx=g.uniform(314.0, 323.0),
        colour_ppy=g.uniform(237.0, 248.0),
        baseline_m=g.uniform(0.0497, 0.0503),
        t_color_depth_m=(g.uniform(0.0145, 0.0153), g.uniform(-0.0002, 0.0002), g.uniform(0.0, 0.0008)),
        rotvec_color_depth_rad=(rx, ry, rz),
        projector_x_m=g.uniform(0.020, 0.030),
    )


def scale_intrinsics(ref: Intrinsics, full_sensor: tuple[int, int], size: tuple[int, int]) -> Intrinsics:
    """Intrinsics of mode ``size`` from those of mode ``ref`` of the same sensor (scale, centred crop)."""
    w_full, h_full = full_sensor
    s_ref = max(ref.width / w_full, ref.height / h_full)
    width, height = size
    s = max(width / w_full, height / h_full)
    k = s / s_ref
    return Intrinsics(
        width=width,
        height=height,
        fx=ref.fx * k,
        fy=ref.fy * k,
        ppx=(width - 1) / 2 + (ref.ppx - (ref.width - 1) / 2) * k,
        ppy=(height - 1) / 2 + (ref.ppy - (ref.height - 1) / 2) * k,
        model=ref.model,
        coeffs=ref.coeffs,
    )


def _rotvec_to_matrix(rotvec: tuple[float, float, float]) -> np.ndarray:
    theta = float(np.linalg.norm(np.asarray(rotvec, dtype=float), axis=-1))
    if theta < 1e-15:
        return np.eye(3)
    k = np.asarray(rotvec, dtype=float) / theta
    kx = skew(k)
    R: np.ndarray = np.eye(3) + np.sin(theta) * kx + (1.0 - np.cos(theta)) * compose(kx, kx)
    return R


@dataclass(frozen=True, eq=False)  # eq on numpy fields is ambiguous
class CameraSpec:
    """Everything the twin and the recorder need to know about one camera's streams and geometry."""

    serial: str
    depth: Intrinsics  # also ir1 and ir2 (rectified pair)
    color: Intrinsics
    baseline_m: float
    T_color_depth: np.ndarray = field(repr=False)  # librealsense extrinsic depth -> colour
    projector_x_m: float = 0.025
    fps: int = 30
    colour_fps: int = 30
    accel_hz: int = 250
    gyro_hz: int = 200
    depth_unit_m: float = DEPTH_UNIT_M
    name: str = "Intel RealSense D435I"

    @property
    def T_ir2_depth(self) -> np.ndarray:
        """librealsense extrinsic depth -> ir2: a translation of -baseline along x."""
        T = np.eye(4)
        T[0, 3] = -self.baseline_m
        return T

    @property
    def min_depth_m(self) -> float:
        """Closest measurable depth: disparity at the end of the D4 search range."""
        return self.depth.fx * self.baseline_m / MAX_DISPARITY_PX

    def T_depth_stream(self, key: str) -> np.ndarray:
        """Pose of stream ``key``'s optical frame in the depth frame (``T_depth_<key>``).

        Rigid inverses and products without BLAS (:func:`~darp.kinematics.transforms.compose`): these
        poses reach the bags and the rendered images, which must not depend on the BLAS kernel.
        """
        if key in ("depth", "ir1", "accel", "gyro"):
            return np.eye(4)
        if key == "ir2":
            return invert_transform(self.T_ir2_depth)
        if key == "color":
            return invert_transform(self.T_color_depth)
        raise ConfigError(f"unknown stream {key!r} (streams: depth, color, ir1, ir2, accel, gyro)")

    def extrinsics(self, source: str, target: str) -> np.ndarray:
        """4x4 ``T_target_source`` between two streams, as ``Recording.extrinsics`` returns it."""
        return compose(invert_transform(self.T_depth_stream(target)), self.T_depth_stream(source))

    def stream_profiles(self) -> dict[str, StreamProfile]:
        """The six streams of a D435i recording as darp ``StreamProfile`` objects, by darp stream key."""
        identity_imu = MotionIntrinsics(data=(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0))
        d, c = self.depth, self.color
        return {
            "depth": StreamProfile("depth", "Depth", 0, 0, "z16", self.fps, d.width, d.height, d),
            "ir1": StreamProfile("ir1", "Infrared", 1, 0, "y8", self.fps, d.width, d.height, d),
            "ir2": StreamProfile("ir2", "Infrared", 2, 0, "y8", self.fps, d.width, d.height, d),
            "color": StreamProfile("color", "Color", 0, 1, "bgr8", self.colour_fps, c.width, c.height, c),
            "accel": StreamProfile(
                "accel", "Accel", 0, 2, "motion_xyz32f", self.accel_hz, motion_intrinsics=identity_imu
            ),
            "gyro": StreamProfile(
                "gyro", "Gyro", 0, 2, "motion_xyz32f", self.gyro_hz, motion_intrinsics=identity_imu
            ),
        }


def _mode(size: tuple[int, int], modes: tuple[tuple[int, int], ...], what: str) -> tuple[int, int]:
    """``size`` as a (width, height) tuple, or a ConfigError listing the D435 modes."""
    width, height = (int(x) for x in size)
    if (width, height) not in modes:
        raise ConfigError(f"{what} resolution {width}x{height} is not a D435 mode (modes: {modes})")
    return width, height


def make_camera_spec(
    unit: UnitCalibration | None = None,
    *,
    serial: str = "000000000000",
    depth_resolution: tuple[int, int] = REFERENCE_RESOLUTION,
    colour_resolution: tuple[int, int] = REFERENCE_RESOLUTION,
    fps: int = 30,
    colour_fps: int = 30,
    accel_hz: int = 250,
    gyro_hz: int = 200,
) -> CameraSpec:
    """Build a camera's streams at the requested modes from a unit calibration (nominal if ``None``)."""
    unit = unit if unit is not None else UnitCalibration()
    depth_size = _mode(depth_resolution, DEPTH_RESOLUTIONS, "depth")
    colour_size = _mode(colour_resolution, COLOUR_RESOLUTIONS, "colour")
    if fps not in DEPTH_FPS or colour_fps not in COLOUR_FPS:
        raise ConfigError(
            f"frame rates must be in {DEPTH_FPS} (depth) and {COLOUR_FPS} (colour), got {fps} and {colour_fps}"
        )
    if accel_hz not in ACCEL_HZ or gyro_hz not in GYRO_HZ:
        raise ConfigError(
            f"IMU rates must be in {ACCEL_HZ} (accel) and {GYRO_HZ} (gyro), got {accel_hz}, {gyro_hz}"
        )
    w_ref, h_ref = REFERENCE_RESOLUTION
    depth_ref = Intrinsics(
        w_ref, h_ref, unit.depth_fx, unit.depth_fy, unit.depth_ppx, unit.depth_ppy, "Brown Conrady"
    )
    colour_ref = Intrinsics(
        w_ref, h_ref, unit.colour_fx, unit.colour_fy, unit.colour_ppx, unit.colour_ppy, "Inverse Brown Conrady"
    )
    T_color_depth = np.eye(4)
    T_color_depth[:3, :3] = _rotvec_to_matrix(unit.rotvec_color_depth_rad)
    T_color_depth[:3, 3] = unit.t_color_depth_m
    return CameraSpec(
        serial=serial,
        depth=scale_intrinsics(depth_ref, DEPTH_FULL_SENSOR, depth_size),
        color=scale_intrinsics(colour_ref, COLOUR_FULL_SENSOR, colour_size),
        baseline_m=unit.baseline_m,
        T_color_depth=T_color_depth,
        projector_x_m=unit.projector_x_m,
        fps=fps,
        colour_fps=colour_fps,
        accel_hz=accel_hz,
        gyro_hz=gyro_hz,
    )


def with_resolution(
    spec: CameraSpec, depth_resolution: tuple[int, int], colour_resolution: tuple[int, int] | None = None
) -> CameraSpec:
    """The same unit at other stream modes (colour unchanged when ``colour_resolution`` is None)."""
    depth = scale_intrinsics(
        spec.depth, DEPTH_FULL_SENSOR, _mode(depth_resolution, DEPTH_RESOLUTIONS, "depth")
    )
    color = spec.color
    if colour_resolution is not None:
        color = scale_intrinsics(
            spec.color, COLOUR_FULL_SENSOR, _mode(colour_resolution, COLOUR_RESOLUTIONS, "colour")
        )
    return replace(spec, depth=depth, color=color)
