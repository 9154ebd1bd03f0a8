"""Closed-form inverse kinematics of the Z1 (all solutions, limits not applied).

- Joints 5 (z) and 6 (x) intersect at the link05 origin (the *wrist centre*), and every tool frame
  darp names lies on link06's x axis, so the wrist centre is the target minus ``(0.0492 + offset)``
  along the target's x axis.
- All joint offsets lie in the x-z plane of their parent, and joints 2-4 are parallel (y), so the
  wrist centre lies in the vertical plane at angle q1 (two choices: facing it or turned away).
- In that plane, the tool x axis is ``Ry(q2+q3+q4) Rz(q5) e_x``: its out-of-plane part gives q5
  (two choices), its in-plane part the pitch sum q2+q3+q4; joint 4's origin is then 0.07 m back
  from the wrist centre, leaving a planar two-link problem for q2, q3 (elbow up or down); q6 is
  what rotation remains.

That gives at most 8 solutions per pose, computed for many poses at once.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError
from darp.geometry.rigid import check_rigid
from darp.kinematics import z1
from darp.kinematics.transforms import rotation_to_rotvec

Array = NDArray[np.float64]

__all__ = [
    "JOINT_WEIGHTS",
    "SHOULDER_Z",
    "analytic_ik",
    "check_targets",
    "limit_violation",
    "pose_residuals",
    "wrap_angle",
]

# Geometry of the closed form (from the joint table).
SHOULDER_Z = z1.JOINT_ORIGINS_M[0, 2] + z1.JOINT_ORIGINS_M[1, 2]  # joint2 axis height (link01 frame z + J1)
_J2_Z_IN_LINK01 = z1.JOINT_ORIGINS_M[1, 2]
_UPPER = complex(z1.JOINT_ORIGINS_M[2, 0], z1.JOINT_ORIGINS_M[2, 2])  # link02 -> link03 in the x-z plane
_FORE = complex(z1.JOINT_ORIGINS_M[3, 0], z1.JOINT_ORIGINS_M[3, 2])  # link03 -> link04
_A5 = z1.JOINT_ORIGINS_M[4, 0]
_A6 = z1.JOINT_ORIGINS_M[5, 0]
_L1, _L2 = abs(_UPPER), abs(_FORE)
_BETA = float(np.angle(-np.conj(_UPPER) * _FORE))
# Distance between joint vectors when choosing among solutions: wrist joints weigh less.
JOINT_WEIGHTS = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.25])


def wrap_angle(a: Array) -> Array:
    """Angles wrapped to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def check_targets(T: ArrayLike, batched: bool) -> Array:
    arr = np.asarray(T, dtype=np.float64)
    if (arr.ndim != 3 if batched else arr.ndim != 2) or arr.shape[-2:] != (4, 4):
        raise KinematicsError(f"IK target must have shape {'(N, 4, 4)' if batched else '(4, 4)'}, "
                              f"got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError("IK target contains NaN or infinite values")
    if arr.size:
        check_rigid(arr, "IK target", error=KinematicsError)
    return arr if batched else arr[None]


def pose_residuals(Q: Array, T_targets: Array, frame: str) -> tuple[Array, Array, Array]:
    """(6-vector error [dp; rotvec] in base frame (N, 6), position error m (N,), rotation error rad (N,))."""
    T = z1.fk_batch(Q, frame)
    dp = T_targets[:, :3, 3] - T[:, :3, 3]
    dr = rotation_to_rotvec(T_targets[:, :3, :3] @ np.swapaxes(T[:, :3, :3], -1, -2))
    return np.concatenate([dp, dr], axis=1), np.linalg.norm(dp, axis=1), np.linalg.norm(dr, axis=1)


def analytic_ik(T_base_targets: ArrayLike, frame: str = "flange",
                q1_ref: ArrayLike | None = None) -> tuple[Array, NDArray[np.bool_], Array]:
    """All closed-form solutions for targets (N, 4, 4): (Q (N, 8, 6), geometric_ok (N, 8), reach_miss_m (N, 8)).

    ``geometric_ok`` marks branches that exist (elbow within reach, cos q5 != 0); joint limits are
    *not* applied here. ``reach_miss_m`` is how far the elbow triangle misses closing (0 when it
    closes). ``q1_ref`` (N,) is used for q1 when the wrist centre is on the joint-1 axis.
    """
    T = check_targets(T_base_targets, batched=True)
    offset = z1.frame_offset_m(frame)
    n = T.shape[0]
    R, p = T[:, :3, :3], T[:, :3, 3]
    w = p - (_A6 + offset) * R[:, :, 0]
    rho = np.hypot(w[:, 0], w[:, 1])
    ref = np.zeros(n) if q1_ref is None else np.broadcast_to(np.asarray(q1_ref, float), (n,))
    q1_face = np.where(rho > 1e-12, np.arctan2(w[:, 1], w[:, 0]), ref)
    Q = np.zeros((n, 2, 2, 2, 6))
    ok = np.zeros((n, 2, 2, 2), dtype=bool)
    miss = np.zeros((n, 2, 2, 2))
    for a, q1 in enumerate((q1_face, wrap_angle(q1_face + np.pi))):
        c1, s1 = np.cos(q1), np.sin(q1)
        # Rotate into link01: R1 = Rz(-q1) R.
        R1 = np.empty_like(R)
        R1[:, 0, :] = c1[:, None] * R[:, 0, :] + s1[:, None] * R[:, 1, :]
        R1[:, 1, :] = -s1[:, None] * R[:, 0, :] + c1[:, None] * R[:, 1, :]
        R1[:, 2, :] = R[:, 2, :]
        wx = c1 * w[:, 0] + s1 * w[:, 1]
        wz = w[:, 2] - z1.JOINT_ORIGINS_M[0, 2]
        x6 = R1[:, :, 0]
        s5 = np.clip(x6[:, 1], -1.0, 1.0)
        for b, q5 in enumerate((np.arcsin(s5), wrap_angle(np.pi - np.arcsin(s5)))):
            c5 = np.cos(q5)
            sign = np.where(c5 >= 0, 1.0, -1.0)
            theta = np.arctan2(-x6[:, 2] * sign, x6[:, 0] * sign)
            c5_ok = np.abs(c5) > 1e-9
            # Joint-4 origin, then the planar two-link problem from the joint-2 axis.
            P = (wx - _A5 * np.cos(theta)) + 1j * (wz + _A5 * np.sin(theta) - _J2_Z_IN_LINK01)
            k = (_L1**2 + _L2**2 - np.abs(P) ** 2) / (2.0 * _L1 * _L2)
            reach = np.abs(k) <= 1.0 + 1e-12
            miss_ab = np.where(reach, 0.0, np.maximum(np.abs(P) - (_L1 + _L2), abs(_L1 - _L2) - np.abs(P)))
            acos_k = np.arccos(np.clip(k, -1.0, 1.0))
            # Rotation left for joint 6: Rx(q6) = Rz(-q5) Ry(-theta) R1.
            ct, st = np.cos(theta), np.sin(theta)
            m1 = ct[:, None] * R1[:, 0, :] - st[:, None] * R1[:, 2, :]   # row 0 of Ry(-t) R1
            m2 = st[:, None] * R1[:, 0, :] + ct[:, None] * R1[:, 2, :]   # row 2 of Ry(-t) R1
            row1 = -np.sin(q5)[:, None] * m1 + c5[:, None] * R1[:, 1, :]  # row 1 of Rz(-q5)(...)
            q6 = np.arctan2(m2[:, 1], row1[:, 1])
            for e, sgn in enumerate((1.0, -1.0)):
                q3 = wrap_angle(_BETA - sgn * acos_k)
                q2 = wrap_angle(np.angle(_UPPER + np.exp(-1j * q3) * _FORE) - np.angle(P))
                q4 = wrap_angle(theta - q2 - q3)
                Q[:, a, b, e] = np.stack([q1, q2, q3, q4, q5, q6], axis=1)
                ok[:, a, b, e] = reach & c5_ok
                miss[:, a, b, e] = miss_ab
    return Q.reshape(n, 8, 6), ok.reshape(n, 8), miss.reshape(n, 8)


def limit_violation(Q: Array, lower: Array, upper: Array) -> Array:
    """Largest amount (rad, >= 0) by which any joint of each row lies outside [lower, upper]."""
    return cast(Array, np.max(np.maximum(lower - Q, Q - upper), axis=-1).clip(min=0.0))
