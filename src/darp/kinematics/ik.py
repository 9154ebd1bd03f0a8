"""Inverse kinematics of the Z1: closed-form solutions, damped least squares, and look-at.

The Z1's geometry has a closed-form IK (:mod:`darp.kinematics.ik_closed_form`), used first: at most
8 exact solutions per pose; those inside the joint limits are checked by FK and the one nearest
``q_init`` (else the ``forward`` configuration) is returned. A damped least-squares
(Levenberg-Marquardt) solver with joint-limit clamping runs from several seeds when the closed form
is degenerate or nearly so, or on request (``method="numeric"``). ``success`` is True only when the
FK residual is below tolerance *and* the joints are within limits.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import KinematicsError
from darp.kinematics import z1
from darp.kinematics.ik_closed_form import (
    JOINT_WEIGHTS,
    SHOULDER_Z,
    analytic_ik,
    check_targets,
    limit_violation,
    pose_residuals,
    wrap_angle,
)

Array = NDArray[np.float64]
IndexArray = NDArray[np.intp]

__all__ = [
    "IKResult",
    "LookAtResult",
    "analytic_ik",
    "numeric_ik",
    "pose_residuals",
    "solve_ik",
    "solve_ik_batch",
    "solve_look_at",
]

_LIMIT_TOL_RAD = 1e-9
_NEAR_MISS = 1e-5  # closed-form misses smaller than this trigger the numeric fallback


@dataclass(frozen=True)
class IKResult:
    """Outcome of an IK request. ``q`` is only meaningful when ``success`` is True (else best attempt)."""

    success: bool
    q: Array
    position_error_m: float
    rotation_error_rad: float
    iterations: int
    message: str
    solutions: Array = field(default_factory=lambda: np.zeros((0, 6)))  # all exact in-limit solutions


def numeric_ik(T_base_target: Array, Q_seeds: Array, *, frame: str, lower: Array, upper: Array,
               tol_pos: float, tol_rot: float, max_iters: int) -> tuple[Array, Array, Array, int]:
    """Levenberg-Marquardt on all seeds at once (S, 6) until one of them converges.

    Joints are clamped to the limits and a joint pushed against its limit is dropped from the step.
    Returns (Q, pos_err, rot_err, iterations).
    """
    S = Q_seeds.shape[0]
    Q = np.clip(Q_seeds, lower, upper)
    targets = np.broadcast_to(T_base_target, (S, 4, 4))
    err, pos, rot = pose_residuals(Q, targets, frame)
    cost = np.einsum("ij,ij->i", err, err)
    lam = np.full(S, 1e-2)
    it = 0
    for it in range(1, max_iters + 1):
        converged = (pos < tol_pos) & (rot < tol_rot)
        if np.any(converged):  # a fallback: the first exact solution(s) suffice
            it -= 1
            break
        active = ~converged
        J = z1.jacobian_batch(Q, frame)
        dq = _lm_step(J, err, lam)
        blocked = ((lower >= Q) & (dq < 0)) | ((upper <= Q) & (dq > 0))
        if np.any(blocked):
            dq = _lm_step(J * ~blocked[:, None, :], err, lam)
        Q_new = np.clip(Q + dq, lower, upper)
        err_new, pos_new, rot_new = pose_residuals(Q_new, targets, frame)
        cost_new = np.einsum("ij,ij->i", err_new, err_new)
        better = (cost_new < cost) & active
        Q = np.where(better[:, None], Q_new, Q)
        err = np.where(better[:, None], err_new, err)
        pos, rot = np.where(better, pos_new, pos), np.where(better, rot_new, rot)
        cost = np.where(better, cost_new, cost)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-6), np.minimum(lam * 5.0, 1e3))
    return Q, pos, rot, it


def _lm_step(J: Array, err: Array, lam: Array) -> Array:
    A = J @ np.swapaxes(J, 1, 2) + (lam**2)[:, None, None] * np.eye(6)
    return cast(Array, np.einsum("nji,nj->ni", J, np.linalg.solve(A, err[:, :, None])[:, :, 0]))


def _seeds(q_ref: Array, seeds: ArrayLike | None, n_random: int, rng: np.random.Generator,
           limits: str) -> Array:
    rows = [q_ref[None]]
    if seeds is not None:
        rows.append(z1.check_q(np.atleast_2d(np.asarray(seeds, dtype=np.float64)), batched=True))
    rows.append(np.array([q for name, q in z1.NAMED_CONFIGS.items() if name != "zero"]))
    rows.append(z1.random_configurations(n_random, rng, limits))
    return np.concatenate(rows)


def _select(Q: Array, q_ref: Array) -> IndexArray:
    """Order candidate rows by distance to the reference configuration (wrist joints weigh less)."""
    return np.argsort(np.sum(JOINT_WEIGHTS * (Q - q_ref) ** 2, axis=1), kind="stable")


def solve_ik(T_base_target: ArrayLike, *, frame: str = "flange", q_init: ArrayLike | None = None,
             seeds: ArrayLike | None = None, seed: int | np.random.Generator = 0,
             limits: str = "urdf", method: str = "auto", tol_pos: float = 1e-9, tol_rot: float = 1e-9,
             max_iters: int = 100, n_random_seeds: int = 8) -> IKResult:
    """Joint angles placing ``frame`` at the full 6-D pose ``T_base_target``.

    ``method``: ``"auto"`` (closed form; numeric fallback from seeds when the closed form just
    misses), ``"analytic"`` or ``"numeric"`` (LM from ``q_init``, ``seeds``, the named
    configurations and ``n_random_seeds`` random ones drawn with ``seed``). Among valid solutions
    the one nearest ``q_init`` (else the ``forward`` configuration) wins.
    """
    if method not in ("auto", "analytic", "numeric"):
        raise KinematicsError(f"unknown IK method {method!r}; available: auto, analytic, numeric")
    T = check_targets(T_base_target, batched=False)[0]
    lower, upper = z1.joint_limits(limits)
    q_ref = z1.NAMED_CONFIGS["forward"] if q_init is None else z1.check_q(q_init, batched=False)
    message = ""
    if method in ("auto", "analytic"):
        Q, ok, miss = analytic_ik(T[None], frame, q1_ref=q_ref[0])
        Q, ok, miss = Q[0], ok[0], miss[0]
        viol = limit_violation(Q, lower, upper)
        inside = ok & (viol <= _LIMIT_TOL_RAD)
        if np.any(inside):
            cand = np.clip(Q[inside], lower, upper)
            _, pos, rot = pose_residuals(cand, np.broadcast_to(T, (len(cand), 4, 4)), frame)
            exact = (pos < tol_pos) & (rot < tol_rot)
            if not np.all(exact):  # polish rows that rounding left just above tolerance
                pol, pos2, rot2, _ = numeric_ik(T, cand[~exact], frame=frame, lower=lower, upper=upper,
                                                tol_pos=tol_pos, tol_rot=tol_rot, max_iters=5)
                cand[~exact], pos[~exact], rot[~exact] = pol, pos2, rot2
                exact = (pos < tol_pos) & (rot < tol_rot)
            good = np.flatnonzero(exact)
            if len(good):
                order = good[_select(cand[good], q_ref)]
                best = order[0]
                return IKResult(True, cand[best], float(pos[best]), float(rot[best]), 0,
                                f"closed form: {len(good)} solution(s) within limits", cand[order])
        message = _analytic_failure(ok, miss, viol)
        near = np.any(ok & (viol < _NEAR_MISS)) or np.any(~ok & (miss < _NEAR_MISS))
        if method == "analytic" or not near:
            best = int(np.argmin(np.where(ok, viol, 1e3 + miss)))  # least violation, else least miss
            q_best = np.clip(Q[best], lower, upper)
            _, pos, rot = pose_residuals(q_best[None], T[None], frame)
            return IKResult(False, q_best, float(pos[0]), float(rot[0]), 0, message)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    Q0 = _seeds(q_ref, seeds, n_random_seeds, rng, limits)
    Qn, pos, rot, iters = numeric_ik(T, Q0, frame=frame, lower=lower, upper=upper, tol_pos=tol_pos,
                                     tol_rot=tol_rot, max_iters=max_iters)
    good = np.flatnonzero((pos < tol_pos) & (rot < tol_rot) & z1.within_limits(Qn, limits))
    if len(good):
        order = good[_select(Qn[good], q_ref)]
        best = order[0]
        return IKResult(True, Qn[best], float(pos[best]), float(rot[best]), iters,
                        f"damped least squares from {len(Q0)} seeds", Qn[order])
    best = int(np.argmin(pos + 0.1 * rot))
    prefix = f"{message}; " if message else ""
    return IKResult(False, Qn[best], float(pos[best]), float(rot[best]), iters,
                    f"{prefix}damped least squares did not converge from {len(Q0)} seeds "
                    f"(best residual {pos[best]:.3g} m, {rot[best]:.3g} rad)")


def _analytic_failure(ok: NDArray[np.bool_], miss: Array, viol: Array) -> str:
    if not np.any(ok):
        return f"target out of reach (elbow triangle misses by {np.min(miss) * 1000:.1f} mm)"
    i = int(np.argmin(np.where(ok, viol, np.inf)))
    return (f"all {int(ok.sum())} closed-form solutions violate joint limits "
            f"(closest by {np.degrees(viol[i]):.2f} deg)")


def solve_ik_batch(T_base_targets: ArrayLike, *, frame: str = "flange", q_init: ArrayLike | None = None,
                   limits: str = "urdf", tol_pos: float = 1e-9,
                   tol_rot: float = 1e-9) -> tuple[Array, Array, Array, Array]:
    """Closed-form IK for many targets (N, 4, 4) at once (no numeric fallback).

    Returns (Q (N, 6), success (N,), position_error_m (N,), rotation_error_rad (N,)); rows that
    fail hold NaN joints. ``q_init`` (6,) or (N, 6) chooses among the solutions.
    """
    T = check_targets(T_base_targets, batched=True)
    n = T.shape[0]
    lower, upper = z1.joint_limits(limits)
    q_ref = np.broadcast_to(z1.NAMED_CONFIGS["forward"] if q_init is None else
                            np.asarray(q_init, dtype=np.float64), (n, 6))
    Q, ok, _ = analytic_ik(T, frame, q1_ref=q_ref[:, 0])
    viol = limit_violation(Q, lower, upper)
    Q = np.clip(Q, lower, upper)
    flat_T = np.repeat(T, 8, axis=0)
    _, pos, rot = pose_residuals(Q.reshape(-1, 6), flat_T, frame)
    pos, rot = pos.reshape(n, 8), rot.reshape(n, 8)
    valid = ok & (viol <= _LIMIT_TOL_RAD) & (pos < tol_pos) & (rot < tol_rot)
    dist = np.where(valid, np.sum(JOINT_WEIGHTS * (Q - q_ref[:, None]) ** 2, axis=2), np.inf)
    best = np.argmin(dist, axis=1)
    rows = np.arange(n)
    success = valid[rows, best]
    Q_best = np.where(success[:, None], Q[rows, best], np.nan)
    return Q_best, success, np.where(success, pos[rows, best], np.nan), np.where(success, rot[rows, best], np.nan)


@dataclass(frozen=True)
class LookAtResult(IKResult):
    """IK result of :func:`solve_look_at` with the residuals in look-at terms.

    ``axis_offset_m``: distance from the optical axis to the target; ``distance_error_m``: depth of
    the target along the axis minus the asked distance; ``view_angle_error_rad``: angle between the
    achieved optical axis and the asked ``view_dir_base`` (0 when the direction was left free);
    ``T_base_cam``: the achieved camera pose. ``position_error_m`` / ``rotation_error_rad`` are
    ``hypot(axis offset, distance error)`` and the view-angle error.
    """

    axis_offset_m: float = float("nan")
    distance_error_m: float = float("nan")
    view_angle_error_rad: float = float("nan")
    T_base_cam: Array = field(default_factory=lambda: np.full((4, 4), np.nan))
    roll_rad: float = float("nan")


def _frames_about(dirs: Array, up: Array) -> Array:
    """OpenCV camera rotations (D, 3, 3) with z = dirs and image-up towards ``up`` (any up if parallel)."""
    x = np.cross(dirs, up)
    bad = np.linalg.norm(x, axis=1) < 1e-6
    if np.any(bad):
        x[bad] = np.cross(dirs[bad], np.array([1.0, 0.0, 0.0]))
        still = np.linalg.norm(x, axis=1) < 1e-6
        x[still] = np.cross(dirs[still], np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, np.cross(dirs, x), dirs], axis=-1)


def _cone(axis: Array, max_angle_rad: float, step_rad: float, n_azimuth: int) -> tuple[Array, Array]:
    """Unit directions in a cone around ``axis`` (rings every ``step_rad``) and their angles to it."""
    basis = _frames_about(axis[None], np.array([0.0, 0.0, 1.0]))[0]
    dirs, angles = [axis], [0.0]
    for polar in np.arange(step_rad, max_angle_rad + 1e-9, step_rad):
        az = np.arange(n_azimuth) * 2.0 * np.pi / n_azimuth
        local = np.stack([np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az),
                          np.full_like(az, np.cos(polar))], axis=1)
        dirs.extend(local @ basis.T)
        angles.extend([polar] * n_azimuth)
    return np.array(dirs), np.array(angles)


def solve_look_at(target_base: ArrayLike, distance_m: float, *, T_frame_cam: ArrayLike,
                  view_dir_base: ArrayLike | None = None, frame: str = "flange",
                  up_hint: ArrayLike | None = None, q_init: ArrayLike | None = None,
                  limits: str = "urdf", n_roll: int = 72, max_cone_rad: float = np.radians(80.0),
                  tol_pos: float = 1e-9, tol_rot: float = 1e-9) -> LookAtResult:
    """Joints that put the camera's optical axis (+z, OpenCV) through ``target_base`` at ``distance_m``.

    Roll about the optical axis is free. With ``view_dir_base`` (unit direction from camera to
    target) the camera position is fixed too: a 5-constraint problem. Without it the direction is
    searched in a cone around the shoulder-to-target direction, preferring small deviations from it.
    Candidate rolls (every 360/n_roll deg, then refined) are each solved in closed form, so every
    candidate meets the constraints exactly; the choice prefers image-up towards ``up_hint``
    (default base +z) unless only ``q_init`` is given, in which case the nearest joints win.
    """
    target = np.asarray(target_base, dtype=np.float64)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise KinematicsError(f"look-at target must be a finite 3-vector, got shape {target.shape}")
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise KinematicsError(f"look-at distance must be positive, got {distance_m}")
    T_fc = np.asarray(T_frame_cam, dtype=np.float64)
    if T_fc.shape != (4, 4):
        raise KinematicsError(f"T_frame_cam must be 4x4, got {T_fc.shape}")
    T_cam_frame = np.linalg.inv(T_fc)
    q_ref = z1.NAMED_CONFIGS["forward"] if q_init is None else z1.check_q(q_init, batched=False)
    use_up = up_hint is not None or q_init is None
    up = np.array([0.0, 0.0, 1.0]) if up_hint is None else np.asarray(up_hint, dtype=np.float64)
    if view_dir_base is not None:
        v = np.asarray(view_dir_base, dtype=np.float64)
        if v.shape != (3,) or not np.linalg.norm(v) > 0:
            raise KinematicsError("view_dir_base must be a non-zero 3-vector")
        dirs, dir_cost, wanted = (v / np.linalg.norm(v))[None], np.zeros(1), v / np.linalg.norm(v)
    else:
        v0 = target - np.array([0.0, 0.0, SHOULDER_Z])
        v0 = v0 / np.linalg.norm(v0) if np.linalg.norm(v0) > 1e-9 else np.array([1.0, 0.0, 0.0])
        dirs, dir_cost = _cone(v0, max_cone_rad, np.radians(10.0), 12)
        n_roll, wanted = min(n_roll, 24), None
    lower, upper = z1.joint_limits(limits)
    R0 = _frames_about(dirs, up)

    def candidates(d_idx: IndexArray, rolls: Array) -> tuple[Array, Array, Array]:
        """Best exact candidate per (direction, roll) row: (Q (M, 6), cost (M,), roll (M,))."""
        c, s = np.cos(rolls), np.sin(rolls)
        R = R0[d_idx].copy()
        R[:, :, 0] = c[:, None] * R0[d_idx][:, :, 0] + s[:, None] * R0[d_idx][:, :, 1]
        R[:, :, 1] = -s[:, None] * R0[d_idx][:, :, 0] + c[:, None] * R0[d_idx][:, :, 1]
        T_bc = np.zeros((len(d_idx), 4, 4))
        T_bc[:, :3, :3], T_bc[:, 3, 3] = R, 1.0
        T_bc[:, :3, 3] = target - distance_m * dirs[d_idx]
        T_bf = T_bc @ T_cam_frame
        Q, ok, _ = analytic_ik(T_bf, frame, q1_ref=np.full(len(d_idx), q_ref[0]))
        ok &= limit_violation(Q, lower, upper) <= _LIMIT_TOL_RAD
        Q = np.clip(Q, lower, upper)
        joint_cost = np.sum(JOINT_WEIGHTS * (Q - q_ref) ** 2, axis=2)
        roll_dev = np.abs(wrap_angle(rolls)) if use_up else np.zeros(len(rolls))
        pref = dir_cost[d_idx] + roll_dev
        cost = np.where(ok, (pref[:, None] + 0.05 * joint_cost) if (use_up or wanted is None)
                        else joint_cost, np.inf)
        k = np.argmin(cost, axis=1)
        rows = np.arange(len(d_idx))
        return Q[rows, k], cost[rows, k], rolls

    roll_grid = np.arange(n_roll) * 2.0 * np.pi / n_roll
    d_idx = np.repeat(np.arange(len(dirs)), n_roll)
    Q, cost, rolls = candidates(d_idx, np.tile(roll_grid, len(dirs)))
    if not np.any(np.isfinite(cost)):
        return _look_at_failure(target, distance_m, T_fc, frame, q_ref, dirs, wanted)
    best = int(np.argmin(cost))
    step = 2.0 * np.pi / n_roll
    fine = rolls[best] + np.linspace(-step, step, 17)
    Qf, cost_f, rolls_f = candidates(np.full(17, d_idx[best]), fine)
    if np.min(cost_f) < cost[best]:
        k = int(np.argmin(cost_f))
        Q_best, roll = Qf[k], rolls_f[k]
    else:
        Q_best, roll = Q[best], rolls[best]
    return _look_at_result(Q_best, target, distance_m, T_fc, frame, limits, wanted, float(wrap_angle(roll)),
                           tol_pos, tol_rot, n_candidates=len(d_idx) + 17)


def _look_at_residuals(T_base_cam: Array, target: Array, distance_m: float,
                       wanted: Array | None) -> tuple[float, float, float]:
    rel = target - T_base_cam[:3, 3]
    z = T_base_cam[:3, 2]
    depth = float(rel @ z)
    axis_offset = float(np.linalg.norm(rel - depth * z))
    angle = 0.0 if wanted is None else float(np.arctan2(np.linalg.norm(np.cross(z, wanted)), z @ wanted))
    return axis_offset, depth - distance_m, angle


def _look_at_result(q: Array, target: Array, distance_m: float, T_fc: Array, frame: str, limits: str,
                    wanted: Array | None, roll: float, tol_pos: float, tol_rot: float,
                    n_candidates: int) -> LookAtResult:
    T_bc = z1.fk(q, frame) @ T_fc
    axis_offset, dist_err, angle = _look_at_residuals(T_bc, target, distance_m, wanted)
    ok = (axis_offset < tol_pos and abs(dist_err) < tol_pos and angle < tol_rot
          and bool(z1.within_limits(q, limits)))
    msg = (f"closed form over {n_candidates} (direction, roll) candidates" if ok else
           f"residual above tolerance: axis offset {axis_offset:.3g} m, distance error {dist_err:.3g} m")
    return LookAtResult(ok, q, float(np.hypot(axis_offset, dist_err)), angle, 0, msg,
                        axis_offset_m=axis_offset, distance_error_m=dist_err, view_angle_error_rad=angle,
                        T_base_cam=T_bc, roll_rad=roll)


def _look_at_failure(target: Array, distance_m: float, T_fc: Array, frame: str, q_ref: Array,
                     dirs: Array, wanted: Array | None) -> LookAtResult:
    T_bc = z1.fk(q_ref, frame) @ T_fc
    axis_offset, dist_err, angle = _look_at_residuals(T_bc, target, distance_m, wanted)
    what = "from the given direction" if wanted is not None else f"from any of {len(dirs)} directions"
    return LookAtResult(False, q_ref.copy(), float(np.hypot(axis_offset, dist_err)), angle, 0,
                        f"no joint solution within limits views the target at {distance_m:.3f} m {what}",
                        axis_offset_m=axis_offset, distance_error_m=dist_err, view_angle_error_rad=angle,
                        T_base_cam=T_bc)
