"""The joint logger and HardwareRig: the logger's schedule (in simulated time), file validity, errors, and a
whole capture on the fakes."""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from darp.backend import ArmBackend, JointState
from darp.errors import ConfigError, FormatError, HardwareError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.realsense.recording import open_recording
from darp.hardware import joint_logger
from darp.hardware.joint_logger import JointLogger
from darp.hardware.rig import HardwareRig
from darp.hardware.settings import HardwareSettings
from darp.kinematics.rig import default_rig_path, load_rig

PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
SERIALS = {"arm110": "348522076490", "arm111": "405622074504"}
EPOCH = 1_718_000_000.0  # host-clock seconds at simulated time 0


# -- the joint logger in simulated time -----------------------------------------------------------------
class SimulatedTime:
    """Stands in for the logger module's ``time`` (its schedule reads ``time.monotonic()``) and makes its stop
    event's ``wait(timeout)`` advance simulated seconds at once instead of blocking. At ``until_s`` the event is
    set, as if ``stop()`` had been called then: a run covers exactly that much simulated time, however fast or
    loaded the machine is."""

    def __init__(self, until_s: float) -> None:
        self.now_s, self.until_s = 0.0, until_s

    def monotonic(self) -> float:
        return self.now_s


class SimulatedStopEvent(threading.Event):
    def __init__(self, sim: SimulatedTime) -> None:
        super().__init__()
        self.sim = sim

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is not None and not self.is_set():
            self.sim.now_s += timeout
            if self.sim.now_s >= self.sim.until_s - 1e-9:
                self.set()
        return self.is_set()


def simulate(monkeypatch: pytest.MonkeyPatch, until_s: float = math.inf) -> SimulatedTime:
    """Run JointLoggers created from now on in simulated time (see :class:`SimulatedTime`)."""
    sim = SimulatedTime(until_s)
    monkeypatch.setattr(joint_logger, "time", sim)
    monkeypatch.setattr(joint_logger, "threading",
                        SimpleNamespace(Thread=threading.Thread, Event=lambda: SimulatedStopEvent(sim)))
    return sim


def run_to_end(logger: JointLogger) -> None:
    """Start ``logger`` and wait until its thread ends by itself (simulated time ran out, or an error)."""
    logger.start()
    deadline = time.monotonic() + 60.0  # only a guard against a hang: nothing here is timed
    while logger.running:
        if time.monotonic() > deadline:
            logger.stop()
            pytest.fail("the joint logger's thread did not end")
        time.sleep(0.001)


class ClockArm(ArmBackend):
    """An arm whose state is stamped with the simulated host clock, with joint 1 turning at 0.1 rad/s. It can
    fail after some reads, stay frozen (the driver repeats its last sample), or spend ``slow_reads[n]``
    simulated seconds inside its n-th read (1-based; the state keeps the time the read began)."""

    def __init__(self, arm_id: str, sim: SimulatedTime, fail_after: int | None = None, frozen: bool = False,
                 slow_reads: dict[int, float] | None = None) -> None:
        self.arm_id, self.sim, self.fail_after, self.frozen, self.reads = arm_id, sim, fail_after, frozen, 0
        self.slow_reads = slow_reads or {}

    def read_state(self) -> JointState:
        self.reads += 1
        if self.fail_after is not None and self.reads > self.fail_after:
            raise HardwareError(f"{self.arm_id}: control loop stopped: simulated fault")
        elapsed = 0.0 if self.frozen else self.sim.now_s
        self.sim.now_s += self.slow_reads.get(self.reads, 0.0)
        return JointState(EPOCH + elapsed, PARK + np.array([0.1 * elapsed, 0, 0, 0, 0, 0]), np.zeros(6))

    def move_to(self, q_target_rad, max_speed_rad_s=None) -> None:
        raise NotImplementedError

    def is_moving(self) -> bool:
        return False

    def stop(self) -> None:
        pass


