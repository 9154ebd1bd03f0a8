"""Z1Arm against the contract-enforcing fake of Unitree's SDK binding (no hardware here)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from darp.errors import HardwareError, KinematicsError
from darp.hardware.z1_arm import MotionLimits, Z1Arm, Z1Connection

START = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])  # the default rig's park pose
FAST = MotionLimits(max_speed_rad_s=1.0, max_accel_rad_s2=4.0, settle_timeout_s=1.0)


def connected_arm(fake, q0=START, **kwargs) -> Z1Arm:
    fake.add_controller(q0)
    arm = Z1Arm("arm110", motion=kwargs.pop("motion", FAST), **kwargs)
    arm.connect()
    return arm


def test_move_to_returns_at_once_then_arrives(fake_z1):
    arm = connected_arm(fake_z1)
    try:
        target = START + np.array([0.4, 0.2, -0.2, 0.1, 0.3, -0.5])
        arm.move_to(target)
        just_after = arm.read_state()
        assert arm.is_moving()
        assert np.max(np.abs(just_after.q_rad - START)) < 0.05  # returned before the arm got anywhere
        assert arm.wait_until_still(timeout_s=5.0)
        final = arm.read_state()
        assert np.max(np.abs(final.q_rad - target)) <= FAST.target_tolerance_rad
        assert not arm.is_moving()
    finally:
        arm.close()


def test_streamed_trajectory_is_smooth_and_within_speed(fake_z1):
    arm = connected_arm(fake_z1)
    controller = fake_z1.WORLD.controllers[("127.0.0.1", 8071)]
    try:
        target = START + np.array([0.6, 0.3, -0.3, -0.4, 0.2, 0.8])
        arm.move_to(target)
        assert arm.wait_until_still(timeout_s=5.0)
    finally:
        arm.close()
    t = np.array([c[0] for c in controller.commands])
    q = np.array([c[1] for c in controller.commands])
    qd = np.array([c[2] for c in controller.commands])
    assert len(t) > 200  # streamed at the control rate, not one jump
    assert np.max(np.abs(qd)) <= FAST.max_speed_rad_s * 1.001  # velocity command within the move's limit
    # Commands arrive when the SDK loop sends them, so receipt times carry thread jitter: compare
    # distinct commands, with 20 ms of latency slack (0.02 rad at 1 rad/s), far below any real jump.
    distinct = np.concatenate([[True], np.any(np.diff(q, axis=0) != 0, axis=1)])
    td, qd_distinct = t[distinct], q[distinct]
    steps = np.abs(np.diff(qd_distinct, axis=0))
    assert np.all(steps <= FAST.max_speed_rad_s * (np.diff(td)[:, None] + 0.02))
    moving_span = td[-1] - td[1]  # first distinct entry is the hold before the move
    assert np.max(np.abs(target - START)) / moving_span <= FAST.max_speed_rad_s  # not faster than allowed
    moving = np.abs(target - START) > 0
    # a rest-to-rest move never overshoots: each joint's command is monotone towards the target
    signs = np.sign(np.diff(q[:, moving], axis=0)) * np.sign((target - START)[moving])
    assert np.all(signs >= 0)
    assert np.allclose(q[-1], target, atol=1e-9)


@pytest.mark.parametrize("flavour", ["members", "lowcmd"])
def test_both_sdk_command_paths_move_the_arm(fake_z1, flavour):
    fake_z1.reset(flavour=flavour)
    arm = connected_arm(fake_z1)
    try:
        target = START + 0.2
        target[1] = START[1] + 0.2
        arm.move_to(target)
        assert arm.wait_until_still(timeout_s=5.0)
        assert np.max(np.abs(arm.read_state().q_rad - target)) <= FAST.target_tolerance_rad
    finally:
        arm.close()


def test_stop_brakes_and_holds_short_of_the_target(fake_z1):
    slow = MotionLimits(max_speed_rad_s=0.5, max_accel_rad_s2=2.0, settle_timeout_s=1.0)
    arm = connected_arm(fake_z1, motion=slow)
    try:
        target = START + np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # a 3.75 s quintic at 0.5 rad/s
        arm.move_to(target)
        time.sleep(1.0)  # about 0.12 rad along, at about 0.3 rad/s
        arm.stop()
        assert arm.wait_until_still(timeout_s=2.0)
        held = arm.read_state().q_rad
        time.sleep(0.2)
        again = arm.read_state().q_rad
        assert 0.05 < held[0] - START[0] < 0.5  # moved, then stopped well short of the 1.0 rad target
        assert np.max(np.abs(again - held)) < 1e-3  # and holds there
    finally:
        arm.close()


def test_new_target_during_a_move_blends_without_a_jump(fake_z1):
    arm = connected_arm(fake_z1)
    controller = fake_z1.WORLD.controllers[("127.0.0.1", 8071)]
    try:
        arm.move_to(START + np.array([0.8, 0, 0, 0, 0, 0]))
        time.sleep(0.3)
        second = START + np.array([-0.3, 0.2, 0, 0, 0, 0])
        arm.move_to(second)  # reverses joint 1 while it moves: must decelerate, not jump
        assert arm.wait_until_still(timeout_s=5.0)
        assert np.max(np.abs(arm.read_state().q_rad - second)) <= FAST.target_tolerance_rad
    finally:
        arm.close()
    qd = np.array([c[2] for c in controller.commands])
    assert np.max(np.abs(qd)) <= FAST.max_speed_rad_s * 1.001
    # (the fake also flags any commanded jump as a contract violation, checked by the fixture)


@pytest.mark.parametrize("bad, message", [
    ([0.0, 0.6, -3.0, 1.2, 0.0, 0.0], "joint3 target -3.0000 rad is outside"),
    ([0.0, -0.1, -1.2, 1.2, 0.0, 0.0], "joint2 target -0.1000 rad is outside"),
    ([0.0, 2.9, -1.2, 1.2, 0.0, 0.0], "joint2 target 2.9000 rad is outside"),  # URDF allows it, the SDK not
    ([0.0, 0.6, -1.2], "6 finite angles"),
    ([0.0, 0.6, np.nan, 1.2, 0.0, 0.0], "6 finite angles"),
])
def test_targets_outside_the_limits_are_refused(fake_z1, bad, message):
    arm = connected_arm(fake_z1)
    controller = fake_z1.WORLD.controllers[("127.0.0.1", 8071)]
    try:
        with pytest.raises(KinematicsError, match=message):
            arm.move_to(np.array(bad))
        assert not arm.is_moving()
        time.sleep(0.05)
        assert np.allclose([c[1] for c in controller.commands[-5:]], START, atol=1e-9)  # still holding
        with pytest.raises(KinematicsError, match="max speed"):
            arm.move_to(START, max_speed_rad_s=4.0)
    finally:
        arm.close()


def test_read_state_uses_the_host_clock(fake_z1):
    arm = connected_arm(fake_z1)
    try:
        before = time.time()
        time.sleep(0.01)
        state = arm.read_state()
        after = time.time()
        assert before - 0.01 <= state.time_s <= after
        assert np.allclose(state.q_rad, START, atol=1e-6)
        state.q_rad[:] = 99.0  # a copy: the caller cannot corrupt the driver's state
        assert np.allclose(arm.read_state().q_rad, START, atol=1e-6)
    finally:
        arm.close()


def test_calls_before_connecting_fail_clearly(fake_z1):
    arm = Z1Arm("arm110")
    with pytest.raises(HardwareError, match="arm110: not connected"):
        arm.read_state()
    with pytest.raises(HardwareError, match="not connected"):
        arm.move_to(START)


def test_no_controller_is_a_clear_error(fake_z1):
    arm = Z1Arm("arm110")
    with pytest.raises(HardwareError, match=r"no answer from z1_ctrl at 127\.0\.0\.1:8071.*is that z1_ctrl running"):
        arm.connect(timeout_s=0.2)
    assert not arm.connected


def test_controller_leaving_joint_control_is_reported(fake_z1):
    arm = connected_arm(fake_z1)
    controller = fake_z1.WORLD.controllers[("127.0.0.1", 8071)]
    try:
        arm.move_to(START + 0.3 * np.array([1, 0, 0, 0, 0, 1]))
        time.sleep(0.1)
        controller.trip()  # collision protection: the controller drops to PASSIVE
        time.sleep(0.1)
        with pytest.raises(HardwareError, match="left joint control \\(now PASSIVE\\)"):
            arm.is_moving()
        with pytest.raises(HardwareError, match="left joint control"):
            arm.read_state()
    finally:
        arm.close()


def test_a_second_arm_needs_the_multi_arm_binding(fake_z1):
    fake_z1.add_controller(START, port=8073)
    second = Z1Arm("arm111", Z1Connection(controller_port=8073, sdk_port=8074))
    with pytest.raises(HardwareError, match="arm111: .*needs a unitree_arm_interface built with darp's port patch"):
        second.connect()


def test_two_arms_with_the_multi_arm_binding(fake_z1):
    fake_z1.reset(multi_arm=True)
    fake_z1.add_controller(START, port=8071)
    fake_z1.add_controller(START, port=8073)
    arms = [Z1Arm("arm110", motion=FAST), Z1Arm("arm111", Z1Connection(controller_port=8073, sdk_port=8074),
                                                  motion=FAST)]
    try:
        for arm in arms:
            arm.connect()
        targets = [START + 0.25, START - np.array([0, 0.25, 0.25, 0.25, 0.25, 0.25])]
        for arm, target in zip(arms, targets, strict=True):
            arm.move_to(target)
        for arm, target in zip(arms, targets, strict=True):
            assert arm.wait_until_still(timeout_s=5.0)
            assert np.max(np.abs(arm.read_state().q_rad - target)) <= FAST.target_tolerance_rad
    finally:
        for arm in arms:
            arm.close()


def test_busy_controller_is_refused(fake_z1):
    controller = fake_z1.add_controller(START)
    controller.trip(fake_z1.ArmFSMState.LOWCMD)  # another program drives it in low-level mode
    arm = Z1Arm("arm110")
    with pytest.raises(HardwareError, match="busy in state LOWCMD"):
        arm.connect()
    assert not arm.connected
