"""SDK discovery, lazy imports, recording containers per SDK version, and the rig file's hardware section."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from darp.errors import ConfigError, HardwareError
from darp.hardware import sdk
from darp.hardware.realsense_camera import RealSenseCamera
from darp.hardware.settings import HardwareSettings, hardware_settings_from_dict
from darp.hardware.z1_arm import Z1Arm

ARMS = ("arm110", "arm111")


def test_importing_darp_hardware_loads_no_vendor_sdk():
    code = textwrap.dedent("""
        import sys
        import darp.hardware as hw
        from darp.hardware import HardwareRig, RealSenseCamera, Z1Arm, JointLogger, load_hardware_settings
        import darp.hardware.rig, darp.hardware.z1_arm, darp.hardware.realsense_camera, darp.hardware.sdk
        rig = HardwareRig(__import__("darp.kinematics.rig", fromlist=["load_rig"]).load_rig())
        assert set(rig.arms) == {"arm110", "arm111"} and rig.cameras["arm111"].serial == "405622074504"
        loaded = [m for m in ("pyrealsense2", "unitree_arm_interface") if m in sys.modules]
        print("loaded:", loaded)
        assert not loaded, loaded
    """)
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert "loaded: []" in result.stdout


def test_a_missing_unitree_sdk_says_how_to_get_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "unitree_arm_interface", None)  # import fails as if not installed
    with pytest.raises(HardwareError,
                       match="unitree_arm_interface.*cannot be imported.*build_z1_vendor.sh.*pybind11 >= 2.13"):
        Z1Arm("arm110").connect()
    assert "unavailable" in sdk.sdk_report()["unitree_arm_interface"]


def test_a_missing_realsense_sdk_says_how_to_get_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(HardwareError, match=r"pyrealsense2.*cannot be imported.*pip install 'darp\[realsense\]'"):
        RealSenseCamera("348522076490").open()


def test_the_installed_pyrealsense2_is_reported_with_its_container():
    import pyrealsense2 as rs

    version = sdk.realsense_version(rs)
    assert version == sdk.parse_version(rs.__version__)
    assert sdk.sdk_report()["pyrealsense2"].endswith(f"(records {sdk.native_suffix(version)})")


@pytest.mark.parametrize("version, policy, suffix", [
    ((2, 57, 7), "auto", ".bag"), ((2, 58, 0), "auto", ".db3"), ((2, 59, 1), "auto", ".db3"),
    ((2, 54, 2), "bag", ".bag"), ((2, 59, 1), "db3", ".db3"), ((3, 0, 0), "auto", ".db3"),
])
def test_recording_container_per_sdk_version(version, policy, suffix):
    assert sdk.recording_suffix(policy, version) == suffix


def test_impossible_containers_are_refused_with_the_fix():
    with pytest.raises(HardwareError, match=r"records only ROS2 \.db3.*pip install 'pyrealsense2<2\.58'"):
        sdk.recording_suffix("bag", (2, 58, 0))
    with pytest.raises(HardwareError, match=r"records only ROS1 \.bag files; \.db3 needs pyrealsense2 >= 2\.58"):
        sdk.recording_suffix("db3", (2, 57, 7))
    with pytest.raises(HardwareError, match="must be one of auto, bag, db3"):
        sdk.recording_suffix("mp4", (2, 59, 1))
    assert sdk.parse_version("2.59.1.10330") == (2, 59, 1)
    with pytest.raises(HardwareError, match="cannot read the pyrealsense2 version"):
        sdk.parse_version("development")


def test_default_hardware_settings_give_each_arm_its_own_ports():
    settings = HardwareSettings.defaults(ARMS)
    a, b = settings.arms["arm110"], settings.arms["arm111"]
    assert (a.controller_port, a.sdk_port, a.uses_stock_ports) == (8071, 8072, True)
    assert (b.controller_port, b.sdk_port, b.uses_stock_ports) == (8073, 8074, False)
    assert settings.joint_log_hz == 33.0 and settings.cameras.width == 640 and settings.cameras.fps == 30


def test_a_full_hardware_section_is_read():
    settings = hardware_settings_from_dict({
        "arms": {"arm110": {"controller_ip": "127.0.0.1", "controller_port": 9001, "sdk_port": 9002,
                            "has_gripper": True, "arm_ip": "192.168.123.110"},
                 "arm111": {"controller_port": 9003, "sdk_port": 9004}},
        "motion": {"max_speed_rad_s": 0.8, "max_accel_rad_s2": 3, "limit_margin_rad": 0.05},
        "cameras": {"width": 848, "height": 480, "fps": 15, "imu": "off", "recording_format": "bag"},
        "joint_log_hz": 40}, ARMS)
    assert settings.arms["arm110"].has_gripper and settings.arms["arm110"].arm_ip == "192.168.123.110"
    assert settings.arms["arm111"].controller_port == 9003 and not settings.arms["arm111"].has_gripper
    assert settings.motion.max_speed_rad_s == 0.8 and settings.motion.max_accel_rad_s2 == 3.0
    assert (settings.cameras.width, settings.cameras.imu, settings.cameras.recording_format) == (848, "off", "bag")
    assert settings.joint_log_hz == 40.0
    arm = Z1Arm("arm110", motion=settings.motion)
    lower, upper = arm.joint_limits
    assert np.allclose(lower[1], 0.05) and np.allclose(upper[1], 2.879793 - 0.05)  # SDK limit, with margin


@pytest.mark.parametrize("section, message", [
    ({"arm": {}}, r"unknown key\(s\) hardware\.arm "),
    ({"arms": {"arm112": {}}}, r"hardware\.arms: no arm 'arm112' in the rig"),
    ({"arms": {"arm110": {"port": 1}}}, r"unknown key\(s\) hardware\.arms\.arm110\.port "),
    ({"arms": {"arm110": {"controller_port": "8071"}}}, r"controller_port: expected an integer"),
    ({"arms": {"arm110": {"controller_port": 70000}}}, r"controller_port: must be a UDP port"),
    ({"arms": {"arm110": {"arm_ip": "192.168.123"}}}, r"arm_ip: not an IP address"),
    ({"arms": {"arm111": {"sdk_port": 8072}}}, r"arm111: sdk_port 8072 is already arm110's"),
    ({"arms": {"arm111": {"sdk_port": 8071}}}, r"arm111: sdk_port 8071 is the port of arm110's controller"),
    ({"motion": {"max_speed_rad_s": 4.0}}, r"motion\.max_speed_rad_s: must be in \(0, 3\.1416\]"),
    ({"cameras": {"imu": "yes"}}, r"hardware\.cameras\.imu: must be one of auto, on, off"),
    ({"cameras": {"recording_format": "mp4"}}, r"cameras\.recording_format: must be one of auto, bag, db3"),
    ({"joint_log_hz": 0}, r"joint_log_hz: must be in \(0, 500\]"),
])
def test_bad_hardware_sections_are_clear_config_errors(section, message):
    with pytest.raises(ConfigError, match=message):
        hardware_settings_from_dict(section, ARMS)
