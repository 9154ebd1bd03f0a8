"""Camera pose recovery from the joint log: the paper's eq. 1, evaluated at every camera frame.

    T_world_cam(t) = T_world_base @ T_base_wrist(q(t) + dq) @ T_wrist_cam

``q(t)`` is the joint log linearly interpolated at the frame's timestamp (host clock). A frame before
the first or after the last log sample, or one that falls between two samples further apart than
``max_gap_s``, gets no pose: the log is never extrapolated and never bridged across a dropout.

Pure math: arrays in, arrays out. Reading surveys and writing trajectories is
:mod:`darp.reconstruction.poses`' job.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import numpy as np

from darp.errors import KinematicsError
from darp.geometry.rigid import check_rigid
from darp.kinematics import z1

DEFAULT_MAX_GAP_S = 0.2
"""Longest log gap (s) interpolated across. The paper's logger runs at ~33 Hz (30 ms period), so
0.2 s is more than six missed samples: an arm moving at 0.5 rad/s would travel 0.1 rad unobserved."""

POSED, BEFORE_LOG, AFTER_LOG, IN_GAP = 0, 1, 2, 3
STATUS_NAMES: tuple[str, ...] = ("posed", "before_log", "after_log", "in_gap")

FkBatch = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class JointInterpolation:
    """Joint states of one arm interpolated at query times.

    ``q_rad`` and ``qd_rad_s`` are NaN where ``status != POSED``. ``qd_rad_s`` is the slope of the
    log segment that brackets the query (the finite-difference velocity of the two samples).
    """

    t_s: np.ndarray  # (N,) query times, host clock
    q_rad: np.ndarray  # (N, 6)
    qd_rad_s: np.ndarray  # (N, 6)
    status: np.ndarray  # (N,) int8, one of POSED, BEFORE_LOG, AFTER_LOG, IN_GAP

    @property
    def posed(self) -> np.ndarray:
        """Boolean mask of the queries that have a joint state."""
        return cast(np.ndarray, self.status == POSED)

    def counts(self) -> dict[str, int]:
        """How many queries ended in each status, by name."""
        return {name: int(np.count_nonzero(self.status == code)) for code, name in enumerate(STATUS_NAMES)}


@dataclass(frozen=True)
class CameraPoses:
    """World poses of one camera at its frame times (eq. 1), with the joint states behind them.

    ``T_world_cam`` is NaN for frames whose ``status`` is not ``POSED``.
    ``q_rad`` is the interpolated *logged* configuration (before the joint-zero correction).
    """

    t_s: np.ndarray  # (N,) frame times on the host clock (camera time minus clock offset)
    T_world_cam: np.ndarray  # (N, 4, 4)
    status: np.ndarray  # (N,) int8
    q_rad: np.ndarray  # (N, 6)
    joint_velocity_rad_s: np.ndarray  # (N, 6)

    @property
    def posed(self) -> np.ndarray:
        """Boolean mask of the frames that have a pose."""
        return cast(np.ndarray, self.status == POSED)

    def counts(self) -> dict[str, int]:
        """How many frames ended in each status, by name, plus ``frames`` (the total)."""
        counts = {name: int(np.count_nonzero(self.status == code)) for code, name in enumerate(STATUS_NAMES)}
        return {"frames": int(self.status.size), **counts}

    @property
    def joint_speed_rad_s(self) -> np.ndarray:
        """(N,) largest absolute joint velocity per frame: a simple 'is the arm settled' measure."""
        speed = np.full(self.status.shape, np.nan)
        ok = self.posed
        speed[ok] = np.max(np.abs(self.joint_velocity_rad_s[ok]), axis=1)
        return speed


def _check_log(log_t_s: np.ndarray, log_q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(log_t_s, dtype=np.float64)
    q = np.asarray(log_q_rad, dtype=np.float64)
    if t.ndim != 1 or q.ndim != 2 or q.shape != (t.size, q.shape[1]):
        raise KinematicsError(f"joint log shapes do not match: times {t.shape}, joints {q.shape}")
    if t.size == 0:
        raise KinematicsError("joint log is empty: no camera pose can be recovered")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise KinematicsError("joint log holds non-finite times or joint values")
    if np.any(np.diff(t) < 0):
        raise KinematicsError("joint log times go backwards")
    return t, q


def interpolate_joints(
    log_t_s: np.ndarray,
    log_q_rad: np.ndarray,
    query_t_s: np.ndarray,
    *,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
) -> JointInterpolation:
    """Linearly interpolate a joint log (times non-decreasing) at ``query_t_s``, never extrapolating.

    A query exactly on the first or last sample is inside the log. A query strictly between two
    samples more than ``max_gap_s`` apart is ``IN_GAP``; a query landing exactly on a sample is always
    posed (that sample was measured).
    """
    if not max_gap_s > 0:
        raise KinematicsError(f"max_gap_s must be positive, got {max_gap_s}")
    t_log, q_log = _check_log(log_t_s, log_q_rad)
    t = np.asarray(query_t_s, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(t)):
        raise KinematicsError("query times must be finite")
    n, dof = t.size, q_log.shape[1]
    status = np.full(n, POSED, dtype=np.int8)
    status[t < t_log[0]] = BEFORE_LOG
    status[t > t_log[-1]] = AFTER_LOG
    q = np.full((n, dof), np.nan)
    qd = np.full((n, dof), np.nan)
    inside = status == POSED
    if t_log.size == 1:  # a single sample: only queries exactly on it are inside
        q[inside] = q_log[0]
        qd[inside] = 0.0
        return JointInterpolation(t, q, qd, status)

    ti = t[inside]
    # lower bracket: last sample with t_log <= t (so a hit on a sample uses the segment after it)
    lo = np.clip(np.searchsorted(t_log, ti, side="right") - 1, 0, t_log.size - 2)
    hi = lo + 1
    t0, t1 = t_log[lo], t_log[hi]
    dt = t1 - t0
    on_sample = (ti == t0) | (ti == t1)
    gap = (dt > max_gap_s) & ~on_sample
    safe_dt = np.where(dt > 0, dt, 1.0)
    alpha = np.where(dt > 0, (ti - t0) / safe_dt, 1.0)[:, None]
    q0, q1 = q_log[lo], q_log[hi]
    q_in = q0 + alpha * (q1 - q0)
    # exact sample hits return the sample itself (no rounding from the blend)
    q_in = np.where((ti == t1)[:, None], q1, q_in)
    q_in = np.where((ti == t0)[:, None], q0, q_in)
    qd_in = np.where((dt > 0)[:, None], (q1 - q0) / safe_dt[:, None], 0.0)

    idx = np.flatnonzero(inside)
    q[idx] = q_in
    qd[idx] = qd_in
    status[idx[gap]] = IN_GAP
    q[idx[gap]] = np.nan
    qd[idx[gap]] = np.nan
    return JointInterpolation(t, q, qd, status)


def compose_world_cam(T_world_base: np.ndarray, T_base_wrist: np.ndarray, T_wrist_cam: np.ndarray) -> np.ndarray:
    """Eq. 1's product ``T_world_base @ T_base_wrist @ T_wrist_cam`` for one or many wrist poses."""
    return cast(np.ndarray, np.matmul(np.matmul(T_world_base, T_base_wrist), T_wrist_cam))


