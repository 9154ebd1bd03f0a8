"""The fakes are the oracle for darp.hardware, so they are tested too: no invented API, and the real SDKs'
rules (argument types, blocking, units, what a recording needs) are enforced."""

from __future__ import annotations

import gc
import inspect
import time

import numpy as np
import pytest

from darp.kinematics import z1
from helpers.fakes import fake_pyrealsense2, fake_unitree_arm_interface

# Every name the z1_sdk Python binding defines (examples_py/arm_python_interface.cpp, z1_sdk 2.x),
# plus those of darp's port patch (native/z1_sim/binding-ports.patch).
Z1_BINDING = {
    "module": {"postureToHomo", "homoToPosture", "ArmFSMState", "LowlevelState", "CtrlComponents", "Z1Model",
               "ArmInterface", "DARP_PORTS"},
    "ArmInterface": {"q", "qd", "tau", "gripperQ", "gripperQd", "gripperTau", "lowstate", "_ctrlComp",
                     "setFsmLowcmd", "getCurrentState", "loopOn", "loopOff", "setFsm", "backToStart", "labelRun",
                     "labelSave", "teach", "teachRepeat", "calibration", "MoveJ", "MoveL", "MoveC", "startTrack",
                     "sendRecv", "setWait", "jointCtrlCmd", "cartesianCtrlCmd", "setArmCmd", "setGripperCmd",
                     "isDisconnected"},
    "LowlevelState": {"getQ", "getQd", "getQTau", "getTau", "getGripperQ"},
    "Z1Model": {"checkInSingularity", "jointProtect", "getJointQMax", "getJointQMin", "getJointSpeedMax",
                "inverseKinematics", "forwardKinematics", "inverseDynamics", "CalcJacobian", "solveQP"},
}
FAKE_CONTROLS = {"WORLD", "reset", "add_controller", "add_camera", "violation", "FakeController", "FakeCamera",
                 "SdkContractError", "DT", "STOCK_SDK_PORT", "STOCK_CONTROLLER_PORT", "RECV_TIMEOUT_S",
                 "DISCONNECT_AFTER",
                 "SPEED_LIMIT", "JUMP_SLACK_RAD", "SAVED_STATES", "Q_MIN", "Q_MAX", "STEREO_MODES", "COLOR_MODES",
                 "COLOR_FORMATS", "GYRO_RATES", "KEYS", "SENSOR_OF", "SENSOR_NAMES", "EXPOSURE_LATENCY_MS",
                 "BagRecorder", "Db3Recorder"}
START = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])


def public(obj) -> set[str]:
    return {n for n in vars(obj) if not n.startswith("_")} if inspect.isclass(obj) else {
        n for n in dir(obj) if not n.startswith("_")}


def test_the_z1_fake_invents_no_api(fake_z1):
    fake_z1.reset(multi_arm=True)
    names = {n for n in public(fake_unitree_arm_interface) if not inspect.ismodule(getattr(fake_z1, n))}
    names -= FAKE_CONTROLS | {"annotations", "enum", "math", "threading", "time", "weakref", "np", "ik", "z1",
                              "posture_to_transform", "transform_to_posture", "violation"}
    assert names <= Z1_BINDING["module"], names - Z1_BINDING["module"]
    for cls in ("ArmInterface", "LowlevelState", "Z1Model"):
        extra = public(getattr(fake_z1, cls)) - Z1_BINDING[cls]
        assert not extra, f"{cls}: {extra}"


def test_the_realsense_fake_invents_no_api(fake_rs):
    real = fake_rs._rs
    for name in public(fake_pyrealsense2) - FAKE_CONTROLS:
        value = getattr(fake_rs, name)
        if inspect.ismodule(value) or name in ("annotations", "collections", "threading", "time", "weakref", "np",
                                                 "Path"):
            continue
        assert hasattr(real, name), f"pyrealsense2 has no {name}"
        if inspect.isclass(value) and value.__module__.startswith("helpers.fakes."):
            extra = {m for m in public(value) if not hasattr(getattr(real, name), m)}
            assert not extra, f"pyrealsense2.{name} has no {extra}"
    assert fake_rs.stream is real.stream and fake_rs.option is real.option  # the real enums themselves


def test_z1_state_comes_only_from_the_running_loop(fake_z1):
    fake_z1.add_controller(START)
    arm = fake_z1.ArmInterface(False)
    assert np.all(arm.lowstate.getQ() == 0) and arm.getCurrentState() == fake_z1.ArmFSMState.INVALID
    arm.loopOn()
    time.sleep(0.05)
    assert arm.getCurrentState() == fake_z1.ArmFSMState.PASSIVE
    assert np.allclose(arm.lowstate.getQ(), START)
    arm.loopOff()


def test_z1_movej_blocks_unless_told_not_to(fake_z1):
    fake_z1.add_controller(START)
    arm = fake_z1.ArmInterface(False)
    arm.loopOn()
    target = START + np.array([0.3, 0.2, -0.1, 0.1, 0.2, 0.3])
    posture = fake_z1.homoToPosture(z1.fk(target, "flange"))
    assert arm.MoveJ(posture, 1.5) is True  # setWait(True) is the default: returns once arrived
    assert arm.getCurrentState() == fake_z1.ArmFSMState.JOINTCTRL
    assert np.allclose(arm.lowstate.getQ(), target, atol=0.01)
    arm.setWait(False)
    assert arm.MoveJ(fake_z1.homoToPosture(z1.fk(START, "flange")), 1.5) is True  # returns at once
    assert np.allclose(arm.lowstate.getQ(), target, atol=0.01)  # not moved yet
    deadline = time.monotonic() + 5.0
    while not (arm.getCurrentState() == fake_z1.ArmFSMState.JOINTCTRL and np.allclose(arm.lowstate.getQ(), START,
                                                                                       atol=0.01)):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert arm.MoveJ(np.array([0, 0, 0, 0.7, 0.0, 0.5]), 1.0) is False  # 0.80 m from the shoulder: no IK
    arm.loopOff()


