"""Smooth joint-space trajectories for the Z1 control loop: synchronised quintics within speed and
acceleration limits, blended from the current commanded state so that a new target never jumps.

A :class:`JointPlan` is a short list of quintic :class:`Segment` s; the control thread samples it at
500 Hz and streams the samples to the arm. Position and velocity are continuous across a re-plan because
every plan starts from the position and velocity the previous plan had at that instant (the acceleration
restarts from zero: a bounded step, invisible to a controller that tracks position and velocity).

Rest-to-rest moves use the closed-form quintic whose peak speed is ``1.875 D / T`` and peak acceleration
``5.7735 D / T^2`` (D the largest joint travel), so the shortest duration meeting both limits is exact
and all joints arrive together. A move that starts in motion is found by lengthening T until dense
samples respect the limits; if such a blend would leave the joint limits, the plan first brakes to rest
and then moves. Positions of a rest-to-rest quintic stay between its endpoints, so a plan between two
points inside the limits never leaves them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_DURATION_S = 0.02
_CHECK_SAMPLES = np.linspace(0.0, 1.0, 257)
_PEAK_SPEED = 1.875  # max of d/ds of 10 s^3 - 15 s^4 + 6 s^5
_PEAK_ACCEL = 5.773502691896258  # max of its second derivative (10 / sqrt(3))
_RELATIVE_SLACK = 1e-4


@dataclass(frozen=True, eq=False)
class Segment:
    """Per-joint quintic polynomials on ``[t0_s, t0_s + duration_s]`` (seconds, monotonic clock)."""

    t0_s: float
    duration_s: float
    coeffs: np.ndarray  # (6 joints, 6 coefficients), lowest order first, in seconds since t0_s
    q_end: np.ndarray  # (6,) where the segment comes to rest

    @property
    def end_s(self) -> float:
        return self.t0_s + self.duration_s

    def sample(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at ``t_s``; before the start the start state, after the end rest at ``q_end``."""
        if self.duration_s <= 0.0 or t_s >= self.end_s:
            zeros = np.zeros(6)
            return self.q_end.copy(), zeros, zeros.copy()
        s = max(t_s - self.t0_s, 0.0)
        c = self.coeffs
        powers = s ** np.arange(6)
        q = c @ powers
        qd = c[:, 1:] @ (np.arange(1, 6) * powers[:5])
        qdd = c[:, 2:] @ (np.arange(2, 6) * np.arange(1, 5) * powers[:4])
        return q, qd, qdd

    def dense(self, samples: np.ndarray = _CHECK_SAMPLES) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at ``samples`` (fractions of the duration), each (len(samples), 6)."""
        s = samples * self.duration_s
        c = self.coeffs
        P = s[:, None] ** np.arange(6)[None, :]
        q = P @ c.T
        qd = (P[:, :5] * np.arange(1, 6)) @ c[:, 1:].T
        qdd = (P[:, :4] * (np.arange(2, 6) * np.arange(1, 5))) @ c[:, 2:].T
        return q, qd, qdd


def _coeffs(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray, T: float) -> np.ndarray:
    """Quintic coefficients with (p0, v0, a0) at 0 and (p1, 0, 0) at T."""
    d = p1 - p0 - v0 * T - 0.5 * a0 * T**2
    dv = -v0 - a0 * T
    c3 = (10 * d - 4 * dv * T + 0.5 * a0 * T**2) / T**3
    c4 = (-15 * d + 7 * dv * T - a0 * T**2) / T**4
    c5 = (6 * d - 3 * dv * T + 0.5 * a0 * T**2) / T**5
    return np.stack([p0, v0, 0.5 * a0, c3, c4, c5], axis=1)


def hold(t0_s: float, q: np.ndarray) -> Segment:
    """A segment that stays at ``q``."""
    return Segment(t0_s, 0.0, np.zeros((6, 6)), np.asarray(q, dtype=np.float64).copy())


def plan_segment(t0_s: float, q0: np.ndarray, v0: np.ndarray, a0: np.ndarray, q1: np.ndarray,
                 max_speed: float, max_accel: float, lower: np.ndarray, upper: np.ndarray) -> Segment | None:
    """Shortest synchronised quintic from (q0, v0, a0) to rest at ``q1`` within the limits.

    None when no duration keeps the positions inside ``[lower, upper]`` (never further out than q0).
    """
    distance = float(np.max(np.abs(q1 - q0)))
    speed0, accel0 = float(np.max(np.abs(v0))), float(np.max(np.abs(a0)))
    if distance < 1e-12 and speed0 < 1e-12 and accel0 < 1e-12:
        return hold(t0_s, q1)
    T = max(_PEAK_SPEED * distance / max_speed, np.sqrt(_PEAK_ACCEL * distance / max_accel), MIN_DURATION_S)
    if speed0 == 0.0 and accel0 == 0.0:  # rest to rest: the closed form is exact and stays between q0, q1
        return Segment(t0_s, T, _coeffs(q0, v0, a0, q1, T), np.asarray(q1, dtype=np.float64).copy())
    T = max(T, 2.0 * speed0 / max_accel)
    lo = np.minimum(lower, q0) - 1e-9
    hi = np.maximum(upper, q0) + 1e-9
    for _ in range(60):  # up to about 19 times the first guess
        seg = Segment(t0_s, T, _coeffs(q0, v0, a0, q1, T), np.asarray(q1, dtype=np.float64).copy())
        q, qd, qdd = seg.dense()
        if (np.max(np.abs(qd)) <= max_speed * (1 + _RELATIVE_SLACK)
                and np.max(np.abs(qdd)) <= max_accel * (1 + _RELATIVE_SLACK)):
            return seg if np.all((q >= lo) & (q <= hi)) else None
        T *= 1.05
    return None  # e.g. reversing at speed: one quintic overshoots too fast whatever its duration


@dataclass(frozen=True, eq=False)
class JointPlan:
    """Consecutive segments; sampling past the last one holds its end point."""

    segments: tuple[Segment, ...]
    max_speed_rad_s: float = 0.0
    max_accel_rad_s2: float = 0.0
    notes: tuple[str, ...] = field(default=())

    @property
    def end_s(self) -> float:
        return self.segments[-1].end_s

    @property
    def q_end(self) -> np.ndarray:
        return self.segments[-1].q_end

    def sample(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        for seg in self.segments:
            if t_s < seg.end_s:
                return seg.sample(t_s)
        return self.segments[-1].sample(t_s)


def plan_hold(t0_s: float, q: np.ndarray) -> JointPlan:
    return JointPlan((hold(t0_s, q),))


def plan_stop(t0_s: float, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, max_speed: float, max_accel: float,
              lower: np.ndarray, upper: np.ndarray) -> JointPlan:
    """Brake from (q, qd) to rest as soon as the acceleration limit allows.

    The braking quintic to ``q + qd T / 2`` has speed ``qd (1 - 3s^2 + 2s^3)`` (monotone, no reversal)
    and peak deceleration ``1.5 |qd| / T``, so ``T = 1.5 max|qd| / max_accel`` is exact. The current
    acceleration is not carried over (it steps to zero: position and speed stay continuous, which is
    what the controller tracks). If the stopping point would lie past a joint limit, the arm brakes
    harder instead: the limits come first. ``qdd`` is accepted for symmetry with :func:`plan_move`.
    """
    speed = float(np.max(np.abs(qd)))
    if speed < 1e-12:
        return plan_hold(t0_s, q)
    T = max(1.5 * speed / max_accel, MIN_DURATION_S)
    room = np.where(qd > 0, upper - q, np.where(qd < 0, q - lower, np.inf))
    moving = np.abs(qd) > 1e-12
    t_room = np.full(6, np.inf)
    t_room[moving] = 2.0 * np.maximum(room[moving], 0.0) / np.abs(qd[moving])
    T = max(min(T, float(np.min(t_room))), MIN_DURATION_S)
    q_rest = q + 0.5 * qd * T
    seg = Segment(t0_s, T, _coeffs(q, qd, np.zeros(6), q_rest, T), q_rest)
    return JointPlan((seg,), max(max_speed, speed), max_accel, ("stop",))


def plan_move(t0_s: float, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, q_target: np.ndarray,
              max_speed: float, max_accel: float, lower: np.ndarray, upper: np.ndarray) -> JointPlan:
    """A smooth plan from the current commanded state to rest at ``q_target``.

    Position and speed continue from the current state; the acceleration restarts from zero (see
    :func:`plan_stop`). When one quintic cannot blend within the limits (reversing at speed, or it would
    leave the joint limits), the plan brakes to rest first and then moves rest to rest.
    """
    zero = np.zeros(6)
    seg = plan_segment(t0_s, q, qd, zero, q_target, max_speed, max_accel, lower, upper)
    if seg is not None:
        return JointPlan((seg,), max_speed, max_accel)
    brake = plan_stop(t0_s, q, qd, zero, max_speed, max_accel, lower, upper).segments[0]
    rest = plan_segment(brake.end_s, brake.q_end, zero, zero, q_target, max_speed, max_accel, lower, upper)
    assert rest is not None  # rest to rest always succeeds
    return JointPlan((brake, rest), max_speed, max_accel, ("brake then move",))


__all__ = ["JointPlan", "Segment", "hold", "plan_hold", "plan_move", "plan_segment", "plan_stop"]
