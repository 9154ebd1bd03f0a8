"""darp's Z1 backend against Unitree's own controller and SDK binding (simulated motors; helpers/vendor.py).

What the fakes cannot show: the vendor FSM's answers, its refusals and its reaction to lost links, the real
binding's threading, the joint log's timing on wall time and the motors' tracking lag.
"""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from darp.errors import HardwareError
from darp.formats.arm_poses import read_arm_poses
from darp.hardware.joint_logger import JointLogger
from darp.hardware.rig import HardwareRig
from darp.hardware.vendor_sim import SimController, request_fsm_state
from darp.hardware.z1_arm import MotionLimits, Z1Arm
from darp.hardware.z1_binding import FSM_NAMES, Z1Connection, fsm_name
from darp.kinematics.rig import load_rig
from helpers.vendor import PARK, free_ports

FAST = MotionLimits(max_speed_rad_s=1.0, max_accel_rad_s2=4.0, settle_timeout_s=2.0)
# The motors' first-order lag is Kd/Kp of the controller's joint-tracking gains (kp 25/30/20/25/15/30,
# kd 2000/3000/3000/3000/2000/2000, scaled as the vendor's IOROS does): 0.04 to 0.075 s.
LAG_S = np.array([0.04, 0.05, 0.075, 0.06, 0.0667, 0.0333])
STATE = {name: value for value, name in FSM_NAMES.items()}


def arm_for(sim: SimController, sdk: object, motion: MotionLimits = FAST) -> Z1Arm:
    return Z1Arm(sim.name, Z1Connection(controller_port=sim.sdk_port, sdk_port=sim.client_port), motion=motion,
                 sdk=sdk)  # type: ignore[arg-type]


class CommandRecorder:
    """The real SDK interface, with every ``setArmCmd`` (host time, q) written down as well."""

    def __init__(self, inner: object) -> None:
        object.__setattr__(self, "_inner", inner)
        object.__setattr__(self, "log", [])

    def setArmCmd(self, q, qd, tau):
        self.log.append((time.time(), np.array(q, dtype=float)))
        return self._inner.setArmCmd(q, qd, tau)

    def __getattr__(self, name: str):
        return getattr(self._inner, name)

    def __setattr__(self, name: str, value) -> None:
        setattr(self._inner, name, value)


def record_commands(arm: Z1Arm) -> CommandRecorder:
    recorder = CommandRecorder(arm._arm)
    arm._arm = recorder
    return recorder


def commanded_at(recorder: CommandRecorder, t: np.ndarray) -> np.ndarray:
    times = np.array([c[0] for c in recorder.log])
    q = np.array([c[1] for c in recorder.log])
    return np.stack([np.interp(t, times, q[:, j]) for j in range(6)], axis=1)


def test_two_arms_through_waypoints_logged_at_33_hz(vendor_sdk, controllers, tmp_path):
    arms = [arm_for(sim, vendor_sdk) for sim in controllers]
    waypoints = {"arm110": [PARK + [0.4, 0.3, -0.2, 0.1, 0.3, -0.5], PARK + [-0.3, 0.1, 0.2, -0.2, 0.0, 0.4], PARK],
                 "arm111": [PARK + [-0.2, 0.4, -0.3, -0.3, -0.2, 0.3], PARK + [0.3, 0.0, 0.0, 0.2, 0.2, 0.0], PARK]}
    try:
        for arm in arms:
            arm.connect()
        recorders = {arm.arm_id: record_commands(arm) for arm in arms}
        log = tmp_path / "arm_poses.csv"
        with JointLogger({a.arm_id: a for a in arms}, log) as logger:
            for k in range(3):
                for arm in arms:
                    arm.move_to(np.array(waypoints[arm.arm_id][k]))
                for arm in arms:
                    assert arm.wait_until_still(10.0)
                    error = np.abs(arm.read_state().q_rad - waypoints[arm.arm_id][k])
                    assert np.max(error) <= FAST.target_tolerance_rad
        assert logger.ticks > 0
    finally:
        for arm in arms:
            arm.close()
    poses = read_arm_poses(log)
    for arm_id, recorder in recorders.items():
        t, q = poses.times(arm_id), poses.joints(arm_id)
        dt = np.diff(t)
        rate = (t.size - 1) / (t[-1] - t[0])
        print(f"{arm_id}: {t.size} rows over {t[-1] - t[0]:.2f} s, {rate:.2f} Hz, interval median "
              f"{np.median(dt) * 1e3:.2f} ms, std {np.std(dt) * 1e3:.2f} ms, max {dt.max() * 1e3:.1f} ms")
        assert abs(rate - 33.0) < 1.5  # the logger's schedule is absolute: no drift
        assert abs(np.median(dt) - 1 / 33.0) < 0.003
        assert dt.max() < 0.25  # a busy host delays a tick, never drops seconds
        # The measured joints follow the commands within the motors' lag: at most the joint speed times the lag
        # (plus a few control periods of transport). darp sends the speed too (qd), which the motors use as
        # feed-forward, so on smooth moves the error is far below that bound (a few milliradians).
        inside = t[(t > recorder.log[0][0]) & (t < recorder.log[-1][0])]
        q_in = q[(t > recorder.log[0][0]) & (t < recorder.log[-1][0])]
        error = np.abs(q_in - commanded_at(recorder, inside))
        assert np.all(error <= FAST.max_speed_rad_s * (LAG_S + 0.03) + 2e-3), error.max(axis=0)
        shifts = np.arange(0.0, 0.2, 0.005)
        fit = [np.max(np.abs(q_in - commanded_at(recorder, inside - s))) for s in shifts]
        best = shifts[int(np.argmin(fit))]
        print(f"{arm_id}: largest lag error {error.max():.4f} rad, best shift {best * 1e3:.0f} ms, "
              f"residual {min(fit):.4f} rad")
        assert error.max() < 0.02


