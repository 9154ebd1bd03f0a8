"""The Unitree Z1 arm (hardware revision V3.6): joint table, forward kinematics, Jacobian.

The table is darp's own, written from the facts in ``facts/z1-kinematics.md`` (Unitree's public
description of the arm): every joint origin has zero rotation, so at q = 0 all link frames are
parallel to the base frame (x forward, y left, z up, origin on the underside of the base) and each
joint is a pure rotation about one coordinate axis of its child link. That structure is what makes
the vectorised FK below cheap: rotating about a coordinate axis only mixes two columns of the
parent's rotation.

Frames (all orientations equal link06's):

- ``link00`` ... ``link06``: the URDF link frames; ``link0i`` is moved by ``joint i``.
- ``flange`` (darp's *wrist* frame, the SDK end-effector without gripper): 0.0618 m along link06 x.
- ``gripper`` (SDK end-effector with the gripper, on the gripper joint axis): 0.1 m along link06 x.

Hand-eye transforms are ``T_wrist_cam``; eq. 1 of the paper is
``T_world_cam = T_world_base @ fk(q + dq, "flange") @ T_wrist_cam``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError

Array = NDArray[np.float64]

N_JOINTS = 6
JOINT_NAMES: tuple[str, ...] = ("joint1", "joint2", "joint3", "joint4", "joint5", "joint6")
LINK_NAMES: tuple[str, ...] = ("link00", "link01", "link02", "link03", "link04", "link05", "link06")


@dataclass(frozen=True)
class JointSpec:
    """One revolute joint: origin of the child link in the parent link (zero rotation), axis, limits."""

    name: str
    parent: str
    child: str
    origin_xyz_m: tuple[float, float, float]
    axis: str  # "x", "y" or "z" of the child link (= of the parent at this joint's zero)
    lower_rad: float
    upper_rad: float


Z1_JOINTS: tuple[JointSpec, ...] = (
    JointSpec("joint1", "link00", "link01", (0.0, 0.0, 0.0585), "z", -2.6179939, 2.6179939),
    JointSpec("joint2", "link01", "link02", (0.0, 0.0, 0.045), "y", 0.0, 2.9670597),
    JointSpec("joint3", "link02", "link03", (-0.35, 0.0, 0.0), "y", -2.8797933, 0.0),
    JointSpec("joint4", "link03", "link04", (0.218, 0.0, 0.057), "y", -1.5184364, 1.5184364),
    JointSpec("joint5", "link04", "link05", (0.07, 0.0, 0.0), "z", -1.3439035, 1.3439035),
    JointSpec("joint6", "link05", "link06", (0.0492, 0.0, 0.0), "x", -2.7925268, 2.7925268),
)

_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
JOINT_ORIGINS_M: Array = np.array([j.origin_xyz_m for j in Z1_JOINTS])
JOINT_AXIS_INDEX: tuple[int, ...] = tuple(_AXIS_INDEX[j.axis] for j in Z1_JOINTS)
JOINT_AXES: Array = np.eye(3)[list(JOINT_AXIS_INDEX)]
JOINT_LOWER: Array = np.array([j.lower_rad for j in Z1_JOINTS])
JOINT_UPPER: Array = np.array([j.upper_rad for j in Z1_JOINTS])
# The SDK's own model: joint2 max 2.879793 (tighter than the URDF's 2.9670597) and joint3 min
# -2.885593 (the facts call it tighter, but it is 0.0058 rad *wider* than the URDF's -2.8797933;
# kept as the SDK has it: use "urdf" limits where the tighter of both matters).
SDK_JOINT_LOWER: Array = JOINT_LOWER.copy()
SDK_JOINT_LOWER[2] = -2.885593
SDK_JOINT_UPPER: Array = JOINT_UPPER.copy()
SDK_JOINT_UPPER[1] = 2.879793
VELOCITY_LIMIT_RAD_S: Array = np.full(N_JOINTS, np.pi)
EFFORT_LIMIT_NM: Array = np.array([30.0, 60.0, 30.0, 30.0, 30.0, 30.0])
for _arr in (JOINT_ORIGINS_M, JOINT_AXES, JOINT_LOWER, JOINT_UPPER, SDK_JOINT_LOWER, SDK_JOINT_UPPER,
             VELOCITY_LIMIT_RAD_S, EFFORT_LIMIT_NM):
    _arr.setflags(write=False)

# From the facts (SDK / description). "stow" has q4 = 1.5707, 0.052 rad past joint 4's limit of
# 1.5184364: kept as published; within_limits() reports it outside.
NAMED_CONFIGS: dict[str, Array] = {
    "zero": np.zeros(6),
    "forward": np.array([0.0, 1.5, -1.0, -0.54, 0.0, 0.0]),
    "startFlat": np.array([0.0, 0.0, -0.005, -0.074, 0.0, 0.0]),
    "show_mid": np.array([0.0, 0.9, -1.2, 0.25, 0.0, 0.0]),
    "stow": np.array([0.0, 1.1, -1.1, 1.5707, 0.0, 0.0]),
    "pounce": np.array([0.0, 1.57, -0.707, -0.9, 0.0, 0.0]),
}
for _arr in NAMED_CONFIGS.values():
    _arr.setflags(write=False)

# Tool frames: offset along link06 x (m); orientation is link06's.
WRIST_FRAMES: dict[str, float] = {"flange": 0.0618, "gripper": 0.1}
FRAME_OFFSETS_M: dict[str, float] = {"link06": 0.0, **WRIST_FRAMES}

LIMIT_SETS = ("urdf", "sdk")


def joint_limits(limits: str = "urdf") -> tuple[Array, Array]:
    """(lower, upper) joint limits in rad: ``"urdf"`` (the description) or ``"sdk"`` (tighter)."""
    if limits == "urdf":
        return JOINT_LOWER, JOINT_UPPER
    if limits == "sdk":
        return SDK_JOINT_LOWER, SDK_JOINT_UPPER
    raise KinematicsError(f"unknown joint limit set {limits!r}; available: {', '.join(LIMIT_SETS)}")


def frame_offset_m(frame: str) -> float:
    """Offset of a tool frame along link06 x; raises for unknown names."""
    try:
        return FRAME_OFFSETS_M[frame]
    except KeyError:
        raise KinematicsError(
            f"unknown Z1 frame {frame!r}; available: {', '.join(FRAME_OFFSETS_M)}") from None


def check_q(q: ArrayLike, batched: bool = False) -> Array:
    """Joint vector(s) as float64 (6,) or (N, 6); raises :class:`KinematicsError` on shape or NaN."""
    arr = np.asarray(q, dtype=np.float64)
    ok = arr.ndim == 2 and arr.shape[1] == N_JOINTS if batched else arr.shape == (N_JOINTS,)
    if not ok:
        want = "(N, 6)" if batched else "(6,)"
        raise KinematicsError(f"joint vector must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError("joint vector contains NaN or infinite values")
    return arr


def _chain(Q: Array) -> tuple[list[Array], list[list[Array]]]:
    """Origins (N, 3) and rotation columns [(N, 3)] * 3 of link00..link06 for joint rows Q (N, 6).

    Each joint rotates about a coordinate axis of its child, so ``R_child = R_parent @ R_axis(q)``
    only mixes two columns of ``R_parent``; no 3x3 products are formed.
    """
    n = Q.shape[0]
    cols = [np.tile(e, (n, 1)) for e in np.eye(3)]
    pos = np.zeros((n, 3))
    origins = [pos]
    rotations = [cols]
    cos, sin = np.cos(Q), np.sin(Q)
    for i, (offset, axis) in enumerate(zip(JOINT_ORIGINS_M, JOINT_AXIS_INDEX, strict=True)):
        pos = pos + sum(cols[k] * offset[k] for k in range(3) if offset[k] != 0.0)
        c, s = cos[:, i:i + 1], sin[:, i:i + 1]
        # Columns j, k with (axis, j, k) cyclic: R_axis has e_j -> c e_j + s e_k, e_k -> -s e_j + c e_k.
        j, k = (axis + 1) % 3, (axis + 2) % 3
        new = list(cols)
        new[j] = c * cols[j] + s * cols[k]
        new[k] = c * cols[k] - s * cols[j]
        cols = new
        origins.append(pos)
        rotations.append(cols)
    return origins, rotations


def _assemble(origin: Array, cols: list[Array]) -> Array:
    T = np.zeros((origin.shape[0], 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = cols
    T[:, :3, 3] = origin
    T[:, 3, 3] = 1.0
    return T


# The Z1's structure, which the closed-form FK below relies on (checked at import): axes z, y, y, y,
# z, x and every joint offset in the x-z plane of its parent.
assert tuple(j.axis for j in Z1_JOINTS) == ("z", "y", "y", "y", "z", "x")
assert np.all(JOINT_ORIGINS_M[:, 1] == 0.0) and np.all(JOINT_ORIGINS_M[[0, 1], 0] == 0.0)
assert np.all(JOINT_ORIGINS_M[[4, 5], 2] == 0.0)
_D1, _D2 = JOINT_ORIGINS_M[0, 2], JOINT_ORIGINS_M[1, 2]
(_A2, _B2), (_A3, _B3) = JOINT_ORIGINS_M[2, [0, 2]], JOINT_ORIGINS_M[3, [0, 2]]
_A4, _A5 = JOINT_ORIGINS_M[4, 0], JOINT_ORIGINS_M[5, 0]


def _cos_sin(q: Array) -> tuple[Array, Array]:
    """cos and sin of a 1-D array from one tangent of the half angle.

    numpy's float64 sin and cos are not vectorised on most CPUs; one ``tan`` plus a few arithmetic
    passes costs a third of ``cos`` + ``sin`` and agrees with them to 2.2e-16.
    """
    t = np.tan(0.5 * q)
    u = t * t
    inv = 1.0 + u
    np.divide(1.0, inv, out=inv)
    t *= inv
    t += t
    u -= 1.0
    u *= inv
    np.negative(u, out=u)
    return u, t


# Rows per block: temporaries stay in cache and below malloc's mmap threshold (large short-lived
# arrays cost page faults on every call).
_FK_BLOCK = 4096


def fk_batch(Q: ArrayLike, frame: str = "flange", out: Array | None = None) -> Array:
    """``T_base_frame`` (N, 4, 4) for joint rows Q (N, 6); vectorised over N.

    Closed form: joints 2-4 are parallel, so the tool rotation is ``Rz(q1) Ry(q2+q3+q4) Rz(q5)
    Rx(q6)`` and the wrist centre moves in the vertical plane at q1: about 60 array operations per
    block of rows instead of 6 matrix products per row. Equal to :func:`link_transforms_batch` to
    rounding. ``out``: an (N, 4, 4) float64 array to fill (saves the allocation in loops).
    """
    offset = frame_offset_m(frame)
    Qa = check_q(Q, batched=True)
    n = Qa.shape[0]
    if out is None:
        T = np.empty((n, 4, 4))
    elif isinstance(out, np.ndarray) and out.shape == (n, 4, 4) and out.dtype == np.float64:
        T = out
    else:
        raise KinematicsError(f"out must be a float64 array of shape ({n}, 4, 4)")
    for start in range(0, n, _FK_BLOCK):
        _fk_block(Qa[start:start + _FK_BLOCK], offset, T[start:start + _FK_BLOCK])
    return T


def _fk_block(Q: Array, offset: float, T: Array) -> None:
    (c1, s1), (c2, s2), (c3, s3), (c4, s4), (c5, s5), (c6, s6) = (_cos_sin(Q[:, i]) for i in range(6))
    c23, s23 = c2 * c3 - s2 * s3, s2 * c3 + c2 * s3
    ct, st = c23 * c4 - s23 * s4, s23 * c4 + c23 * s4  # theta = q2 + q3 + q4
    # Ry(phi) (a, 0, b) = (a cos + b sin, 0, -a sin + b cos) in link01's x-z plane.
    x5 = _A2 * c2 + (_A3 * c23 + _B3 * s23) + _A4 * ct + _B2 * s2
    z5 = _D2 - _A2 * s2 + (-_A3 * s23 + _B3 * c23) - _A4 * st + _B2 * c2
    reach = _A5 + offset
    # Tool rotation in link01: Ry(theta) Rz(q5) Rx(q6); then Rz(q1) into the base.
    s5c6, s5s6 = s5 * c6, s5 * s6
    r00, r01, r02 = ct * c5, st * s6 - ct * s5c6, ct * s5s6 + st * c6
    r10, r11, r12 = s5, c5 * c6, -c5 * s6
    r20 = -st * c5
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = r20, st * s5c6 + ct * s6, ct * c6 - st * s5s6
    px, py = x5 + reach * r00, reach * r10
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = c1 * r00 - s1 * r10, c1 * r01 - s1 * r11, c1 * r02 - s1 * r12
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = s1 * r00 + c1 * r10, s1 * r01 + c1 * r11, s1 * r02 + c1 * r12
    T[:, 0, 3], T[:, 1, 3] = c1 * px - s1 * py, s1 * px + c1 * py
    T[:, 2, 3] = _D1 + z5 + reach * r20
    T[:, 3, :3] = 0.0
    T[:, 3, 3] = 1.0


def fk(q: ArrayLike, frame: str = "flange") -> Array:
    """``T_base_frame`` (4, 4) of a tool frame (``flange``, ``gripper``, ``link06``) at joints q (6,).

    The same closed form as :func:`fk_batch` on Python floats: a single pose costs microseconds.
    """
    offset = frame_offset_m(frame)
    q1, q2, q3, q4, q5, q6 = (float(v) for v in check_q(q, batched=False))
    c1, s1, c2, s2, c5, s5, c6, s6 = (math.cos(q1), math.sin(q1), math.cos(q2), math.sin(q2),
                                      math.cos(q5), math.sin(q5), math.cos(q6), math.sin(q6))
    c23, s23 = math.cos(q2 + q3), math.sin(q2 + q3)
    ct, st = math.cos(q2 + q3 + q4), math.sin(q2 + q3 + q4)
    x5 = _A2 * c2 + _B2 * s2 + _A3 * c23 + _B3 * s23 + _A4 * ct
    z5 = _D2 - _A2 * s2 + _B2 * c2 - _A3 * s23 + _B3 * c23 - _A4 * st
    reach = _A5 + offset
    r00, r01, r02 = ct * c5, st * s6 - ct * s5 * c6, ct * s5 * s6 + st * c6
    r10, r11, r12 = s5, c5 * c6, -c5 * s6
    r20, r21, r22 = -st * c5, st * s5 * c6 + ct * s6, ct * c6 - st * s5 * s6
    px, py = x5 + reach * r00, reach * r10
    return np.array([
        [c1 * r00 - s1 * r10, c1 * r01 - s1 * r11, c1 * r02 - s1 * r12, c1 * px - s1 * py],
        [s1 * r00 + c1 * r10, s1 * r01 + c1 * r11, s1 * r02 + c1 * r12, s1 * px + c1 * py],
        [r20, r21, r22, _D1 + z5 + reach * r20],
        [0.0, 0.0, 0.0, 1.0],
    ])


def link_transforms_batch(Q: ArrayLike) -> Array:
    """``T_base_link`` (N, 7, 4, 4) for link00..link06."""
    Qa = check_q(Q, batched=True)
    origins, rotations = _chain(Qa)
    return np.stack([_assemble(o, c) for o, c in zip(origins, rotations, strict=True)], axis=1)


def link_transforms(q: ArrayLike) -> Array:
    """``T_base_link`` (7, 4, 4) for link00..link06 at joints q (6,)."""
    return cast(Array, link_transforms_batch(check_q(q, batched=False)[None])[0])


def joint_positions(q: ArrayLike) -> Array:
    """Positions (6, 3) of the joint origins (J1..J6) in the base frame."""
    return link_transforms(q)[1:, :3, 3]


def jacobian_batch(Q: ArrayLike, frame: str = "flange") -> Array:
    """Geometric Jacobians (N, 6, 6) in the base frame: rows vx, vy, vz, wx, wy, wz of ``frame``."""
    offset = frame_offset_m(frame)
    Qa = check_q(Q, batched=True)
    origins, rotations = _chain(Qa)
    p_end = origins[-1] + offset * rotations[-1][0]
    J = np.empty((Qa.shape[0], 6, N_JOINTS))
    for i, axis in enumerate(JOINT_AXIS_INDEX):
        z = rotations[i + 1][axis]  # joint i+1 axis in base = child link's axis column
        J[:, :3, i] = np.cross(z, p_end - origins[i + 1])
        J[:, 3:, i] = z
    return J


def jacobian(q: ArrayLike, frame: str = "flange") -> Array:
    """Geometric Jacobian (6, 6) in the base frame: linear velocity of the frame origin, then angular."""
    return cast(Array, jacobian_batch(check_q(q, batched=False)[None], frame)[0])


def manipulability(q: ArrayLike, frame: str = "flange") -> float:
    """Yoshikawa's measure sqrt(det(J J^T)); 0 at a singularity (units mix m and rad)."""
    J = jacobian(q, frame)
    return float(np.sqrt(max(np.linalg.det(J @ J.T), 0.0)))


