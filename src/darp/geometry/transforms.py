"""SE(3) / SO(3) arithmetic: transforms, point mapping, rotation vectors (Rodrigues), quaternions, skew matrices.

Conventions (see docs/DEVELOPING.md):

- ``T_a_b`` is the 4x4 homogeneous pose of frame b in frame a; it maps points from b to a.
- Quaternions are ``(x, y, z, w)``, scalar last, like TUM trajectories and ``scipy``; the
  functions return the representative with ``w >= 0``.
- Rotation vectors ("axis-angle") are ``axis * angle_rad`` (3,).

Every function accepts a leading batch dimension where it says so, so that trajectories and
candidate sets are handled without Python loops. Bad shapes and NaN raise
:class:`darp.errors.KinematicsError`, the error these helpers raised when they lived in
:mod:`darp.kinematics.transforms` (which re-exports them).

:func:`compose` and :func:`matvec` multiply without BLAS, so that their results do not depend on the
OpenBLAS kernel picked at run time (docs/determinism.md); the digital twin builds the poses behind
the files it writes with them.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError

Array = NDArray[np.float64]
Float32Array = NDArray[np.float32]


def checked_array(value: ArrayLike, shape_tail: tuple[int, ...], what: str) -> Array:
    """``value`` as float64 of shape (..., *shape_tail) with finite values, else a KinematicsError naming ``what``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape[arr.ndim - len(shape_tail):] != shape_tail or arr.ndim < len(shape_tail):
        raise KinematicsError(f"{what} must have shape (..., {', '.join(map(str, shape_tail))}), "
                              f"got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError(f"{what} contains NaN or infinite values")
    return arr


def compose(*matrices: ArrayLike) -> Array:
    """Product ``M1 @ M2 @ ...`` (left to right) of matrices (..., m, n), batched and broadcast like ``@``.

    Computed by ``np.einsum`` without ``optimize``, which runs numpy's own loops: ``@`` on float64 calls
    OpenBLAS, whose last bit depends on the CPU kernel it picks at run time (FMA or not; the
    ``OPENBLAS_CORETYPE`` variable), so the same program gives other bytes on another machine. Use it
    where that matters (the twin's poses); the result equals ``@`` to rounding.
    """
    if not matrices:
        raise KinematicsError("compose needs at least one matrix")
    out = np.asarray(matrices[0], dtype=np.float64)
    for M in matrices[1:]:
        out = np.einsum("...ij,...jk->...ik", out, np.asarray(M, dtype=np.float64))
    return out


def matvec(M: ArrayLike, v: ArrayLike) -> Array:
    """``M @ v`` for matrices (..., m, n) and vectors (..., n), batched and broadcast, without BLAS (see
    :func:`compose`); ``matvec(T[:3, :3], points) + T[:3, 3]`` maps points (..., 3) by a pose."""
    product: Array = np.einsum("...ij,...j->...i", np.asarray(M, dtype=np.float64), np.asarray(v, dtype=np.float64))
    return product


def make_transform(R: ArrayLike | None = None, t: ArrayLike | None = None) -> Array:
    """Build ``T`` (..., 4, 4) from a rotation (..., 3, 3) and a translation (..., 3); either may be omitted."""
    R_arr = np.eye(3) if R is None else checked_array(R, (3, 3), "rotation")
    t_arr = np.zeros(3) if t is None else checked_array(t, (3,), "translation")
    batch = np.broadcast_shapes(R_arr.shape[:-2], t_arr.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R_arr
    T[..., :3, 3] = t_arr
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: ArrayLike) -> Array:
    """Inverse of rigid transforms (..., 4, 4), using R^T rather than a general matrix inverse."""
    T_arr = checked_array(T, (4, 4), "transform")
    R = T_arr[..., :3, :3]
    t = T_arr[..., :3, 3]
    R_inv = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T_arr)
    out[..., :3, :3] = R_inv
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R_inv, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> Array:
    """Map points (..., 3) given in frame b into frame a.

    A single ``T_a_b`` (4, 4) applies to any number of points; a batch (..., 4, 4) broadcasts
    against the points' leading dimensions (use ``T[:, None]`` for every transform x every point).
    """
    T_arr = checked_array(T_a_b, (4, 4), "transform")
    p = checked_array(points_b, (3,), "points")
    if T_arr.ndim == 2:
        return p @ T_arr[:3, :3].T + T_arr[:3, 3]
    # Batched transforms broadcast against the points' leading dimensions.
    return cast(Array, np.einsum("...ij,...j->...i", T_arr[..., :3, :3], p) + T_arr[..., :3, 3])


def transform_columns(T_a_b: ArrayLike, x: NDArray[np.floating], y: NDArray[np.floating],
                      z: NDArray[np.floating]) -> Float32Array:
    """``T_a_b @ (x, y, z, 1)`` for points given as three columns (N,), float32 out, one column at a time
    (``x R[i, 0] + y R[i, 1] + z R[i, 2] + t[i]``): several times faster than matmul for (N, 3) x (3, 3), for
    clouds of depth points (no validation: the caller checked ``T``)."""
    T = np.asarray(T_a_b)
    R = T[:3, :3].astype(np.float32)
    t = T[:3, 3].astype(np.float32)
    out = np.empty((np.asarray(z).size, 3), np.float32)
    for i in range(3):
        out[:, i] = x * R[i, 0] + y * R[i, 1] + z * R[i, 2] + t[i]
    return out