def test_back_to_start_passive_then_joint_tracking_again(vendor_sdk, controllers):
    arm = arm_for(controllers[0], vendor_sdk)
    try:
        arm.connect()
        arm.back_to_start()  # the controller's own trajectory to startFlat, then joint tracking again
        start_flat = np.array([0.0, 0.0, -0.005, -0.074, 0.0, 0.0])
        assert np.max(np.abs(arm.read_state().q_rad - start_flat)) < 0.005
        arm.move_to(PARK)
        assert arm.wait_until_still(10.0)
        arm.passive()
        assert not arm.is_moving() and "Switched from joint space control to passive" in controllers[0].log_text()
        with pytest.raises(HardwareError, match="arm110: the arm is passive"):
            arm.move_to(PARK + 0.1)
        arm.stop()  # nothing to stop: no error
        arm.connect()  # back into joint tracking where it is
        arm.move_to(PARK + 0.1)
        assert arm.wait_until_still(10.0)
    finally:
        arm.close()
    log = controllers[0].log_text()
    for line in ("Switched from joint space control to back to start", "Reached Goal State: startFlat",
                 "Switched from passive to joint space control"):
        assert line in log


def test_stop_brakes_short_of_the_target_and_holds(vendor_sdk, controllers):
    arm = arm_for(controllers[0], vendor_sdk, MotionLimits(max_speed_rad_s=0.5, max_accel_rad_s2=2.0))
    try:
        arm.connect()
        arm.move_to(PARK + np.array([1.0, 0, 0, 0, 0, 0]))  # a 3.75 s move
        time.sleep(1.0)
        arm.stop()
        assert arm.wait_until_still(3.0)
        held = arm.read_state().q_rad
        time.sleep(0.3)
        assert 0.05 < held[0] - PARK[0] < 0.6
        assert np.max(np.abs(arm.read_state().q_rad - held)) < 1e-3
    finally:
        arm.close()


def _inject(kind: str, sims: list[SimController]) -> str:
    """Make arm111's controller fail; returns what the error must say."""
    target = sims[1]
    if kind == "controller killed":
        target.kill()
        return "no answer from z1_ctrl"
    if kind == "wrong FSM state":  # another SDK client switches the arm to PASSIVE
        request_fsm_state(target.sdk_port, STATE["PASSIVE"])
        return r"left joint control \(now PASSIVE\)"
    target.toggle_motor_link()  # "motor link lost"
    return r"left joint control \(now PASSIVE\)"


@pytest.mark.parametrize("kind", ["controller killed", "wrong FSM state", "motor link lost"])
def test_a_failing_controller_is_one_error_naming_the_arm_and_both_arms_stop(vendor_sdk, controllers, kind):
    rig = load_rig()
    arms = {sim.name: arm_for(sim, vendor_sdk) for sim in controllers}
    hardware = HardwareRig(rig, arms=dict(arms), cameras={})
    try:
        hardware.connect()
        for arm_id, arm in arms.items():
            arm.move_to(PARK + (0.8 if arm_id == "arm110" else -0.8) * np.array([1, 0, 0, 0, 0, 1]))
        time.sleep(0.4)
        expected = _inject(kind, controllers)
        deadline = time.monotonic() + 5.0
        while hardware.fault() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        fault = hardware.fault()
        assert fault is not None and fault.arms == ("arm111",)
        assert "\n" not in fault.message and fault.message.startswith("arm111: ")
        with pytest.raises(HardwareError, match=f"arm111: .*{expected}"):
            arms["arm111"].read_state()
        arms["arm110"].stop()  # what the survey does on a fault: stop every arm
        assert arms["arm110"].wait_until_still(3.0)
        held = arms["arm110"].read_state().q_rad
        time.sleep(0.3)
        assert np.max(np.abs(arms["arm110"].read_state().q_rad - held)) < 1e-3
        assert arms["arm110"].fault_error is None
    finally:
        hardware.close()


