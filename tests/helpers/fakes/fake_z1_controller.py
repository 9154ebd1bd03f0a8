"""The simulated ``z1_ctrl`` controller and arm behind :mod:`helpers.fakes.fake_unitree_arm_interface`.

FSM states, joint tracking with a first-order lag at most pi rad/s, MoveJ/labelRun trajectories, and the
checks on streamed joint commands (limits, speed, jumps). Contract violations are raised as
:class:`SdkContractError` and recorded in ``WORLD.violations``.
"""

from __future__ import annotations

import enum
import math
import threading
import time
import weakref

import numpy as np

from darp.kinematics import z1

DT = 0.002
SPEED_LIMIT = math.pi
JUMP_SLACK_RAD = 0.02
Q_MIN, Q_MAX = np.asarray(z1.SDK_JOINT_LOWER), np.asarray(z1.SDK_JOINT_UPPER)


class ArmFSMState(enum.IntEnum):
    """The names the binding exports, with arm_common.h's values (BACKTOSTART = 14 etc. are not exported)."""

    INVALID = 0
    PASSIVE = 1
    JOINTCTRL = 2
    CARTESIAN = 3
    MOVEJ = 4
    MOVEL = 5
    MOVEC = 6
    TRAJECTORY = 7
    TOSTATE = 8
    SAVESTATE = 9
    TEACH = 10
    TEACHREPEAT = 11
    LOWCMD = 16


class SdkContractError(RuntimeError):
    """The SDK was used in a way the real one would silently misbehave on (hang, jerk, never send)."""


class _World:
    def __init__(self) -> None:
        self.controllers: dict[tuple[str, int], FakeController] = {}
        self.bound_ports: set[int] = set()
        self.violations: list[str] = []
        self.flavour = "lowcmd"  # which command the SDK sends in JOINTCTRL: members q/qd or setArmCmd's lowcmd
        self.interfaces: list[weakref.ref] = []
        self.multi_arm = False


WORLD = _World()


def violation(message: str) -> None:
    WORLD.violations.append(message)
    raise SdkContractError(message)


class FakeController:
    """One ``z1_ctrl`` process and its arm: FSM, joint tracking with lag, MoveJ/labelRun trajectories."""

    def __init__(self, q0: np.ndarray, lag_s: float = 0.01) -> None:
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros(6)
        self.state = ArmFSMState.PASSIVE
        self.lag_s = lag_s
        self.q_hold = self.q.copy()
        self.traj: tuple[float, np.ndarray, np.ndarray, float] | None = None
        self.commands: list[tuple[float, np.ndarray, np.ndarray]] = []  # (monotonic time, q, qd) tracked
        self._last_t: float | None = None
        self._last_cmd: tuple[float, np.ndarray] | None = None
        self.lock = threading.Lock()

    def trip(self, state: ArmFSMState = ArmFSMState.PASSIVE) -> None:
        """Simulate collision protection / an emergency stop: the controller leaves joint control."""
        with self.lock:
            self.state, self.traj, self.q_hold = state, None, self.q.copy()

    def exchange(self, request, track: bool, q_cmd: np.ndarray, qd_cmd: np.ndarray,
                 move: tuple[np.ndarray, float] | None) -> ArmFSMState:
        now = time.monotonic()
        with self.lock:
            dt = 0.0 if self._last_t is None else min(now - self._last_t, 0.05)
            self._last_t = now
            if request is not None and request != self.state:
                self._transition(request, move, now)
            if self.state == ArmFSMState.JOINTCTRL and track:
                self._track(now, q_cmd, qd_cmd)
            self._step(now, dt)
            return self.state

    def _transition(self, request: ArmFSMState, move, now: float) -> None:
        if request == ArmFSMState.LOWCMD and self.state != ArmFSMState.PASSIVE:
            return  # "Only state_passive could transfer to state_lowcmd"
        if request in (ArmFSMState.MOVEJ, ArmFSMState.TOSTATE) and move is not None:
            target, speed = move
            duration = max(1.5708 * float(np.max(np.abs(target - self.q))) / speed, 0.01)
            self.traj = (now, self.q.copy(), target.copy(), duration)
        self.state = request
        self.q_hold = self.q.copy()
        self._last_cmd = None

    def _track(self, now: float, q_cmd: np.ndarray, qd_cmd: np.ndarray) -> None:
        if np.any(q_cmd < Q_MIN - 1e-6) or np.any(q_cmd > Q_MAX + 1e-6):
            violation(f"joint command {np.round(q_cmd, 4)} outside the SDK limits (degrees instead of radians?)")
        if np.any(np.abs(qd_cmd) > SPEED_LIMIT * (1 + 1e-6)):
            violation(f"joint speed command {np.round(qd_cmd, 4)} rad/s above the Z1's pi rad/s")
        t_prev, q_prev = self._last_cmd if self._last_cmd is not None else (now, self.q_hold)
        # Time since the last *different* command: a sender stalled by the OS (Python threads on a busy
        # machine) legitimately catches up in one step; a few centiradians of catch-up are tolerated.
        allowed = SPEED_LIMIT * 1.2 * max(now - t_prev, DT) + JUMP_SLACK_RAD
        if np.max(np.abs(q_cmd - q_prev)) > allowed:
            violation(f"joint command jumped by {np.max(np.abs(q_cmd - q_prev)):.4f} rad in "
                      f"{now - t_prev:.4f} s (more than the arm can move: the motors would jerk)")
        if self._last_cmd is None or np.any(q_cmd != q_prev):
            self._last_cmd = (now, q_cmd.copy())
        self.q_hold = q_cmd.copy()
        self.commands.append((now, q_cmd.copy(), qd_cmd.copy()))

    def _step(self, now: float, dt: float) -> None:
        target = self.q_hold
        if self.traj is not None:
            t0, q0, q1, duration = self.traj
            s = min((now - t0) / duration, 1.0)
            target = q0 + (q1 - q0) * (0.5 - 0.5 * math.cos(math.pi * s))
            if s >= 1.0:
                self.traj, self.q_hold, self.state, target = None, q1.copy(), ArmFSMState.JOINTCTRL, q1
        if self.state == ArmFSMState.PASSIVE or dt <= 0:
            self.qd = np.zeros(6)
            return
        alpha = 1.0 - math.exp(-dt / self.lag_s)
        step = np.clip((target - self.q) * alpha, -SPEED_LIMIT * dt, SPEED_LIMIT * dt)
        self.q = self.q + step
        self.qd = step / dt