def singular_values(q: ArrayLike, frame: str = "flange") -> Array:
    """Singular values of the Jacobian, largest first."""
    return cast(Array, np.linalg.svd(jacobian(q, frame), compute_uv=False))


def min_singular_value(q: ArrayLike, frame: str = "flange") -> float:
    """Smallest Jacobian singular value: distance-like singularity measure (0 = singular)."""
    return float(singular_values(q, frame)[-1])


def condition_number(q: ArrayLike, frame: str = "flange") -> float:
    """Jacobian condition number sigma_max / sigma_min (inf at a singularity)."""
    s = singular_values(q, frame)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def within_limits(q: ArrayLike, limits: str = "urdf", tol_rad: float = 0.0) -> bool | NDArray[np.bool_]:
    """True where every joint lies in [lower - tol, upper + tol]; q (6,) -> bool, (N, 6) -> (N,)."""
    lower, upper = joint_limits(limits)
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape[-1:] != (N_JOINTS,) or arr.ndim > 2:
        raise KinematicsError(f"joint vector must have shape (6,) or (N, 6), got {arr.shape}")
    ok = np.all((arr >= lower - tol_rad) & (arr <= upper + tol_rad), axis=-1)
    return bool(ok) if arr.ndim == 1 else ok


def random_configurations(n: int, rng: np.random.Generator | int, limits: str = "urdf") -> Array:
    """n joint vectors drawn uniformly inside the joint limits, from ``rng`` (a generator or a seed: never the
    clock, so that a run repeats)."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    lower, upper = joint_limits(limits)
    return lower + (upper - lower) * gen.random((n, N_JOINTS))
