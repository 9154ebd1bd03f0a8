"""Robot- and camera-flavoured transforms: the Z1 SDK's roll-pitch-yaw posture, look-at camera poses, darp's
world frame from the two bases; and, re-exported, the SE(3) / SO(3) arithmetic of :mod:`darp.geometry.transforms`
(one definition, many callers import it from here).

- Camera frames follow OpenCV: x right, y down, z forward (the optical axis).
- The Z1 SDK posture is ``[roll, pitch, yaw, x, y, z]`` with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

Every function accepts a leading batch dimension where it says so.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError
from darp.geometry.transforms import (
    axis_angle_to_rotation,
    checked_array,
    compose,
    invert_transform,
    make_transform,
    matvec,
    orthonormalize,
    pose_error,
    quaternion_to_rotation,
    rotation_error_rad,
    rotation_to_quaternion,
    rotation_to_rotvec,
    rotvec_to_rotation,
    transform_points,
    translation_error_m,
)

Array = NDArray[np.float64]

__all__ = [
    "axis_angle_to_rotation",
    "compose",
    "invert_transform",
    "look_at",
    "look_at_rotation",
    "make_transform",
    "matvec",
    "orthonormalize",
    "pose_error",
    "posture_to_transform",
    "quaternion_to_rotation",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_error_rad",
    "rotation_to_quaternion",
    "rotation_to_rotvec",
    "rotation_to_rpy",
    "rotvec_to_rotation",
    "rpy_to_rotation",
    "transform_points",
    "transform_to_posture",
    "translation_error_m",
    "world_from_base_origins",
]


def _axis_rotation(angle_rad: ArrayLike, axis: int) -> Array:
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def rot_x(angle_rad: ArrayLike) -> Array:
    """Rotation about x by ``angle_rad`` (scalar or array -> (..., 3, 3))."""
    return _axis_rotation(angle_rad, 0)


def rot_y(angle_rad: ArrayLike) -> Array:
    """Rotation about y by ``angle_rad`` (scalar or array -> (..., 3, 3))."""
    return _axis_rotation(angle_rad, 1)


def rot_z(angle_rad: ArrayLike) -> Array:
    """Rotation about z by ``angle_rad`` (scalar or array -> (..., 3, 3))."""
    return _axis_rotation(angle_rad, 2)


def look_at_rotation(forward: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Array:
    """``R_world_cam`` (OpenCV: z = forward, y down, x right) for a viewing direction and an up hint.

    The image's up (-y) is the component of ``up`` orthogonal to ``forward``. Raises
    :class:`KinematicsError` when ``forward`` is (nearly) parallel to ``up``.
    """
    f = checked_array(forward, (3,), "forward")
    u = checked_array(up, (3,), "up")
    z = f / np.linalg.norm(f, axis=-1, keepdims=True)
    x = np.cross(z, u)  # right = forward x up in a right-handed frame
    nx = np.linalg.norm(x, axis=-1, keepdims=True)
    if np.any(nx < 1e-9 * np.linalg.norm(u, axis=-1, keepdims=True)):
        raise KinematicsError("look-at direction is parallel to the up hint; give another up")
    x = x / nx
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Array:
    """``T_world_cam`` of a camera at ``eye`` whose optical axis (+z) passes through ``target``."""
    e = checked_array(eye, (3,), "eye")
    t = checked_array(target, (3,), "target")
    if np.any(np.linalg.norm(t - e, axis=-1) < 1e-12):
        raise KinematicsError("look-at eye and target coincide")
    return make_transform(look_at_rotation(t - e, up), e)


def rpy_to_rotation(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> Array:
    """Z1 SDK convention: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (batched)."""
    return compose(rot_z(yaw_rad), rot_y(pitch_rad), rot_x(roll_rad))


def rotation_to_rpy(R: ArrayLike) -> Array:
    """Inverse of :func:`rpy_to_rotation`: (..., 3) [roll, pitch, yaw], pitch in [-pi/2, pi/2].

    At pitch = +-pi/2 (gimbal lock) roll is set to 0 and yaw carries the whole rotation.
    """
    M = checked_array(R, (3, 3), "rotation")
    pitch = np.arcsin(np.clip(-M[..., 2, 0], -1.0, 1.0))
    cos_p = np.sqrt(M[..., 2, 1] ** 2 + M[..., 2, 2] ** 2)
    lock = cos_p < 1e-9
    roll = np.where(lock, 0.0, np.arctan2(M[..., 2, 1], M[..., 2, 2]))
    yaw = np.where(lock, np.arctan2(-M[..., 0, 1], M[..., 1, 1]), np.arctan2(M[..., 1, 0], M[..., 0, 0]))
    return np.stack([roll, pitch, yaw], axis=-1)


def posture_to_transform(posture: ArrayLike) -> Array:
    """Z1 SDK posture [roll, pitch, yaw, x, y, z] (..., 6) -> ``T`` (..., 4, 4)."""
    p = checked_array(posture, (6,), "posture")
    return make_transform(rpy_to_rotation(p[..., 0], p[..., 1], p[..., 2]), p[..., 3:])


def transform_to_posture(T: ArrayLike) -> Array:
    """``T`` (..., 4, 4) -> Z1 SDK posture [roll, pitch, yaw, x, y, z] (..., 6)."""
    T_arr = checked_array(T, (4, 4), "transform")
    return np.concatenate([rotation_to_rpy(T_arr[..., :3, :3]), T_arr[..., :3, 3]], axis=-1)


def world_from_base_origins(origin_a: ArrayLike, origin_b: ArrayLike, up: ArrayLike) -> Array:
    """``T_frame_world`` of darp's world as defined by the two base origins and the up direction (all
    given in one frame): origin midway between the base origins, z = ``up``, x from ``origin_a``
    towards ``origin_b`` made orthogonal to z (docs/rig-and-poses.md). The calibration realises the
    world this way from measured quantities, and the twin draws its truth in the same definition."""
    a = checked_array(origin_a, (3,), "base origin")
    b = checked_array(origin_b, (3,), "base origin")
    z = checked_array(up, (3,), "up direction")
    # Norms over axis=-1 and elementwise dot products: np.linalg.norm of a 1-D array and ``@`` call BLAS
    # (see compose), and the twin's truth is built with this function.
    if np.linalg.norm(z, axis=-1) < 1e-12:
        raise KinematicsError("world frame: the up direction has zero length")
    z = z / np.linalg.norm(z, axis=-1)
    x = (b - a) - np.sum((b - a) * z) * z
    if np.linalg.norm(x, axis=-1) < 1e-3:
        raise KinematicsError("world frame: the two base origins are (nearly) on one vertical line")
    x = x / np.linalg.norm(x, axis=-1)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = 0.5 * (a + b)
    return T