def skew(v: Array) -> Array:
    """The cross-product matrix ``[v]x`` (..., 3, 3) of vectors (..., 3): ``skew(v) @ u == cross(v, u)``."""
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def rotvec_to_rotation(rotvec: ArrayLike) -> Array:
    """Rodrigues: rotation vector (..., 3) = axis * angle_rad -> rotation matrix (..., 3, 3)."""
    v = checked_array(rotvec, (3,), "rotation vector")
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    K = skew(v)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    # sin(t)/t and (1-cos(t))/t^2, with their Taylor series for tiny angles.
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    R: Array = np.eye(3) + a * K + b * compose(K, K)
    return R


def axis_angle_to_rotation(axis: ArrayLike, angle_rad: ArrayLike) -> Array:
    """Rotation about a (not necessarily unit) ``axis`` (..., 3) by ``angle_rad`` (...)."""
    ax = checked_array(axis, (3,), "axis")
    norm = np.linalg.norm(ax, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise KinematicsError("rotation axis has zero length")
    return rotvec_to_rotation(ax / norm * np.asarray(angle_rad, dtype=np.float64)[..., None])


def rotation_to_rotvec(R: ArrayLike) -> Array:
    """Logarithm of rotations (..., 3, 3) -> rotation vectors (..., 3) with angle in [0, pi].

    Goes through the quaternion, which stays accurate near 0 and near pi (where the
    ``arccos(trace)`` formula loses half its digits).
    """
    quat = rotation_to_quaternion(R)
    xyz, w = quat[..., :3], quat[..., 3]
    s = np.linalg.norm(xyz, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-12
    scale = np.where(small, 2.0 / np.where(w == 0, 1.0, w), angle / np.where(small, 1.0, s))
    return xyz * scale[..., None]


def quaternion_to_rotation(quat_xyzw: ArrayLike) -> Array:
    """Unit quaternion(s) (..., 4) in (x, y, z, w) order -> rotation matrices (..., 3, 3)."""
    q = checked_array(quat_xyzw, (4,), "quaternion")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise KinematicsError("quaternion has zero norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_to_quaternion(R: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) in (x, y, z, w) order, w >= 0.

    Shepperd's method: pick the largest of the four squared components to divide by, so the
    result is accurate for every rotation.
    """
    M = checked_array(R, (3, 3), "rotation")
    m00, m11, m22 = M[..., 0, 0], M[..., 1, 1], M[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22, 1 + tr], -1)
    k = np.argmax(cand, axis=-1)
    quat = np.empty(M.shape[:-2] + (4,))
    d = {
        0: (cand[..., 0], M[..., 1, 0] + M[..., 0, 1], M[..., 0, 2] + M[..., 2, 0], M[..., 2, 1] - M[..., 1, 2]),
        1: (M[..., 1, 0] + M[..., 0, 1], cand[..., 1], M[..., 2, 1] + M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0]),
        2: (M[..., 0, 2] + M[..., 2, 0], M[..., 2, 1] + M[..., 1, 2], cand[..., 2], M[..., 1, 0] - M[..., 0, 1]),
        3: (M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1], cand[..., 3]),
    }
    for idx, comps in d.items():
        mask = k == idx
        if np.any(mask):
            quat[mask] = np.stack([c[mask] for c in comps], -1)
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    return np.where(quat[..., 3:4] < 0, -quat, quat)


def rotation_error_rad(R_a: ArrayLike, R_b: ArrayLike) -> Array | float:
    """Angle (rad, in [0, pi]) of the rotation taking R_a to R_b; accepts 3x3 or 4x4 (batched)."""
    A = np.asarray(R_a, dtype=np.float64)[..., :3, :3]
    B = np.asarray(R_b, dtype=np.float64)[..., :3, :3]
    ang = np.linalg.norm(rotation_to_rotvec(np.swapaxes(A, -1, -2) @ B), axis=-1)
    return float(ang) if ang.ndim == 0 else ang


def translation_error_m(T_a: ArrayLike, T_b: ArrayLike) -> Array | float:
    """Euclidean distance between the origins of two poses (batched)."""
    d = np.linalg.norm(np.asarray(T_a, float)[..., :3, 3] - np.asarray(T_b, float)[..., :3, 3], axis=-1)
    return float(d) if d.ndim == 0 else d


def pose_error(T_a: ArrayLike, T_b: ArrayLike) -> tuple[Array | float, Array | float]:
    """(translation error m, rotation error rad) between two poses (batched)."""
    return translation_error_m(T_a, T_b), rotation_error_rad(T_a, T_b)


def orthonormalize(R: ArrayLike) -> Array:
    """Nearest rotation matrix (polar decomposition via SVD) to a noisy 3x3 (batched)."""
    M = checked_array(R, (3, 3), "rotation")
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return cast(Array, (U * D[..., None, :]) @ Vt)


__all__ = [
    "axis_angle_to_rotation",
    "checked_array",
    "compose",
    "invert_transform",
    "make_transform",
    "matvec",
    "orthonormalize",
    "pose_error",
    "quaternion_to_rotation",
    "rotation_error_rad",
    "rotation_to_quaternion",
    "rotation_to_rotvec",
    "rotvec_to_rotation",
    "skew",
    "transform_columns",
    "transform_points",
    "translation_error_m",
]