def test_z1_misuse_is_caught(fake_z1):
    fake_z1.add_controller(START)
    posture = fake_z1.homoToPosture(z1.fk(START, "flange"))
    with pytest.raises(TypeError):
        fake_z1.ArmInterface(1)  # pybind's bool caster takes only bools
    arm = fake_z1.ArmInterface(False)
    with pytest.raises(fake_z1.SdkContractError, match="hangs here forever"):
        arm.MoveJ(posture, 1.0)  # the real SDK would wait for an answer that never comes
    arm.loopOn()
    with pytest.raises(TypeError):
        arm.setArmCmd(START, np.zeros(6))  # the binding has no default for tau
    with pytest.raises(TypeError):
        arm.setArmCmd(np.zeros(7), np.zeros(6), np.zeros(6))  # 7-vectors include the gripper: not here
    mm = posture.copy()
    mm[3:] *= 1000.0
    with pytest.raises(fake_z1.SdkContractError, match="millimetres"):
        arm.MoveJ(mm, 1.0)
    with pytest.raises(fake_z1.SdkContractError, match="maxSpeed"):
        arm.MoveJ(posture, 180.0)  # degrees per second
    with pytest.raises(fake_z1.SdkContractError, match="already bound"):
        fake_z1.ArmInterface(False)  # a second stock interface in one process
    arm.startTrack(fake_z1.ArmFSMState.JOINTCTRL)
    arm.setArmCmd(START + np.array([0.5, 0, 0, 0, 0, 0]), np.zeros(6), np.zeros(6))  # a jump the motors cannot follow
    time.sleep(0.05)
    assert any("jumped" in v for v in fake_z1.WORLD.violations)
    arm.loopOff()
    with pytest.raises(TypeError, match="No constructor"):
        fake_z1.CtrlComponents()  # the stock binding cannot build a second arm's components
    fake_z1.WORLD.violations.clear()  # all of the above were on purpose


def test_realsense_requests_are_checked_like_librealsense(fake_rs, tmp_path):
    rs = fake_rs
    rs.add_camera("111")
    cfg = rs.config()
    with pytest.raises(TypeError):
        cfg.enable_stream(rs.stream.depth, 640, 480, rs.format.z16, 30.0)  # ints must be ints
    with pytest.raises(TypeError):
        cfg.enable_device(111)
    cfg.enable_device("111")
    cfg.enable_stream(rs.stream.depth, 640, 480, rs.format.z16, 30)
    cfg.enable_stream(rs.stream.infrared, 1, 424, 240, rs.format.y8, 30)  # the stereo module runs one mode
    with pytest.raises(RuntimeError, match="Couldn't resolve requests"):
        rs.pipeline().start(cfg)
    cfg.enable_stream(rs.stream.infrared, 1, 640, 480, rs.format.y8, 30)
    cfg.enable_record_to_file(str(tmp_path / "x.bag"))
    with pytest.raises(RuntimeError, match="Output file must have .db3 extension"):
        rs.pipeline().start(cfg)
    cfg = rs.config()
    cfg.enable_device("111")
    first = rs.pipeline()
    first.start(cfg)
    with pytest.raises(RuntimeError, match="Device or resource busy"):
        rs.pipeline().start(cfg)
    first.stop()
    rs.add_camera("222")
    with pytest.raises(RuntimeError, match="picks one arbitrarily"):
        rs.pipeline().start(rs.config())
    rs.WORLD.violations.clear()  # on purpose


def test_realsense_frames_count_up_and_follow_the_streaming_device_options(fake_rs):
    rs = fake_rs
    rs.add_camera("111")
    for dev in rs.context().query_devices():  # set before start, on another device object: no effect
        for s in dev.query_sensors():
            s.set_option(rs.option.global_time_enabled, 0.0)
    cfg = rs.config()
    cfg.enable_device("111")
    cfg.enable_stream(rs.stream.depth, 424, 240, rs.format.z16, 30)
    pipe = rs.pipeline()
    profile = pipe.start(cfg)
    frames = [pipe.wait_for_frames().get_depth_frame() for _ in range(3)]
    numbers = [f.get_frame_number() for f in frames]
    assert numbers == sorted(numbers) and len(set(numbers)) == 3
    assert {f.get_frame_timestamp_domain() for f in frames} == {rs.timestamp_domain.global_time}
    assert abs(frames[-1].get_timestamp() / 1e3 - time.time()) < 0.5
    profile.get_device().first_depth_sensor().set_option(rs.option.global_time_enabled, 0.0)
    time.sleep(0.1)
    later = pipe.wait_for_frames().get_depth_frame()
    assert later.get_frame_timestamp_domain() == rs.timestamp_domain.hardware_clock
    pipe.stop()


def test_a_recording_is_finished_only_when_the_recording_device_is_released(fake_rs, tmp_path):
    rs = fake_rs
    rs.reset(version="2.57.7")
    rs.add_camera("111")
    cfg = rs.config()
    cfg.enable_device("111")
    cfg.enable_stream(rs.stream.depth, 424, 240, rs.format.z16, 30)
    cfg.enable_record_to_file(str(tmp_path / "x.bag"))
    pipe = rs.pipeline()
    profile = pipe.start(cfg)
    time.sleep(0.2)
    pipe.stop()
    gc.collect()
    assert not (tmp_path / "x.bag").exists()  # the profile still holds the recorder: file unfinished
    del profile
    gc.collect()
    assert (tmp_path / "x.bag").exists()