def _default_fk_batch(wrist_frame: str) -> FkBatch:
    return lambda Q: z1.fk_batch(Q, frame=wrist_frame)


def camera_poses(
    log_t_s: np.ndarray,
    log_q_rad: np.ndarray,
    frame_t_s: np.ndarray,
    *,
    T_world_base: np.ndarray,
    T_wrist_cam: np.ndarray,
    joint_offsets_rad: np.ndarray | None = None,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    clock_offset_s: float = 0.0,
    wrist_frame: str = "flange",
    fk_batch: FkBatch | None = None,
) -> CameraPoses:
    """Eq. 1 at every camera frame of one arm.

    ``frame_t_s`` are camera timestamps in seconds; ``clock_offset_s`` is how far the camera clock is
    ahead of the host clock (camera time = host time + offset), so the log is sampled at
    ``frame_t_s - clock_offset_s``. ``joint_offsets_rad`` (dq) is *added* to the logged joints before
    forward kinematics. ``fk_batch`` maps (N, 6) joints to (N, 4, 4) ``T_base_wrist``; by default the
    Z1 model's ``fk_batch`` for ``wrist_frame``.
    """
    T_wb = check_rigid(T_world_base, "T_world_base", error=KinematicsError)
    T_wc = check_rigid(T_wrist_cam, "T_wrist_cam", error=KinematicsError)
    if not np.isfinite(clock_offset_s):
        raise KinematicsError(f"clock offset must be finite, got {clock_offset_s}")
    host_t = np.asarray(frame_t_s, dtype=np.float64).reshape(-1) - float(clock_offset_s)
    interp = interpolate_joints(log_t_s, log_q_rad, host_t, max_gap_s=max_gap_s)
    dof = interp.q_rad.shape[1]
    dq = np.zeros(dof) if joint_offsets_rad is None else np.asarray(joint_offsets_rad, dtype=np.float64)
    if dq.shape != (dof,) or not np.all(np.isfinite(dq)):
        raise KinematicsError(f"joint offsets must be {dof} finite values, got shape {dq.shape}")

    poses = np.full((host_t.size, 4, 4), np.nan)
    ok = interp.posed
    if np.any(ok):
        fk = fk_batch if fk_batch is not None else _default_fk_batch(wrist_frame)
        T_base_wrist = np.asarray(fk(interp.q_rad[ok] + dq), dtype=np.float64)
        poses[ok] = compose_world_cam(T_wb, T_base_wrist, T_wc)
    return CameraPoses(
        t_s=host_t,
        T_world_cam=poses,
        status=interp.status,
        q_rad=interp.q_rad,
        joint_velocity_rad_s=interp.qd_rad_s,
    )


__all__ = [
    "AFTER_LOG",
    "BEFORE_LOG",
    "DEFAULT_MAX_GAP_S",
    "IN_GAP",
    "POSED",
    "STATUS_NAMES",
    "CameraPoses",
    "JointInterpolation",
    "camera_poses",
    "compose_world_cam",
    "interpolate_joints",
]
