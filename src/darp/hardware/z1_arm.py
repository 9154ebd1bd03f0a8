"""``Z1Arm``: one Unitree Z1 driven through the Z1 SDK's Python binding as an :class:`ArmBackend`.

How the SDK is used (z1_sdk ``unitree_arm_interface``; :mod:`darp.hardware.z1_binding`; docs/hardware.md):

- ``ArmInterface`` talks UDP to a ``z1_ctrl`` controller process. :meth:`Z1Arm.connect` starts the SDK's
  own 500 Hz exchange thread (``loopOn()``, C++: it keeps the controller's link alive while Python threads
  wait for the GIL; the controller goes PASSIVE after about 2 s without the SDK), waits for the
  controller's first real state and enters joint tracking (``startTrack(ArmFSMState.JOINTCTRL)``).
- ``MoveJ`` takes a *Cartesian* posture (the controller's IK picks the joints), so it cannot command a
  joint target. Joint targets are streamed instead: a darp control thread samples a smooth, speed- and
  acceleration-limited trajectory (:mod:`darp.hardware.trajectory`) at 500 Hz and sets each sample with
  ``setArmCmd(q, qd, tau)`` (what the controller tracks in JOINTCTRL; ``arm.q``/``arm.qd`` are written
  too, for older SDK releases). ``move_to`` only swaps the trajectory and returns at once. The
  trajectory's clock advances at most two periods per cycle, so a stalled Python thread slows a move down
  rather than sending a step.
- The control thread caches the latest joint state with its host-clock time (``time.time()``, the clock
  of RealSense global timestamps), which :meth:`Z1Arm.read_state` returns.
- If the controller leaves joint control (a motor error, motor link loss, collision protection, another
  client) or stops answering (darp's patched binding: ``isDisconnected()`` for ``LINK_GRACE_S``, about
  3 s after a controller dies), the thread stops commanding and the next call raises a HardwareError naming the arm.
  :meth:`Z1Arm.back_to_start` and :meth:`Z1Arm.passive` hand the arm to the controller's own motions.
  :meth:`Z1Arm.close` brakes and stops the SDK loop; the controller itself goes PASSIVE about 2 s later.

Targets outside the Z1's joint limits (the tighter of darp's table and the SDK's model) are refused
before anything is sent: in joint tracking the vendor controller forwards any position to the motors.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from types import ModuleType, TracebackType
from typing import Any, Self

import numpy as np

from darp.backend import ArmBackend, JointState
from darp.errors import ConfigError, HardwareError, KinematicsError
from darp.hardware import sdk as sdk_loader
from darp.hardware.trajectory import JointPlan, plan_hold, plan_move, plan_stop
from darp.hardware.z1_binding import (
    DEFAULT_CONTROLLER_PORT,
    DEFAULT_SDK_PORT,
    Z1Connection,
    call_with_timeout,
    fsm_name,
    is_answer,
    make_arm_interface,
    read_lowstate,
    sdk_disconnected,
)
from darp.kinematics import z1

log = logging.getLogger(__name__)

CONTROL_HZ = 500.0
FSM_TIMEOUT_S = 5.0  # how long an FSM switch (startTrack, setFsm) may take
BACK_TO_START_TIMEOUT_S = 60.0
# The SDK reports a lost link after four 0.5 s receive time-outs, and (measured) also for a moment while the
# controller still hears it, on a busy host ("[STATE] UDP connection restablished" follows): darp takes the
# link for lost when the SDK says so for this long.
LINK_GRACE_S = 1.0


@dataclass(frozen=True)
class MotionLimits:
    """Speed and acceleration of moves, and when a move counts as done."""

    max_speed_rad_s: float = 0.6
    max_accel_rad_s2: float = 2.0
    target_tolerance_rad: float = 0.02  # measured joints within this of the target: arrived
    settle_timeout_s: float = 2.0  # after the trajectory ends, how long the arm may take to arrive
    limit_margin_rad: float = 0.0  # refuse targets closer than this to a joint limit

    def __post_init__(self) -> None:
        top = float(np.max(z1.VELOCITY_LIMIT_RAD_S))
        if not 0 < self.max_speed_rad_s <= top:
            raise ConfigError(f"motion.max_speed_rad_s: must be in (0, {top:.4f}], got {self.max_speed_rad_s}")
        for name in ("max_accel_rad_s2", "target_tolerance_rad", "settle_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"motion.{name}: must be positive, got {getattr(self, name)}")
        if not self.limit_margin_rad >= 0:
            raise ConfigError(f"motion.limit_margin_rad: must be >= 0, got {self.limit_margin_rad}")


class Z1Arm(ArmBackend):
    """One Z1 through the SDK; a 500 Hz control thread streams a smooth trajectory to the target."""

    def __init__(self, arm_id: str, connection: Z1Connection | None = None, *, motion: MotionLimits | None = None,
                 sdk: ModuleType | None = None, control_hz: float = CONTROL_HZ) -> None:
        self.arm_id = arm_id
        self.connection = connection or Z1Connection()
        self.motion = motion or MotionLimits()
        self.control_hz = float(control_hz)
        self._sdk = sdk
        self._arm: Any | None = None  # the SDK's ArmInterface while connected
        self._lock = threading.Lock()
        self._stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        self._plan: JointPlan | None = None
        self._traj_t = 0.0  # the trajectory clock: advances with the control loop (see _run)
        self._wall_t = 0.0
        self._latest: JointState | None = None
        self._fault: HardwareError | None = None
        self._fsm_jointctrl: Any = None  # the SDK's ArmFSMState.JOINTCTRL
        self._silent_since: float | None = None  # since when the SDK says the link is lost
        self._loop_on = False  # the SDK's own exchange thread (only while an FSM call waits, or passive)
        self._observing = False  # passive or in the controller's own motion: no darp commands
        self.cycles = 0
        self.late_cycles = 0
        lower = np.maximum(z1.JOINT_LOWER, z1.SDK_JOINT_LOWER)
        upper = np.minimum(z1.JOINT_UPPER, z1.SDK_JOINT_UPPER)
        self._lower, self._upper = lower.copy(), upper.copy()

    # -- connection -------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while streaming joint commands, or observing a passive arm (:meth:`passive`)."""
        return self._arm is not None and (self._observing or (self._thread is not None and self._thread.is_alive()))

    @property
    def joint_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) limits that targets must respect (rad), margin included."""
        m = self.motion.limit_margin_rad
        return self._lower + m, self._upper - m

    def connect(self, timeout_s: float = 3.0) -> None:
        """Reach the controller, enter joint tracking holding the current pose, stream commands at 500 Hz.

        Also takes a passive arm (:meth:`passive`) back into joint tracking."""
        if self._thread is not None and self._thread.is_alive():
            return
        sdk = self._sdk if self._sdk is not None else sdk_loader.load_unitree_sdk()
        self._sdk = sdk
        states = sdk.ArmFSMState
        self._fsm_jointctrl = states.JOINTCTRL
        arm = self._arm if self._arm is not None else make_arm_interface(sdk, self.connection, self.arm_id)
        self._set_loop(arm, True)
        try:
            state = self._wait_for_controller(arm, timeout_s)
            if fsm_name(state) not in ("PASSIVE", "JOINTCTRL"):
                raise HardwareError(f"{self.arm_id}: the controller is busy in state {fsm_name(state)} "
                                    f"(another program is driving the arm?)")
            self._adopt_sdk_limits(arm)
            call_with_timeout(lambda: arm.startTrack(states.JOINTCTRL), FSM_TIMEOUT_S,
                              f"{self.arm_id}: startTrack(JOINTCTRL) at {self.connection.describe()}")
            state = arm.getCurrentState()
            if fsm_name(state) != "JOINTCTRL":
                raise HardwareError(f"{self.arm_id}: the controller refused joint control (it is in {fsm_name(state)})")
            q0, qd0 = read_lowstate(arm)
        except BaseException:
            self._set_loop(arm, False)
            self._arm, self._observing = None, False
            raise
        self._start_tracking(arm, q0, qd0)
        log.info("%s: connected to %s at q = %s", self.arm_id, self.connection.describe(), np.round(q0, 4))

    def _set_loop(self, arm: Any, on: bool) -> None:
        """Start or stop the SDK's own 500 Hz exchange thread (a C++ thread: it keeps the controller's link
        alive while Python threads wait for the GIL; the controller goes PASSIVE after ~2 s of silence)."""
        if on and not self._loop_on:
            arm.loopOn()
        elif not on and self._loop_on:
            arm.loopOff()
        self._loop_on = on

    def _start_tracking(self, arm: Any, q0: np.ndarray, qd0: np.ndarray) -> None:
        self._arm = arm
        self._observing = False
        self._fault = None
        self._silent_since = None
        self._latest = JointState(time.time(), q0, qd0)
        self._wall_t = time.monotonic()
        self._traj_t = 0.0
        self._plan = plan_hold(self._traj_t, q0)
        self._stop_event.clear()
        self._thread = threading.Thread(target=self._run, name=f"z1-{self.arm_id}", daemon=True)
        self._thread.start()

    def _wait_for_controller(self, arm: Any, timeout_s: float) -> Any:
        """The controller's first real state (until its first answer the SDK's is INVALID or garbage)."""
        deadline = time.monotonic() + timeout_s
        while True:
            state = arm.getCurrentState()
            if is_answer(state):
                return state
            if time.monotonic() > deadline:
                raise HardwareError(f"{self.arm_id}: no answer from {self.connection.describe()} within "
                                    f"{timeout_s:g} s: is that z1_ctrl running and the arm powered and reachable?")
            time.sleep(0.005)

    def _adopt_sdk_limits(self, arm: Any) -> None:
        """Tighten the joint limits to the SDK model's where it is stricter."""
        try:
            model = arm._ctrlComp.armModel
            q_max = np.array(model.getJointQMax(), dtype=np.float64).reshape(-1)[:6]
            q_min = np.array(model.getJointQMin(), dtype=np.float64).reshape(-1)[:6]
        except (AttributeError, TypeError, ValueError):
            return
        if q_min.shape == (6,) and q_max.shape == (6,) and np.all(np.isfinite(q_min + q_max)):
            self._lower = np.maximum(self._lower, q_min)
            self._upper = np.minimum(self._upper, q_max)

    def _brake_and_pause(self, brake_timeout_s: float = 3.0) -> None:
        """Brake to rest at the acceleration limit, then stop darp's thread (the controller holds the pose)."""
        thread = self._thread
        if thread is None:
            return
        try:
            if thread.is_alive() and self._fault is None:
                with self._lock:
                    plan = self._plan = self._stop_plan(self._traj_t)
                    end = plan.end_s
                deadline = time.monotonic() + brake_timeout_s
                while self._traj_t < end + 0.05 and time.monotonic() < deadline and thread.is_alive():
                    time.sleep(0.01)
        finally:
            self._stop_event.set()
            thread.join(timeout=2.0)
            self._thread = None

    def close(self, brake_timeout_s: float = 3.0) -> None:
        """Brake to rest, stop streaming and the SDK link (idempotent). About 2 s later the vendor controller,
        no longer hearing the SDK, switches the arm to PASSIVE by itself (damping only: a real arm sinks)."""
        if self._arm is None:
            return
        try:
            self._brake_and_pause(brake_timeout_s)
        finally:
            arm, self._arm = self._arm, None
            self._observing = False
            self._set_loop(arm, False)
        log.info("%s: disconnected", self.arm_id)

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- the controller's own motions -------------------------------------------------------------
    def back_to_start(self, timeout_s: float = BACK_TO_START_TIMEOUT_S) -> None:
        """The controller's ``backToStart``: its own trajectory to the home pose (startFlat, folded), then
        joint tracking again from there. Blocks until done; no darp collision check applies to this path."""
        arm = self._begin_vendor_motion()
        sdk = self._sdk
        assert sdk is not None
        try:
            call_with_timeout(arm.backToStart, timeout_s, f"{self.arm_id}: backToStart")
            state = arm.getCurrentState()
            if fsm_name(state) != "JOINTCTRL":
                raise HardwareError(f"{self.arm_id}: backToStart ended in state {fsm_name(state)}, not JOINTCTRL")
            call_with_timeout(lambda: arm.startTrack(sdk.ArmFSMState.JOINTCTRL), FSM_TIMEOUT_S,
                              f"{self.arm_id}: startTrack(JOINTCTRL)")
            q0, qd0 = read_lowstate(arm)
        except HardwareError as err:
            self._fault = err
            raise
        self._start_tracking(arm, q0, qd0)

    def passive(self) -> None:
        """Switch the controller to PASSIVE (motors damped only: a real arm sinks under gravity). The state is
        still read (the SDK loop stays on); :meth:`connect` takes the arm back into joint tracking."""
        arm = self._begin_vendor_motion()
        sdk = self._sdk
        assert sdk is not None
        try:
            call_with_timeout(lambda: arm.setFsm(sdk.ArmFSMState.PASSIVE), FSM_TIMEOUT_S,
                              f"{self.arm_id}: setFsm(PASSIVE)")
        except HardwareError as err:
            self._fault = err
            raise

    def _begin_vendor_motion(self) -> Any:
        """Stop commanding (after braking) and leave the arm to the controller; returns the interface."""
        self._check_running()
        self._brake_and_pause()
        arm = self._arm
        assert arm is not None
        self._observing = True
        return arm

    # -- control thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        """Sample the plan every period and send it. Plans run on a trajectory clock that advances by the
        elapsed time but at most two periods per cycle: if the OS stalls this thread, the move is slowed
        down instead of the next command jumping ahead (a step the motors would follow with a jerk)."""
        period = 1.0 / self.control_hz
        max_step = 2.0 * period
        next_t = time.monotonic()
        zeros = np.zeros(6)
        while not self._stop_event.is_set():
            try:
                now = time.monotonic()
                with self._lock:
                    self._traj_t += min(max(now - self._wall_t, 0.0), max_step)
                    self._wall_t = now
                self._cycle(zeros)
            except Exception as err:  # any SDK failure stops commanding; reported later
                message = err.message if isinstance(err, HardwareError) else f"{type(err).__name__}: {err}"
                self._fault = HardwareError(f"{self.arm_id}: control loop stopped: {message}")
                log.info("%s", self._fault)  # raised by the next call, reported by the rig's fault()
                return
            self.cycles += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop_event.wait(delay)
            else:
                self.late_cycles += 1
                if delay < -5 * period:  # fell far behind (machine busy): resynchronise, do not burst
                    next_t = time.monotonic()

    def _connected_plan(self) -> JointPlan:
        """The trajectory being tracked (set when connecting, never unset)."""
        if self._plan is None:
            raise HardwareError(f"{self.arm_id}: not connected (call connect() first)")
        return self._plan

    def _connected_state(self) -> JointState:
        """The latest joint state (set when connecting, never unset)."""
        if self._latest is None:
            raise HardwareError(f"{self.arm_id}: not connected (call connect() first)")
        return self._latest

    def _cycle(self, zeros: np.ndarray) -> None:
        """Read the latest state the SDK loop received, check the controller, set this period's command (the
        SDK's own C++ loop sends it at 500 Hz, whether or not this Python thread gets the GIL in time)."""
        arm = self._arm
        if arm is None:
            raise HardwareError("the SDK interface was closed")
        if sdk_disconnected(arm):  # the SDK's flag also rises for a moment on a busy host: it must persist
            now = time.monotonic()
            self._silent_since = self._silent_since if self._silent_since is not None else now
            if now - self._silent_since >= LINK_GRACE_S:
                raise HardwareError(f"no answer from {self.connection.describe()}: the controller stopped or the "
                                    f"link is down (the SDK's receive time-outs); motion stopped")
        else:
            self._silent_since = None
        q_meas, qd_meas = read_lowstate(arm)
        stamp = time.time()
        state = arm.getCurrentState()
        if state != self._fsm_jointctrl:
            raise HardwareError(f"the controller left joint control (now {fsm_name(state)}): a motor error or "
                                f"link loss, collision protection, an emergency stop or another client; "
                                f"motion stopped")
        with self._lock:
            self._latest = JointState(stamp, q_meas, qd_meas)
            q_cmd, qd_cmd, _ = self._connected_plan().sample(self._traj_t)
        arm.setArmCmd(q_cmd, qd_cmd, zeros)
        arm.q = q_cmd
        arm.qd = qd_cmd

    def _stop_plan(self, now: float) -> JointPlan:
        q, qd, qdd = self._connected_plan().sample(now)
        return plan_stop(now, q, qd, qdd, self.motion.max_speed_rad_s, self.motion.max_accel_rad_s2,
                         self._lower, self._upper)

    def _check_running(self) -> None:
        if self._fault is not None:
            raise self._fault
        if not self.connected:
            raise HardwareError(f"{self.arm_id}: not connected (call connect() first)")

    @property
    def fault_error(self) -> HardwareError | None:
        """Why the control loop stopped (the controller left joint control, an SDK failure), or None."""
        return self._fault

    # -- ArmBackend -------------------------------------------------------------------------------
    def read_state(self) -> JointState:
        """The latest joint state from the controller (at most one control cycle old), host-clock time."""
        self._check_running()
        arm = self._arm
        if self._observing and arm is not None:  # passive, or the controller's own motion: the SDK loop reads
            if sdk_disconnected(arm):
                self._fault = HardwareError(f"{self.arm_id}: no answer from {self.connection.describe()}: the "
                                            f"controller stopped or the link is down")
                raise self._fault
            q, qd = read_lowstate(arm)
            return JointState(time.time(), q, qd)
        with self._lock:
            s = self._connected_state()
        return JointState(s.time_s, s.q_rad.copy(), s.qd_rad_s.copy())

    def move_to(self, q_target_rad: np.ndarray, max_speed_rad_s: float | None = None) -> None:
        """Start a smooth joint move to ``q_target_rad`` (rad, SDK angles); returns at once."""
        target = self._check_target(q_target_rad)
        speed = self.motion.max_speed_rad_s if max_speed_rad_s is None else float(max_speed_rad_s)
        top = float(np.max(z1.VELOCITY_LIMIT_RAD_S))
        if not (np.isfinite(speed) and 0 < speed <= top):
            raise KinematicsError(f"{self.arm_id}: max speed must be in (0, {top:.4f}] rad/s, got {speed}")
        self._check_running()
        if self._observing:
            raise HardwareError(f"{self.arm_id}: the arm is passive (connect() takes it back into joint tracking)")
        with self._lock:
            now = self._traj_t
            q, qd, qdd = self._connected_plan().sample(now)
            self._plan = plan_move(now, q, qd, qdd, target, speed, self.motion.max_accel_rad_s2,
                                   self._lower, self._upper)

    def is_moving(self) -> bool:
        """True until the trajectory has ended and the measured joints are within tolerance of its end."""
        self._check_running()
        if self._observing:
            return False
        with self._lock:
            plan = self._connected_plan()
            now, end, target, q = self._traj_t, plan.end_s, plan.q_end, self._connected_state().q_rad
        if now < end:
            return True
        error = np.abs(q - target)
        if float(np.max(error)) <= self.motion.target_tolerance_rad:
            return False
        if now - end < self.motion.settle_timeout_s:
            return True
        j = int(np.argmax(error))
        raise HardwareError(f"{self.arm_id}: joint{j + 1} is {error[j]:.4f} rad from its target "
                            f"{self.motion.settle_timeout_s:g} s after the move ended (blocked or overloaded?)")

    def stop(self) -> None:
        """Brake to rest at the acceleration limit and hold there (nothing to do for a passive arm)."""
        self._check_running()
        if self._observing:
            return
        with self._lock:
            self._plan = self._stop_plan(self._traj_t)

    def wait_until_still(self, timeout_s: float, poll_s: float = 0.01) -> bool:
        """Block until :meth:`is_moving` is False; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while self.is_moving():
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)
        return True

    def _check_target(self, q_target_rad: np.ndarray) -> np.ndarray:
        q = np.asarray(q_target_rad, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise KinematicsError(f"{self.arm_id}: joint target must be 6 finite angles in rad, got "
                                  f"shape {np.shape(q_target_rad)}")
        lower, upper = self.joint_limits
        outside = np.flatnonzero((q < lower - 1e-9) | (q > upper + 1e-9))
        if outside.size:
            j = int(outside[0])
            raise KinematicsError(f"{self.arm_id}: joint{j + 1} target {q[j]:.4f} rad is outside the Z1 limits "
                                  f"[{lower[j]:.4f}, {upper[j]:.4f}] (nothing was sent to the arm)")
        return q.copy()


@dataclass(frozen=True)
class ArmProbe:
    """One read of an arm's controller without commanding it: FSM state, joints (SDK angles), limits."""

    state: str
    q_rad: np.ndarray
    qd_rad_s: np.ndarray
    lower_rad: np.ndarray  # darp's limits tightened by the SDK model's, as Z1Arm enforces them
    upper_rad: np.ndarray