def test_a_joint_pushed_into_its_hard_stop_trips_and_is_reported(vendor_sdk, vendor_build, tmp_path):
    """Joint 1 stops at 0.3 rad on this arm (a cable, a fixture: darp's limits allow more): the motor pushes at
    full torque, trips its over-current protection and the controller drops the arm to PASSIVE."""
    ports = free_ports(2)
    sim = SimController("arm110", ports[0], ports[1], q0_rad=PARK, run_dir=tmp_path, build=vendor_build,
                        joint_ranges={1: (-2.6, 0.3)})
    with sim:
        arm = arm_for(sim, vendor_sdk)
        try:
            arm.connect()
            arm.move_to(PARK + np.array([0.6, 0, 0, 0, 0, 0]))
            with pytest.raises(HardwareError, match=r"arm110: .*left joint control \(now PASSIVE\)"):
                assert arm.wait_until_still(5.0)
        finally:
            arm.close()
        assert "[ERROR] Motor 0 phase current is too large" in sim.log_text()


def test_taken_ports_are_clear_errors_and_the_process_survives(vendor_sdk, controllers):
    sim = controllers[0]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as squatter:
        squatter.bind(("127.0.0.1", sim.client_port))  # the SDK would print "bind failed" and exit(255)
        arm = arm_for(sim, vendor_sdk)
        with pytest.raises(HardwareError, match=f"arm110: SDK port {sim.client_port} is taken"):
            arm.connect()
    with pytest.raises(HardwareError, match=f"again: cannot start z1_ctrl_sim: UDP port {sim.sdk_port}"):
        SimController("again", sim.sdk_port, sim.client_port + 1000, build=sim.build).start()


def test_a_busy_controller_is_refused_by_name(vendor_sdk, controllers):
    sim = controllers[0]
    request_fsm_state(sim.sdk_port, STATE["LOWCMD"], duration_s=0.1)  # another client, low-level mode
    time.sleep(0.1)
    arm = arm_for(sim, vendor_sdk)
    with pytest.raises(HardwareError, match="arm110: the controller is busy in state LOWCMD"):
        arm.connect()
    assert not arm.connected
    assert fsm_name(vendor_sdk.ArmFSMState.LOWCMD) == "LOWCMD" and int(vendor_sdk.ArmFSMState.LOWCMD) == 16


def test_an_external_plant_answers_for_the_motors(vendor_sdk, vendor_build, tmp_path):
    """``--plant``: the motors' state comes from another process over the documented datagrams (here a
    kinematic plant in this test; native/z1_sim/README.md, "External plant")."""
    import struct
    import threading

    plant = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    plant.bind(("127.0.0.1", 0))
    plant.settimeout(0.2)
    q = PARK.copy()
    seen = {"commands": 0}
    stop = threading.Event()

    def serve() -> None:
        nonlocal q
        while not stop.is_set():
            try:
                data, sender = plant.recvfrom(512)
            except TimeoutError:
                continue
            assert len(data) == 256 and data[:4] == b"Z1C1"
            seq, dt = struct.unpack_from("<Id", data, 4)
            q_cmd, dq_cmd, tau, kp, kd = (np.array(struct.unpack_from("<6d", data, 16 + 48 * k)) for k in range(5))
            rate = np.where(kd > 0, dq_cmd + kp / np.maximum(kd, 1e-9) * (q_cmd - q), 0.0)
            q = q + np.clip(rate, -np.pi, np.pi) * dt
            seen["commands"] += 1
            plant.sendto(b"Z1S1" + struct.pack("<I", seq) + struct.pack("<18d", *q, *rate, *tau), sender)

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    ports = free_ports(2)
    try:
        with SimController("arm110", ports[0], ports[1], q0_rad=PARK, run_dir=tmp_path, build=vendor_build,
                           plant=("127.0.0.1", plant.getsockname()[1])) as sim:
            arm = arm_for(sim, vendor_sdk)
            try:
                arm.connect()
                target = PARK + np.array([0.3, 0.2, -0.2, 0.0, 0.1, 0.0])
                arm.move_to(target)
                assert arm.wait_until_still(10.0)
                assert np.max(np.abs(arm.read_state().q_rad - target)) <= FAST.target_tolerance_rad
                assert np.max(np.abs(q - target)) <= FAST.target_tolerance_rad  # the plant's own joints
            finally:
                arm.close()
    finally:
        stop.set()
        server.join(timeout=2.0)
        plant.close()
    assert seen["commands"] > 250  # one exchange per controller cycle (250 Hz)
