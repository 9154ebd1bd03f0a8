"""The joint logger and HardwareRig: rate, file validity, errors, and a whole capture on the fakes."""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml

from darp.backend import ArmBackend, JointState
from darp.errors import ConfigError, FormatError, HardwareError
from darp.formats.arm_poses import read_arm_poses
from darp.formats.realsense.recording import open_recording
from darp.hardware.joint_logger import JointLogger
from darp.hardware.rig import HardwareRig
from darp.kinematics.rig import default_rig_path, load_rig

PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
SERIALS = {"arm110": "348522076490", "arm111": "405622074504"}


class ClockArm(ArmBackend):
    """An arm whose state is the host clock and a slowly turning joint 1; can fail after some reads."""

    def __init__(self, arm_id: str, fail_after: int | None = None, frozen: bool = False) -> None:
        self.arm_id, self.fail_after, self.frozen, self.reads = arm_id, fail_after, frozen, 0
        self._t0 = time.time()

    def read_state(self) -> JointState:
        self.reads += 1
        if self.fail_after is not None and self.reads > self.fail_after:
            raise HardwareError(f"{self.arm_id}: control loop stopped: simulated fault")
        t = self._t0 if self.frozen else time.time()
        return JointState(t, PARK + np.array([0.1 * (t - self._t0), 0, 0, 0, 0, 0]), np.zeros(6))

    def move_to(self, q_target_rad, max_speed_rad_s=None) -> None:
        raise NotImplementedError

    def is_moving(self) -> bool:
        return False

    def stop(self) -> None:
        pass


def test_joint_log_runs_at_about_33_hz_and_writes_a_valid_file(tmp_path):
    arms = {"arm110": ClockArm("arm110"), "arm111": ClockArm("arm111")}
    path = tmp_path / "arm_poses.csv"
    logger = JointLogger(arms, path)
    start = time.time()
    logger.start()
    time.sleep(1.0)
    logger.stop()
    elapsed = time.time() - start
    log = read_arm_poses(path, strict_tail=True)
    assert log.arms == ("arm110", "arm111")
    for arm_id, arm in arms.items():
        times = log.times(arm_id)
        rate = log.rows(arm_id) / elapsed
        assert 25 <= rate <= 40, f"{arm_id}: {rate:.1f} Hz"  # behaviour, generous bounds: not a benchmark
        assert np.all(np.diff(times) > 0)
        assert start - 0.01 <= times[0] and times[-1] <= time.time()  # host clock seconds
        assert np.allclose(log.joints(arm_id)[:, 0], 0.1 * (times - arm._t0), atol=1e-6)
    assert logger.rows_written == log.n_rows


def test_repeated_samples_are_not_logged_twice(tmp_path):
    arms = {"arm110": ClockArm("arm110", frozen=True)}
    with JointLogger(arms, tmp_path / "arm_poses.csv") as logger:
        time.sleep(0.2)
    assert read_arm_poses(tmp_path / "arm_poses.csv").rows("arm110") == 1
    assert logger.repeated_samples >= 3


def test_an_arm_fault_stops_the_log_and_is_reported(tmp_path):
    path = tmp_path / "arm_poses.csv"
    logger = JointLogger({"arm110": ClockArm("arm110", fail_after=5)}, path)
    logger.start()
    time.sleep(0.4)
    assert not logger.running
    with pytest.raises(HardwareError, match="joint log stopped early: arm110: control loop stopped: simulated fault"):
        logger.stop()
    assert read_arm_poses(path).rows("arm110") == 5  # everything before the fault is kept, valid
    with pytest.raises(FormatError, match="already exists \\(refusing to overwrite a joint log\\)"):
        JointLogger({"arm110": ClockArm("arm110")}, path).start()


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
                   for arm_id, port in zip(arms, (8071, 8073))}
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