def probe_arm(arm_id: str, connection: Z1Connection | None = None, *, timeout_s: float = 3.0,
              sdk: ModuleType | None = None) -> ArmProbe:
    """Read one arm's joint state and stop: SDK loop on, wait for the controller, read, loop off.

    Read-only (for pre-flight checks): never requests an FSM state, never starts tracking, never sends a
    joint command. Errors are :meth:`Z1Arm.connect`'s (no answer, binding cannot reach the ports).
    """
    reader = Z1Arm(arm_id, connection, sdk=sdk)
    sdk = sdk if sdk is not None else sdk_loader.load_unitree_sdk()
    arm = make_arm_interface(sdk, reader.connection, arm_id)
    arm.loopOn()
    try:
        state = reader._wait_for_controller(arm, timeout_s)
        reader._adopt_sdk_limits(arm)
        q, qd = read_lowstate(arm)
    finally:
        arm.loopOff()
    lower, upper = reader.joint_limits
    return ArmProbe(fsm_name(state), q, qd, lower, upper)


__all__ = ["CONTROL_HZ", "DEFAULT_CONTROLLER_PORT", "DEFAULT_SDK_PORT", "ArmProbe", "MotionLimits", "Z1Arm",
           "Z1Connection", "make_arm_interface", "probe_arm"]
