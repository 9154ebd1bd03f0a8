"""How darp reaches one Z1 through Unitree's Python binding ``unitree_arm_interface`` (z1_sdk).

Facts measured on the vendor's binding and controller (docs/hardware.md, "What the vendor software does"):

- ``ArmInterface(hasGripper)`` (stock) always binds SDK port 8072 and talks to 127.0.0.1:8071. darp's
  patch (native/z1_sim/binding-ports.patch, built by scripts/build_z1_vendor.sh) adds
  ``ArmInterface(hasGripper, controllerIP, controllerPort, sdkPort)``, marked by ``DARP_PORTS``. The SDK
  owns what it is given (``~unitreeArm`` deletes its components, ``~CtrlComponents`` the UDP port and the
  model), so the components are built in C++, never handed over from Python.
- If the SDK port is taken, the SDK's ``UDPPort`` prints ``bind failed`` and **exits the process**
  (status 255): :func:`make_arm_interface` checks the port first.
- Until the first answer, ``getCurrentState()`` is uninitialised memory in the stock binding (the patch sets
  it to INVALID). The binding's ``ArmFSMState`` lacks BACKTOSTART, CALIBRATION, NEXT and SETTRAJ, and its
  ``.pyi`` gives wrong values for several states: :func:`fsm_name` names states by the C++ values.
- The stock binding holds the GIL in every call that waits (``backToStart`` for seconds, ``sendRecv`` up to
  its 0.5 s receive time-out); the patch releases it there.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any, TypeVar

import numpy as np

from darp.errors import HardwareError

DEFAULT_CONTROLLER_PORT = 8071  # where the stock SDK sends (z1_ctrl's SDK port)
DEFAULT_SDK_PORT = 8072  # where the stock SDK listens
PORTS_ATTR = "DARP_PORTS"  # set by darp's binding patch: ArmInterface(hasGripper, ip, controllerPort, sdkPort)

# ArmFSMState as z1_controller's and z1_sdk's arm_common.h define it (the binding exposes only some names).
FSM_NAMES = {0: "INVALID", 1: "PASSIVE", 2: "JOINTCTRL", 3: "CARTESIAN", 4: "MOVEJ", 5: "MOVEL", 6: "MOVEC",
             7: "TRAJECTORY", 8: "TOSTATE", 9: "SAVESTATE", 10: "TEACH", 11: "TEACHREPEAT", 12: "CALIBRATION",
             13: "SETTRAJ", 14: "BACKTOSTART", 15: "NEXT", 16: "LOWCMD"}

T = TypeVar("T")


@dataclass(frozen=True)
class Z1Connection:
    """How to reach one arm's ``z1_ctrl`` controller (UDP on this host)."""

    controller_ip: str = "127.0.0.1"
    controller_port: int = DEFAULT_CONTROLLER_PORT
    sdk_port: int = DEFAULT_SDK_PORT
    has_gripper: bool = False
    arm_ip: str | None = None  # the arm's own address in that controller's config.xml (for messages)

    @property
    def uses_stock_ports(self) -> bool:
        """True when the stock binding (which hard-codes 127.0.0.1:8071/8072) can reach the controller."""
        return (self.controller_ip, self.controller_port, self.sdk_port) == (
            "127.0.0.1", DEFAULT_CONTROLLER_PORT, DEFAULT_SDK_PORT)

    def describe(self) -> str:
        arm = f", arm {self.arm_ip}" if self.arm_ip else ""
        return f"z1_ctrl at {self.controller_ip}:{self.controller_port} (SDK port {self.sdk_port}{arm})"


def fsm_value(state: object) -> int | None:
    """The C++ value of an ``ArmFSMState`` (or of an int), None when it has none."""
    try:
        value: int = int(state)  # type: ignore[call-overload]
    except (TypeError, ValueError):
        return None
    return value


def fsm_name(state: object) -> str:
    """The controller's name of an FSM state, from its C++ value (the binding names only some of them)."""
    value = fsm_value(state)
    if value is not None and value in FSM_NAMES:
        return FSM_NAMES[value]
    return getattr(state, "name", None) or str(state)


def is_answer(state: object) -> bool:
    """True for a state the controller can report (not INVALID, not uninitialised memory)."""
    value = fsm_value(state)
    return value is not None and value in FSM_NAMES and value != 0


def sdk_port_free(port: int) -> bool:
    """True when this host's UDP ``port`` can be bound (the SDK exits the whole process when it cannot)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind(("0.0.0.0", int(port)))
        except OSError:
            return False
    return True


def has_port_patch(sdk: ModuleType) -> bool:
    """True for a binding built with darp's port patch (any controller and SDK port)."""
    return bool(getattr(sdk, PORTS_ATTR, False))


def make_arm_interface(sdk: ModuleType, connection: Z1Connection, arm_id: str, *, check_port: bool = True) -> Any:
    """An ``ArmInterface`` for ``connection``: the stock constructor on the stock ports, else darp's.

    The binding has no type information: its objects are ``Any`` here."""
    if check_port and not sdk_port_free(connection.sdk_port):
        raise HardwareError(f"{arm_id}: SDK port {connection.sdk_port} is taken on this host (another darp, "
                            f"another SDK program, or a controller on that port?); {connection.describe()} is "
                            f"unreachable until it is free (the SDK would exit the process)")
    if connection.uses_stock_ports and not has_port_patch(sdk):
        return sdk.ArmInterface(bool(connection.has_gripper))
    if not has_port_patch(sdk):
        raise HardwareError(
            f"{arm_id}: {connection.describe()} needs a unitree_arm_interface built with darp's port patch "
            f"(the stock binding only reaches 127.0.0.1:8071 from port 8072): build it with "
            f"scripts/build_z1_vendor.sh (docs/hardware.md, 'Two arms')")
    return sdk.ArmInterface(bool(connection.has_gripper), str(connection.controller_ip),
                            int(connection.controller_port), int(connection.sdk_port))


def read_lowstate(arm: Any) -> tuple[np.ndarray, np.ndarray]:
    """The SDK's latest joint positions and speeds (the first six: index 6 is the gripper)."""
    q = np.array(arm.lowstate.getQ(), dtype=np.float64).reshape(-1)[:6]
    qd = np.array(arm.lowstate.getQd(), dtype=np.float64).reshape(-1)[:6]
    return q, qd


def sdk_disconnected(arm: Any) -> bool:
    """The SDK's own link check (darp's patched binding only: about 2 s of silence; False elsewhere)."""
    check = getattr(arm, "isDisconnected", None)
    return bool(check()) if check is not None else False


def call_with_timeout(call: Callable[[], T], timeout_s: float, what: str) -> T:
    """Run a blocking SDK call (an FSM switch waits for the controller, forever if it never answers) with a
    time limit; a HardwareError naming ``what`` on time-out (the call is left to finish in the background)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = call()
        except BaseException as err:  # handed to the caller
            box["error"] = err

    thread = threading.Thread(target=run, name=f"z1-sdk-{what}", daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        raise HardwareError(f"{what}: the controller did not complete it within {timeout_s:g} s")
    if "error" in box:
        raise box["error"]
    return box.get("value")  # type: ignore[return-value]


__all__ = [
    "DEFAULT_CONTROLLER_PORT",
    "DEFAULT_SDK_PORT",
    "FSM_NAMES",
    "PORTS_ATTR",
    "Z1Connection",
    "call_with_timeout",
    "fsm_name",
    "fsm_value",
    "has_port_patch",
    "is_answer",
    "make_arm_interface",
    "read_lowstate",
    "sdk_disconnected",
    "sdk_port_free",
]
