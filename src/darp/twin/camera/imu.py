"""Accelerometer and gyroscope samples of a D435i-class IMU moving along a camera trajectory.

Frame convention (librealsense): motion samples are reported in the depth sensor's axes, after the
SDK rotates the raw BMI055 axes: x right, y down, z forward (the OpenCV depth frame). The
accelerometer measures specific force ``f = R_world_imu^T (a_world - g_world)`` in m/s^2, so a camera
at rest and level (y down) reads about (0, -9.81, 0); facing the floor (z down) about (0, 0, -9.81).
The gyroscope measures the body angular velocity in the same axes, rad/s. ``T_depth_imu`` places the
IMU's centre relative to the depth frame (a lever arm; zero by default: the offset of the D435i's
accelerometer is a few millimetres and no unit value is in the facts).

Motion comes from a pose function ``T_world_cam(t_s)`` (the depth frame's pose, vectorised over an
array of times); velocities and accelerations are central differences of it, so it must be smooth
(C2) around the sample times. :func:`pose_function_from_samples` turns sampled poses into one
(cubic spline for position, rotation spline for orientation).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from darp.errors import TwinError
from darp.kinematics.transforms import matvec

PoseFunction = Callable[[np.ndarray], np.ndarray]  # (N,) times in s -> (N, 4, 4) T_world_cam
STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class ImuSettings:
    """IMU error magnitudes (white noise densities, per-unit constant biases) and geometry."""

    accel_noise_density: float = 1.5e-3  # m/s^2/sqrt(Hz): BMI055 150 ug/sqrt(Hz)
    gyro_noise_density: float = 2.4e-4  # rad/s/sqrt(Hz): BMI055 0.014 deg/s/sqrt(Hz)
    accel_bias_sigma: float = 0.1  # m/s^2 per axis (uncalibrated D435i units read |g| off by 0.1-0.4)
    gyro_bias_sigma: float = 0.003  # rad/s per axis (still D435i units show a few mrad/s)
    gravity_world: tuple[float, float, float] = (0.0, 0.0, -STANDARD_GRAVITY_M_S2)  # world z up
    t_depth_imu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU centre in the depth frame
    difference_step_s: float = 1e-3  # central-difference step for velocities and accelerations

    def __post_init__(self) -> None:
        if (
            min(
                self.accel_noise_density, self.gyro_noise_density, self.accel_bias_sigma, self.gyro_bias_sigma
            )
            < 0
        ):
            raise TwinError("IMU noise densities and bias sigmas must be >= 0")
        if self.difference_step_s <= 0:
            raise TwinError(f"difference_step_s must be > 0, got {self.difference_step_s}")

    @classmethod
    def ideal(cls) -> ImuSettings:
        """Exact samples: no noise, no bias."""
        return cls(accel_noise_density=0.0, gyro_noise_density=0.0, accel_bias_sigma=0.0, gyro_bias_sigma=0.0)


def _check_poses(T: np.ndarray, n: int) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (n, 4, 4) or not np.all(np.isfinite(T)):
        raise TwinError(f"pose function must return finite (N, 4, 4) poses, got shape {T.shape}")
    return T


class ImuSimulator:
    """Samples one IMU along a trajectory; biases are drawn once from the seed (a unit's constant bias)."""

    def __init__(self, settings: ImuSettings, seed: int | np.random.Generator = 0) -> None:
        self.settings = settings
        self._rng = np.random.default_rng(seed)
        self.accel_bias = self._rng.normal(0.0, settings.accel_bias_sigma, 3)
        self.gyro_bias = self._rng.normal(0.0, settings.gyro_bias_sigma, 3)

    def true_specific_force(self, t_s: np.ndarray, pose: PoseFunction) -> np.ndarray:
        """(N, 3) exact accelerometer values in the IMU (depth) axes, m/s^2."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        h = self.settings.difference_step_s
        lever = np.asarray(self.settings.t_depth_imu_m, dtype=float)
        T_prev, T_now, T_next = (_check_poses(pose(t + k * h), t.size) for k in (-1, 0, 1))
        p = [T[:, :3, 3] + matvec(T[:, :3, :3], lever) for T in (T_prev, T_now, T_next)]  # no BLAS
        a_world = (p[2] - 2.0 * p[1] + p[0]) / (h * h)
        f_world = a_world - np.asarray(self.settings.gravity_world, dtype=float)
        f_imu: np.ndarray = np.einsum("nji,nj->ni", T_now[:, :3, :3], f_world)  # R^T f
        return f_imu

    def true_angular_velocity(self, t_s: np.ndarray, pose: PoseFunction) -> np.ndarray:
        """(N, 3) exact body angular velocity in the IMU (depth) axes, rad/s."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        h = self.settings.difference_step_s
        R_prev = _check_poses(pose(t - h), t.size)[:, :3, :3]
        R_next = _check_poses(pose(t + h), t.size)[:, :3, :3]
        R_rel = np.einsum("nji,njk->nik", R_prev, R_next)  # R_prev^T R_next: rotation in body axes
        w: np.ndarray = Rotation.from_matrix(R_rel).as_rotvec() / (2.0 * h)
        return w

    def accel(self, t_s: np.ndarray, pose: PoseFunction, rate_hz: float) -> np.ndarray:
        """(N, 3) accelerometer samples with bias and white noise for a stream at ``rate_hz``."""
        f = self.true_specific_force(t_s, pose)
        sigma = float(self.settings.accel_noise_density * np.sqrt(rate_hz))
        return f + self.accel_bias + self._rng.normal(0.0, 1.0, f.shape) * sigma

    def gyro(self, t_s: np.ndarray, pose: PoseFunction, rate_hz: float) -> np.ndarray:
        """(N, 3) gyroscope samples with bias and white noise for a stream at ``rate_hz``."""
        w = self.true_angular_velocity(t_s, pose)
        sigma = float(self.settings.gyro_noise_density * np.sqrt(rate_hz))
        return w + self.gyro_bias + self._rng.normal(0.0, 1.0, w.shape) * sigma

    def sample(
        self,
        t_start_s: float,
        t_stop_s: float,
        pose: PoseFunction,
        accel_hz: float = 250.0,
        gyro_hz: float = 200.0,
    ) -> dict[str, np.ndarray]:
        """Both streams on their own clocks over ``[t_start_s, t_stop_s)``.

        Returns ``accel_t_s`` (N,), ``accel`` (N, 3), ``gyro_t_s`` (M,), ``gyro`` (M, 3).
        """
        if not t_stop_s > t_start_s or accel_hz <= 0 or gyro_hz <= 0:
            raise TwinError(
                f"IMU sampling needs t_stop > t_start and positive rates, got "
                f"[{t_start_s}, {t_stop_s}) at {accel_hz}/{gyro_hz} Hz"
            )
        t_accel = t_start_s + np.arange(int(np.ceil((t_stop_s - t_start_s) * accel_hz))) / accel_hz
        t_gyro = t_start_s + np.arange(int(np.ceil((t_stop_s - t_start_s) * gyro_hz))) / gyro_hz
        t_accel, t_gyro = t_accel[t_accel < t_stop_s], t_gyro[t_gyro < t_stop_s]
        return {
            "accel_t_s": t_accel,
            "accel": self.accel(t_accel, pose, accel_hz),
            "gyro_t_s": t_gyro,
            "gyro": self.gyro(t_gyro, pose, gyro_hz),
        }


def pose_function_from_samples(t_s: np.ndarray, T_world_cam: np.ndarray) -> PoseFunction:
    """A smooth pose function through sampled poses (cubic position spline, rotation spline).

    Times outside the samples are clamped to the ends (the IMU then reads the end state at rest
    only if the motion was at rest there).
    """
    t = np.asarray(t_s, dtype=float).reshape(-1)
    T = np.asarray(T_world_cam, dtype=float)
    if T.shape != (t.size, 4, 4) or t.size < 2 or np.any(np.diff(t) <= 0):
        raise TwinError(
            f"need >= 2 poses with strictly increasing times, got {t.size} times and poses of shape {T.shape}"
        )
    pos_spline = CubicSpline(t, T[:, :3, 3], axis=0)
    rot_spline = RotationSpline(t, Rotation.from_matrix(T[:, :3, :3]))

    def pose(times: np.ndarray) -> np.ndarray:
        tt = np.clip(np.asarray(times, dtype=float).reshape(-1), t[0], t[-1])
        out = np.tile(np.eye(4), (tt.size, 1, 1))
        out[:, :3, :3] = rot_spline(tt).as_matrix()
        out[:, :3, 3] = pos_spline(tt)
        return out

    return pose
