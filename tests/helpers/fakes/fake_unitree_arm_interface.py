"""A contract-enforcing stand-in for Unitree's ``unitree_arm_interface`` (the z1_sdk Python binding).

It mirrors the binding's names and argument rules (examples_py/arm_python_interface.cpp, z1_sdk 2.x)
and the behaviour of the SDK plus a ``z1_ctrl`` controller and its arm, so that code passing here is
likely to work on the rig:

- ``ArmInterface(hasGripper)`` binds the SDK port 8072 and talks to the controller on 8071; a second
  stock interface in one process cannot bind 8072 again. The stock binding has ``CtrlComponents`` and
  ``Z1Model`` classes without constructors; with ``reset(multi_arm=True)`` it is darp's patched binding
  (native/z1_sim/binding-ports.patch): ``DARP_PORTS``, ``ArmInterface(hasGripper, controllerIP,
  controllerPort, sdkPort)`` and ``isDisconnected()``.
- ``lowstate`` holds zeros and ``getCurrentState()`` is INVALID until an exchange with a running
  controller; exchanges happen in the SDK loop (500 Hz wall time after ``loopOn()``) or per ``sendRecv()``.
  An exchange nobody answers waits the SDK's 0.5 s receive time-out; four in a row and ``isDisconnected()``
  is true (as measured on the vendor SDK). In JOINTCTRL the controller tracks what ``setArmCmd`` set
  (flavour ``lowcmd``, the vendor SDK's behaviour) or, with flavour ``members``, ``arm.q``/``arm.qd``.
- ``ArmFSMState`` has the C++ values of arm_common.h (the vendor's ``.pyi`` gives wrong ones) and only the
  names the binding exports.
- FSM calls wait for the controller like the SDK: ``setFsm``/``startTrack``/``labelRun``/``backToStart``
  and ``MoveJ`` with ``setWait(True)`` block until the state changes (the real SDK would hang forever
  with the loop off: here that is an error). With ``setWait(False)`` ``MoveJ`` returns at once.
- Units: radians, rad/s. Commands outside the joint limits, joint speeds above pi rad/s, a commanded
  joint that jumps faster than the arm can move, postures beyond the arm's reach (millimetres?) and
  commands that would never be sent (loop off) are contract violations: raised as
  :class:`SdkContractError` *and* recorded in ``WORLD.violations`` for the test fixture to check.

The simulated arm tracks joint commands with a first-order lag (``lag_s``) at most pi rad/s.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
import weakref

import numpy as np

from darp.kinematics import ik, z1
from darp.kinematics.transforms import posture_to_transform, transform_to_posture
from helpers.fakes.fake_z1_controller import (
    DT,
    Q_MAX,
    Q_MIN,
    SPEED_LIMIT,
    WORLD,
    ArmFSMState,
    FakeController,
    SdkContractError,
    violation,
)

STOCK_SDK_PORT, STOCK_CONTROLLER_PORT = 8072, 8071
RECV_TIMEOUT_S = 0.5  # the SDK's UDPPort waits this long for an answer
DISCONNECT_AFTER = 4  # time-outs in a row before the SDK's isDisConnect
SAVED_STATES = {name: np.array(q, dtype=float) for name, q in {
    "forward": [0.0, 1.5, -1.0, -0.54, 0.0, 0.0], "startFlat": [0.0, 0.0, -0.005, -0.074, 0.0, 0.0],
    "show_left": [-1.0, 0.9, -1.0, -0.3, 0.0, 0.0], "show_mid": [0.0, 0.9, -1.2, 0.3, 0.0, 0.0],
    "show_right": [1.0, 0.9, -1.0, -0.3, 0.0, 0.0]}.items()}


def _vec6(value, what: str) -> np.ndarray:
    """pybind11's Eigen caster: a sequence of 6 numbers (lists and int arrays are converted), else TypeError."""
    if isinstance(value, (str, bytes)) or value is None:
        raise TypeError(f"{what}: incompatible function arguments (expected a 6-vector of float)")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{what}: incompatible function arguments (expected a 6-vector of float)") from None
    if arr.shape != (6,):
        raise TypeError(f"{what}: incompatible function arguments (got shape {arr.shape}, expected (6,))")
    if not np.all(np.isfinite(arr)):
        violation(f"{what}: NaN or infinite values sent to the arm")
    return arr.copy()