def test_joint_log_follows_its_33_hz_schedule_and_writes_a_valid_file(tmp_path, monkeypatch):
    assert HardwareSettings.defaults(("arm110", "arm111")).joint_log_hz == 33.0  # what a rig logs at by default
    sim = simulate(monkeypatch, until_s=1.0)
    arms = {"arm110": ClockArm("arm110", sim), "arm111": ClockArm("arm111", sim)}
    path = tmp_path / "arm_poses.csv"
    logger = JointLogger(arms, path)
    assert logger.rate_hz == 33.0
    run_to_end(logger)
    logger.stop()
    log = read_arm_poses(path, strict_tail=True)
    assert log.arms == ("arm110", "arm111")
    for arm_id in arms:
        times = log.times(arm_id)
        assert log.rows(arm_id) == 33  # one simulated second: a row at 0, 1/33, ..., 32/33 s
        np.testing.assert_allclose(times - EPOCH, np.arange(33) / 33.0, atol=2e-6)  # the log has µs resolution
        np.testing.assert_allclose(log.joints(arm_id)[:, 0], 0.1 * (times - EPOCH), atol=1e-6)  # each row's own state
    assert logger.ticks == 33 and logger.skipped_ticks == 0
    assert logger.rows_written == log.n_rows == 66


def test_a_slow_read_drops_the_ticks_it_overran_and_the_schedule_holds(tmp_path, monkeypatch):
    sim = simulate(monkeypatch, until_s=1.0)
    path = tmp_path / "arm_poses.csv"
    logger = JointLogger({"arm110": ClockArm("arm110", sim, slow_reads={10: 0.1})}, path)  # 3.3 periods
    run_to_end(logger)
    logger.stop()
    times = read_arm_poses(path, strict_tail=True).times("arm110") - EPOCH
    # rows 0..9 on the 33 Hz grid (the 10th read began at 9/33 s); the next tick runs late, at 9/33 + 0.1 s,
    # instead of the two it overran (dropped, not run back to back); then the grid again from 13/33 s
    expected = [k / 33 for k in range(10)] + [9 / 33 + 0.1] + [k / 33 for k in range(13, 33)]
    np.testing.assert_allclose(times, expected, atol=2e-6)
    assert logger.skipped_ticks == 2 and logger.ticks + logger.skipped_ticks == 33


def test_repeated_samples_are_not_logged_twice(tmp_path, monkeypatch):
    sim = simulate(monkeypatch, until_s=0.2)
    logger = JointLogger({"arm110": ClockArm("arm110", sim, frozen=True)}, tmp_path / "arm_poses.csv")
    run_to_end(logger)
    logger.stop()
    assert read_arm_poses(tmp_path / "arm_poses.csv").rows("arm110") == 1
    assert logger.ticks == 7 and logger.repeated_samples == 6  # ticks at 0, 1/33, ..., 6/33 s


def test_an_arm_fault_stops_the_log_and_is_reported(tmp_path, monkeypatch):
    sim = simulate(monkeypatch)
    path = tmp_path / "arm_poses.csv"
    logger = JointLogger({"arm110": ClockArm("arm110", sim, fail_after=5)}, path)
    run_to_end(logger)  # the thread ends by itself at the fault
    assert not logger.running
    with pytest.raises(HardwareError, match="joint log stopped early: arm110: control loop stopped: simulated fault"):
        logger.stop()
    assert read_arm_poses(path).rows("arm110") == 5  # everything before the fault is kept, valid
    with pytest.raises(FormatError, match="already exists \\(refusing to overwrite a joint log\\)"):
        JointLogger({"arm110": ClockArm("arm110", sim)}, path).start()


def rig_file(tmp_path, hardware: dict | None = None):
    data = yaml.safe_load(default_rig_path().read_text())
    data["hardware"] = hardware if hardware is not None else {
        "arms": {"arm110": {"arm_ip": "192.168.123.110"},
                 "arm111": {"controller_port": 8073, "sdk_port": 8074, "arm_ip": "192.168.123.111"}},
        "motion": {"max_speed_rad_s": 1.0, "max_accel_rad_s2": 4.0},
        "cameras": {"width": 424, "height": 240, "fps": 15}}
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def plug_in(fake_z1, fake_rs, arms=("arm110", "arm111")):
    fake_z1.reset(multi_arm=True)
    controllers = {arm_id: fake_z1.add_controller(PARK, port=port)
                   for arm_id, port in zip(arms, (8071, 8073), strict=False)}
    for serial in SERIALS.values():
        fake_rs.add_camera(serial)
    return controllers


