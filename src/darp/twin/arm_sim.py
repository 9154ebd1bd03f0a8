"""A simulated Z1 arm: smooth joint moves with speed and acceleration limits, encoder errors, ArmBackend.

Motion: a move is one synchronised quintic per joint from the current state (position, velocity and
acceleration, so a new command during a move blends without a jump) to rest at the target. All joints
share the move's duration, which is the shortest that keeps every joint within ``max_speed_rad_s``
and ``max_accel_rad_s2`` (the Z1 SDK's ``MoveJ(q, maxSpeed)`` with ``setWait(False)`` behaves the
same way: non-blocking, every joint arriving together). Because a move is an analytic function of
time, the *true* joint angle at any instant is exact; nothing is integrated.

Angles: commands and reports are in the SDK's (encoder) frame. The arm's joint-zero offsets ``dq``
make the true angle ``q_true = q_sdk + dq`` (eq. 1's sign convention), so a commanded target ``q``
puts the links at ``q + dq`` and the reported angle is ``q_true - dq + encoder noise``.

Link-side deflection (:class:`darp.twin.arm_errors.LinkDeflection`, optional): sag under gravity,
backlash and repeatability move the links away from the motor-side path without the encoders seeing
it. :meth:`SimArm.true_state` (rendering, truth) includes it; :meth:`SimArm.read_state` does not.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from darp.backend import ArmBackend, JointState
from darp.errors import KinematicsError, TwinError
from darp.kinematics import z1
from darp.kinematics.transforms import matvec
from darp.twin.arm_errors import LinkDeflection
from darp.twin.clock import NS_PER_S, SimClock

_SAMPLES = np.linspace(0.0, 1.0, 65)
HISTORY = 4  # moves kept for state queries at past instants


@dataclass(frozen=True)
class QuinticMove:
    """Per-joint quintic polynomials over ``[t0_ns, t0_ns + duration]`` (true joint angles)."""

    t0_ns: int
    duration_s: float
    coeffs: np.ndarray  # (6 joints, 6 coefficients), lowest order first, in seconds since t0
    q_end: np.ndarray  # (6,)
    link_offset: np.ndarray | None = None  # (6,) link-side offset during this move (backlash, repeatability)

    @classmethod
    def plan(cls, t0_ns: int, p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray,
             max_speed: float, max_accel: float) -> QuinticMove:
        """Shortest synchronised quintic from (p0, v0, a0) to rest at p1 within the limits."""
        distance = float(np.max(np.abs(p1 - p0)))
        moving = float(np.max(np.abs(v0))) + float(np.max(np.abs(a0)))
        if distance < 1e-12 and moving < 1e-12:
            return cls(t0_ns, 0.0, np.zeros((6, 6)), p1.copy())
        # Rest-to-rest quintic: peak speed 1.875 D/T, peak acceleration 5.7735 D/T^2.
        T = max(1.875 * distance / max_speed, np.sqrt(5.7735 * distance / max_accel), 0.02)
        if moving > 0:
            T = max(T, 2.0 * float(np.max(np.abs(v0))) / max_accel)
        for _ in range(60):
            move = cls(t0_ns, T, _quintic_coeffs(p0, v0, a0, p1, T), p1.copy())
            s = _SAMPLES * T
            if (np.max(np.abs(move._derivative(s, 1))) <= max_speed * 1.0001
                    and np.max(np.abs(move._derivative(s, 2))) <= max_accel * 1.0001):
                return move
            T *= 1.08
        raise TwinError(f"cannot plan a move within {max_speed} rad/s and {max_accel} rad/s^2")

    @property
    def end_ns(self) -> int:
        return self.t0_ns + round(self.duration_s * NS_PER_S)

    def _derivative(self, s: np.ndarray, order: int) -> np.ndarray:
        """(len(s), 6) derivative ``order`` of the polynomials at seconds-since-start ``s``.

        ``matvec`` rather than ``powers @ c.T``: the joint angles end up in the twin's files, which must
        not depend on the BLAS kernel (see :func:`darp.kinematics.transforms.compose`).
        """
        c = self.coeffs
        if order == 0:
            powers = np.stack([s ** k for k in range(6)], axis=1)
        elif order == 1:
            powers = np.stack([k * s ** (k - 1) if k else np.zeros_like(s) for k in range(6)], axis=1)
        else:
            powers = np.stack([k * (k - 1) * s ** (k - 2) if k > 1 else np.zeros_like(s) for k in range(6)], axis=1)
        return matvec(c, powers)  # (N, 6): row n is c @ powers[n]

    def state(self, t_ns: np.ndarray | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd), each (N, 6) (or (6,) for a scalar time), clamped to the move's span."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        if self.duration_s == 0.0:
            q = np.tile(self.q_end, (t.size, 1))
            zeros = np.zeros_like(q)
            out = (q, zeros, zeros.copy())
        else:
            s = np.clip((t - self.t0_ns) / NS_PER_S, 0.0, self.duration_s)
            after = t >= self.end_ns
            q = self._derivative(s, 0)
            qd = self._derivative(s, 1)
            qdd = self._derivative(s, 2)
            q[after] = self.q_end
            qd[after] = 0.0
            qdd[after] = 0.0
            out = (q, qd, qdd)
        if np.ndim(t_ns) == 0:
            return out[0][0], out[1][0], out[2][0]
        return out


def _quintic_coeffs(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray, T: float) -> np.ndarray:
    """Coefficients c0..c5 per joint: boundary (p0, v0, a0) at 0 and (p1, 0, 0) at T."""
    d = p1 - p0 - v0 * T - 0.5 * a0 * T ** 2
    dv = -v0 - a0 * T
    da = -a0
    c3 = (10 * d - 4 * dv * T + 0.5 * da * T ** 2) / T ** 3
    c4 = (-15 * d + 7 * dv * T - da * T ** 2) / T ** 4
    c5 = (6 * d - 3 * dv * T + 0.5 * da * T ** 2) / T ** 5
    return np.stack([p0, v0, 0.5 * a0, c3, c4, c5], axis=1)


class SimArm(ArmBackend):
    """One simulated Z1 on a :class:`SimClock`; implements :class:`ArmBackend`."""

    def __init__(
        self,
        arm_id: str,
        clock: SimClock,
        q_initial_rad: np.ndarray,
        *,
        joint_offsets_rad: np.ndarray | None = None,
        encoder_noise_std_rad: float = 0.0,
        rng: np.random.Generator | None = None,
        max_speed_rad_s: float = 0.6,
        max_accel_rad_s2: float = 2.0,
        settle_s: float = 0.1,
        deflection: LinkDeflection | None = None,
    ) -> None:
        self.arm_id = arm_id
        self.clock = clock
        self.joint_offsets_rad = np.zeros(6) if joint_offsets_rad is None else np.asarray(joint_offsets_rad, float)
        self.encoder_noise_std_rad = float(encoder_noise_std_rad)
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.max_speed_rad_s = float(max_speed_rad_s)
        self.max_accel_rad_s2 = float(max_accel_rad_s2)
        self.settle_ns = round(settle_s * NS_PER_S)
        self.deflection = deflection if deflection is not None and deflection.active else None
        q0 = self._check_target(q_initial_rad) + self.joint_offsets_rad
        self._moves: list[QuinticMove] = [QuinticMove(clock.elapsed_ns, 0.0, np.zeros((6, 6)), q0)]
        self.moves_commanded = 0

    @property
    def _move(self) -> QuinticMove:
        return self._moves[-1]

    def _start(self, move: QuinticMove) -> None:
        if self.deflection is not None:
            move = replace(move, link_offset=self.deflection.move_offset(self._move.q_end, move.q_end))
        # A few past moves are kept so that states shortly before the latest command (IMU central
        # differences, a frame rendered just before a new command) come from the move then running.
        self._moves = [m for m in self._moves if m.t0_ns < move.t0_ns][-(HISTORY - 1):] + [move]

    # -- truth ------------------------------------------------------------------------------------
    def true_state(self, t_ns: int | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True link-side (q, qd, qdd) at simulation time ``t_ns`` (default now); vectorised over times.

        The motor-side path (:meth:`path_state`) plus the link deflection, if any (its rates are not added).
        """
        q, qd, qdd = self.path_state(t_ns)
        if self.deflection is None:
            return q, qd, qdd
        t = self.clock.elapsed_ns if t_ns is None else t_ns
        times = np.atleast_1d(np.asarray(t, dtype=np.int64))
        starts = np.array([m.t0_ns for m in self._moves])
        which = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self._moves) - 1)
        offsets = np.array([m.link_offset if m.link_offset is not None else np.zeros(6) for m in self._moves])
        Q = np.atleast_2d(q)
        link = Q + offsets[which] + self.deflection.sag(Q)
        return (link[0] if np.ndim(t) == 0 else link), qd, qdd

    def path_state(self, t_ns: int | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Motor-side (q, qd, qdd) of the commanded moves (joint-zero offsets included, no deflection).

        The last few moves are kept; earlier times are answered with the oldest kept move's start.
        """
        t = self.clock.elapsed_ns if t_ns is None else t_ns
        if len(self._moves) == 1:
            return self._moves[0].state(t)
        times = np.atleast_1d(np.asarray(t, dtype=np.int64))
        starts = np.array([m.t0_ns for m in self._moves])
        which = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(self._moves) - 1)
        q, qd, qdd = (np.empty((times.size, 6)) for _ in range(3))
        for k in np.unique(which):
            sel = which == k
            q[sel], qd[sel], qdd[sel] = self._moves[k].state(times[sel])
        if np.ndim(t) == 0:
            return q[0], qd[0], qdd[0]
        return q, qd, qdd

    def true_q(self, t_ns: int | None = None) -> np.ndarray:
        """True joint angles (6,) at ``t_ns`` (default now)."""
        return self.true_state(t_ns)[0]

    @property
    def move_end_ns(self) -> int:
        return self._move.end_ns

    # -- ArmBackend -------------------------------------------------------------------------------
    def read_state(self) -> JointState:
        """Reported state: true angles minus the joint-zero offsets plus encoder noise, at ``clock.now()``."""
        q, qd, _ = self.path_state()
        q_reported = q - self.joint_offsets_rad
        if self.encoder_noise_std_rad > 0:
            q_reported = q_reported + self._rng.normal(0.0, self.encoder_noise_std_rad, 6)
        return JointState(time_s=self.clock.now(), q_rad=q_reported, qd_rad_s=qd.copy())

    def move_to(self, q_target_rad: np.ndarray, max_speed_rad_s: float | None = None) -> None:
        """Start a move to ``q_target_rad`` (SDK angles); returns at once."""
        target = self._check_target(q_target_rad) + self.joint_offsets_rad
        speed = self.max_speed_rad_s if max_speed_rad_s is None else float(max_speed_rad_s)
        if not 0 < speed <= float(np.max(z1.VELOCITY_LIMIT_RAD_S)):
            raise KinematicsError(f"{self.arm_id}: max speed must be in (0, pi] rad/s, got {speed}")
        now = self.clock.elapsed_ns
        q, qd, qdd = self.path_state(now)
        self._start(QuinticMove.plan(now, q, qd, qdd, target, speed, self.max_accel_rad_s2))
        self.moves_commanded += 1

    def is_moving(self) -> bool:
        return self.clock.elapsed_ns < self._move.end_ns + (self.settle_ns if self._move.duration_s > 0 else 0)

    def stop(self) -> None:
        """Decelerate to rest at the acceleration limit (holds the reached position)."""
        now = self.clock.elapsed_ns
        q, qd, qdd = self.path_state(now)
        if not np.any(qd) and not np.any(qdd):
            self._start(QuinticMove(now, 0.0, np.zeros((6, 6)), q.copy()))
            return
        t_stop = max(float(np.max(np.abs(qd))) / self.max_accel_rad_s2, 0.02)
        q_rest = q + 0.5 * qd * t_stop
        self._start(QuinticMove.plan(now, q, qd, qdd, q_rest, float(z1.VELOCITY_LIMIT_RAD_S[0]),
                                     self.max_accel_rad_s2))

    def _check_target(self, q: np.ndarray) -> np.ndarray:
        arr = np.asarray(q, dtype=np.float64)
        if arr.shape != (6,) or not np.all(np.isfinite(arr)):
            raise KinematicsError(f"{self.arm_id}: joint target must be 6 finite angles, got {np.shape(q)}")
        lower, upper = z1.joint_limits("urdf")
        bad = np.nonzero((arr < lower - 1e-9) | (arr > upper + 1e-9))[0]
        if bad.size:
            j = int(bad[0])
            raise KinematicsError(f"{self.arm_id}: joint{j + 1} target {arr[j]:.4f} rad is outside "
                                  f"[{lower[j]:.4f}, {upper[j]:.4f}]")
        return arr.copy()


__all__ = ["QuinticMove", "SimArm"]