def _float(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{what}: incompatible function arguments (expected float, got {type(value).__name__})")
    return float(value)


def _bool(value, what: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{what}: incompatible function arguments (expected bool, got {type(value).__name__})")
    return bool(value)


def add_controller(q0=SAVED_STATES["startFlat"], *, port: int = STOCK_CONTROLLER_PORT,
                   ip: str = "127.0.0.1", lag_s: float = 0.01) -> FakeController:
    """Start a simulated ``z1_ctrl`` (with its arm at ``q0``) listening for the SDK on ``ip:port``."""
    controller = FakeController(np.asarray(q0, dtype=float), lag_s)
    WORLD.controllers[(ip, port)] = controller
    return controller


def reset(*, multi_arm: bool = False, flavour: str = "lowcmd") -> None:
    """Forget every controller, port and violation; choose the binding variant."""
    for ref in WORLD.interfaces:
        arm = ref()
        if arm is not None:
            arm._shutdown_loop()
    WORLD.__init__()
    WORLD.flavour = flavour
    WORLD.multi_arm = multi_arm
    if multi_arm:
        globals()["DARP_PORTS"] = 1
        ArmInterface.isDisconnected = ArmInterface._is_disconnected  # type: ignore[attr-defined]
    else:
        globals().pop("DARP_PORTS", None)
        if "isDisconnected" in vars(ArmInterface):
            del ArmInterface.isDisconnected


def postureToHomo(posture) -> np.ndarray:
    return posture_to_transform(_vec6(posture, "postureToHomo"))


def homoToPosture(T) -> np.ndarray:
    return transform_to_posture(np.asarray(T, dtype=float))


def _bind(port: int) -> None:
    if port in WORLD.bound_ports:
        violation(f"UDPPort bind failed: port {port} is already bound in this process (the real SDK exits the "
                  f"process here; a second stock ArmInterface shares the SDK port 8072)")
    WORLD.bound_ports.add(port)


class Z1Model:
    def __init__(self, *args) -> None:
        if len(args) != 4:
            raise TypeError("Z1Model(): incompatible constructor arguments (endPosLocal, endEffectorMass, "
                            "endEffectorCom, endEffectorInertia)")
        self.end_frame = "flange"

    def getJointQMax(self) -> np.ndarray:
        return Q_MAX.copy()

    def getJointQMin(self) -> np.ndarray:
        return Q_MIN.copy()

    def getJointSpeedMax(self) -> np.ndarray:
        return np.full(6, SPEED_LIMIT)

    def forwardKinematics(self, q, index: int = 6) -> np.ndarray:
        return z1.fk(_vec6(q, "forwardKinematics"), self.end_frame if index >= 6 else "link06")

    def inverseKinematics(self, Tdes, qPast, checkInWorkSpace: bool = False):
        result = ik.solve_ik(np.asarray(Tdes, dtype=float), frame=self.end_frame, q_init=_vec6(qPast, "IK"),
                             limits="sdk")
        return bool(result.success), np.asarray(result.q, dtype=float)

    def jointProtect(self, q, qd):
        return np.clip(_vec6(q, "jointProtect"), Q_MIN, Q_MAX), np.clip(_vec6(qd, "jointProtect"), -SPEED_LIMIT,
                                                                        SPEED_LIMIT)


class CtrlComponents:
    def __init__(self) -> None:
        raise TypeError("unitree_arm_interface.CtrlComponents: No constructor defined!")

    @classmethod
    def _internal(cls) -> CtrlComponents:
        comp = object.__new__(cls)
        comp.dt = DT
        comp.armModel = object.__new__(Z1Model)
        comp.armModel.end_frame = "flange"
        return comp


class LowlevelState:
    def __init__(self) -> None:
        self._q, self._qd, self._qdd, self._tau = (np.zeros(6) for _ in range(4))

    def getQ(self) -> np.ndarray:
        return self._q.copy()

    def getQd(self) -> np.ndarray:
        return self._qd.copy()

    def getQTau(self) -> np.ndarray:
        return self._tau.copy()

    def getTau(self) -> np.ndarray:
        return self._tau.copy()

    def getGripperQ(self) -> float:
        return 0.0


class ArmInterface:
    """The SDK's ``unitreeArm`` as bound to Python."""

    def __init__(self, hasGripper=True, *ports) -> None:
        self._has_gripper = _bool(hasGripper, "ArmInterface.__init__")
        if ports:
            if not WORLD.multi_arm or len(ports) != 3:
                raise TypeError("ArmInterface(): incompatible constructor arguments (stock binding: hasGripper)")
            ip, to_port, own_port = ports
            if not isinstance(ip, str) or not all(isinstance(p, int) and not isinstance(p, bool)
                                                  for p in (to_port, own_port)):
                raise TypeError("ArmInterface(): incompatible constructor arguments (bool, str, int, int)")
        else:
            ip, to_port, own_port = "127.0.0.1", STOCK_CONTROLLER_PORT, STOCK_SDK_PORT
        _bind(own_port)
        weakref.finalize(self, WORLD.bound_ports.discard, own_port)
        self._ctrlComp = CtrlComponents._internal()
        self._to = (ip, to_port)
        self._timeouts = 0
        if self._has_gripper:
            self._ctrlComp.armModel.end_frame = "gripper"
        self.lowstate = LowlevelState()
        self._q, self._qd, self._tau = np.zeros(6), np.zeros(6), np.zeros(6)
        self._low_q, self._low_qd = np.zeros(6), np.zeros(6)
        self.gripperQ = self.gripperQd = self.gripperTau = 0.0
        self._recv = ArmFSMState.INVALID
        self._request: ArmFSMState | None = None
        self._move: tuple[np.ndarray, float] | None = None
        self._track = False
        self._wait = True
        self._loop: threading.Thread | None = None
        self._loop_stop = threading.Event()
        self._exchange_lock = threading.Lock()
        WORLD.interfaces.append(weakref.ref(self))

    # -- command members (def_readwrite Vec6) ------------------------------------------------------
    q = property(lambda self: self._q, lambda self, v: setattr(self, "_q", _vec6(v, "ArmInterface.q")))
    qd = property(lambda self: self._qd, lambda self, v: setattr(self, "_qd", _vec6(v, "ArmInterface.qd")))
    tau = property(lambda self: self._tau, lambda self, v: setattr(self, "_tau", _vec6(v, "ArmInterface.tau")))

    # -- the exchange with the controller ------------------------------------------------------------
    def _exchange(self) -> None:
        with self._exchange_lock:
            controller = WORLD.controllers.get(self._to)
            if controller is None:  # nothing answers: the SDK waits for its time-out; lowstate keeps its values
                time.sleep(RECV_TIMEOUT_S)
                self._timeouts += 1
                return
            self._timeouts = 0
            q_cmd, qd_cmd = (self._q, self._qd) if WORLD.flavour == "members" else (self._low_q, self._low_qd)
            state = controller.exchange(self._request, self._track, q_cmd.copy(), qd_cmd.copy(), self._move)
            if self._request is not None and state == self._request:
                self._request, self._move = None, None
            if state != ArmFSMState.JOINTCTRL:
                self._track = False
            self._recv = state
            with controller.lock:
                self.lowstate._q, self.lowstate._qd = controller.q.copy(), controller.qd.copy()

    def _loop_body(self) -> None:
        next_t = time.monotonic()
        while not self._loop_stop.is_set():
            # a contract error is recorded in WORLD.violations; a real controller would not stop either
            with contextlib.suppress(SdkContractError):
                self._exchange()
            next_t += DT
            delay = next_t - time.monotonic()
            if delay > 0:
                self._loop_stop.wait(delay)
            elif delay < -0.05:
                next_t = time.monotonic()

    @property
    def _loop_on(self) -> bool:
        return self._loop is not None and self._loop.is_alive()

    def loopOn(self) -> None:
        if self._loop_on:
            return
        self._loop_stop.clear()
        self._loop = threading.Thread(target=self._loop_body, name="fake-z1-sdk-loop", daemon=True)
        self._loop.start()

    def loopOff(self) -> None:
        self._shutdown_loop()

    def _shutdown_loop(self) -> None:
        self._loop_stop.set()
        if self._loop is not None:
            self._loop.join(timeout=1.0)
        self._loop = None

    def _is_disconnected(self) -> bool:
        return self._timeouts >= DISCONNECT_AFTER

    def sendRecv(self) -> None:
        if self._loop_on:
            violation("sendRecv() while loopOn(): two threads would exchange with the controller")
        self._exchange()

    def _require_loop(self, what: str) -> None:
        if not self._loop_on:
            violation(f"{what} waits for the controller, which only answers through the SDK loop: with "
                      f"loopOff() the real SDK hangs here forever (call loopOn() first)")

    def _wait_state(self, done, what: str, timeout_s: float = 10.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not done():
            self._require_loop(what)
            if time.monotonic() > deadline:
                violation(f"{what}: the controller never answered (the real SDK would hang)")
            time.sleep(DT)

    # -- FSM ------------------------------------------------------------------------------------------
    def getCurrentState(self) -> ArmFSMState:
        return self._recv

    def setFsm(self, fsm) -> bool:
        if not isinstance(fsm, ArmFSMState):
            raise TypeError("setFsm(): incompatible function arguments (expected ArmFSMState)")
        if fsm == ArmFSMState.LOWCMD and self._recv != ArmFSMState.PASSIVE:
            return False
        self._request = fsm
        if fsm != ArmFSMState.LOWCMD:
            self._wait_state(lambda: self._recv == fsm, f"setFsm({fsm.name})")
        return True

    def setWait(self, Y_N) -> None:
        self._wait = _bool(Y_N, "setWait")

    def startTrack(self, fsm) -> None:
        if fsm not in (ArmFSMState.JOINTCTRL, ArmFSMState.CARTESIAN):
            violation(f"startTrack({fsm!r}): only JOINTCTRL or CARTESIAN (the SDK prints an error and does nothing)")
        self._require_loop("startTrack")
        self.setFsm(fsm)
        time.sleep(0.01)
        self._q = self.lowstate.getQ()
        self._qd = np.zeros(6)
        self._low_q, self._low_qd = self._q.copy(), np.zeros(6)
        self._track = True

    def setArmCmd(self, q, qd, tau) -> None:
        q, qd = _vec6(q, "setArmCmd q"), _vec6(qd, "setArmCmd qd")
        _vec6(tau, "setArmCmd tau")
        self._low_q, self._low_qd = q, qd  # sent with the next exchange (SDK loop or sendRecv)

    def setGripperCmd(self, gripperPos, gripperW, gripperTau) -> None:
        for value, name in ((gripperPos, "gripperPos"), (gripperW, "gripperW"), (gripperTau, "gripperTau")):
            _float(value, f"setGripperCmd {name}")

    def setFsmLowcmd(self) -> None:
        self.loopOn()
        self.setFsm(ArmFSMState.PASSIVE)
        self.setFsm(ArmFSMState.LOWCMD)
        self.loopOff()

    def _run_to(self, fsm: ArmFSMState, target: np.ndarray, speed: float, what: str, wait: bool) -> None:
        self._require_loop(what)
        self._move = (target, speed)
        self._request = fsm
        if wait:
            self._wait_state(lambda: self._request is None and self._recv == ArmFSMState.JOINTCTRL, what, 60.0)

    def MoveJ(self, *args) -> bool:
        if len(args) == 2:
            posture, gripper, speed = args[0], None, args[1]
        elif len(args) == 3:
            posture, gripper, speed = args
        else:
            raise TypeError("MoveJ(): incompatible function arguments: (posture, maxSpeed) or "
                            "(posture, gripperPos, maxSpeed)")
        posture, speed = _vec6(posture, "MoveJ posture"), _float(speed, "MoveJ maxSpeed")
        if gripper is not None and not -math.pi / 2 <= _float(gripper, "MoveJ gripperPos") <= 0:
            violation(f"MoveJ gripperPos {gripper} outside [-pi/2, 0] rad")
        if not 0 < speed <= SPEED_LIMIT:
            violation(f"MoveJ maxSpeed {speed} outside (0, pi] rad/s")
        if np.linalg.norm(posture[3:]) > 1.0:
            violation(f"MoveJ posture position {posture[3:]} m is beyond the Z1's reach (millimetres?)")
        ok, q = self._ctrlComp.armModel.inverseKinematics(posture_to_transform(posture), self.lowstate.getQ())
        if not ok:
            return False
        self._run_to(ArmFSMState.MOVEJ, q, speed, "MoveJ", self._wait)
        return True

    def labelRun(self, label) -> None:
        if not isinstance(label, str):
            raise TypeError("labelRun(): incompatible function arguments (expected str)")
        if len(label) >= 10 or label not in SAVED_STATES:
            violation(f"labelRun({label!r}): not a label of savedArmStates.csv shorter than 10 characters "
                      f"(the controller would not move and the SDK would wait forever)")
        self._run_to(ArmFSMState.TOSTATE, SAVED_STATES[label], 1.0, "labelRun", self._wait)

    def backToStart(self) -> None:
        self._run_to(ArmFSMState.TOSTATE, SAVED_STATES["startFlat"], 1.0, "backToStart", self._wait)


reset()