def test_a_capture_on_the_rig_logs_moves_and_records_on_one_clock(fake_z1, fake_rs, tmp_path):
    plug_in(fake_z1, fake_rs)
    path = rig_file(tmp_path)
    assert load_rig(path).arm_ids == ("arm110", "arm111")  # the geometry loader tolerates the section
    survey = tmp_path / "mug"
    with HardwareRig.open(path) as rig:
        files = rig.start_recordings(survey)
        rig.start_joint_log(survey / "arm_poses.csv")
        target = rig.park_q("arm110") + np.array([0.5, 0.2, -0.2, 0.1, 0.3, 0.4])
        rig.arms["arm110"].move_to(target)
        assert rig.arms["arm110"].is_moving()
        assert rig.wait_until_still("arm110", timeout_s=5.0)
        time.sleep(0.1)
        rig.stop_joint_log()
        assert rig.stop_recordings() == files
    assert set(files) == {"arm110", "arm111"}
    log = read_arm_poses(survey / "arm_poses.csv", strict_tail=True)
    q, t = log.joints("arm110"), log.times("arm110")
    assert np.allclose(q[0], PARK, atol=1e-3) and np.allclose(q[-1], target, atol=0.02)
    # Logged motion respects the 1 rad/s limit. Each row's time is when the driver read the state, which
    # can trail the measurement by a few ms of thread jitter, so speeds are taken over >= 0.1 s spans.
    j = np.searchsorted(t, t + 0.1)
    ok = j < len(t)
    speeds = np.abs(q[j[ok]] - q[ok]) / (t[j[ok]] - t[ok])[:, None]
    assert np.max(speeds) <= 1.0 * 1.3
    assert np.max(np.abs(np.diff(q, axis=0))) <= 1.0 * (np.max(np.diff(t)) + 0.05)  # no jumps between rows
    assert np.allclose(log.joints("arm111"), PARK, atol=1e-3)  # the other arm held still
    for arm_id, file in files.items():
        assert file.name == f"cam{SERIALS[arm_id]}.db3"
        with open_recording(file) as rec:
            stamps_s = rec.timestamps_ms("depth") / 1e3
        # camera and joint log share the host clock: the recording spans the logged motion
        assert stamps_s[0] < t[0] + 0.5 and stamps_s[-1] > t[-1] - 0.5


def test_opening_part_of_a_rig_releases_what_was_connected(fake_z1, fake_rs, tmp_path):
    plug_in(fake_z1, fake_rs, arms=("arm110",))  # arm111's controller is not running
    with pytest.raises(HardwareError, match="arm111: no answer from z1_ctrl at 127.0.0.1:8073 .*192.168.123.111"):
        HardwareRig.open(rig_file(tmp_path), connect_timeout_s=0.3)
    loops = [ref() for ref in fake_z1.WORLD.interfaces]
    assert loops and not any(arm is not None and arm._loop_on for arm in loops)  # arm110 released
    assert fake_rs.WORLD.streaming == {}


def test_hardware_section_errors_name_the_file_and_field(tmp_path):
    bad = {"arms": {"arm110": {"controller_port": 8073}, "arm111": {"controller_port": 8073, "sdk_port": 8074}}}
    with pytest.raises(ConfigError, match=r"rig\.yaml: hardware\.arms\.arm111: controller 127\.0\.0\.1:8073 is "
                                          r"already arm110's"):
        HardwareRig.open(rig_file(tmp_path, bad))
    with pytest.raises(ConfigError, match=r"hardware\.cameras\.fps: expected an integer"):
        HardwareRig.open(rig_file(tmp_path, {"cameras": {"fps": "thirty"}}))


def test_open_rig_takes_a_loaded_rig_and_reads_its_hardware_section(fake_z1, fake_rs, tmp_path):
    plug_in(fake_z1, fake_rs)
    from darp.hardware import open_rig

    with open_rig(load_rig(rig_file(tmp_path))) as rig:  # as `darp calib capture --hardware` calls it
        assert rig.arms["arm111"].connection.controller_port == 8073
        assert rig.arms["arm111"].connection.arm_ip == "192.168.123.111"
        frame = rig.cameras["arm110"].latest_frameset()
        assert frame.depth_m.shape == (240, 424)  # the section's camera settings were applied
        assert rig.arms["arm110"].read_state().q_rad == pytest.approx(PARK, abs=1e-6)
