"""``darp hardware check``: verdicts, one-line failures and exit codes on the SDK fakes; nothing moves."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import yaml

from darp.cli._app import run
from darp.hardware.check import FAIL, OK, WARNING, check_rig, usb_load_mb_s
from darp.hardware.realsense_camera import CameraSettings
from darp.hardware.z1_arm import Z1Connection, probe_arm
from darp.kinematics.rig import default_rig_path

PARK = np.array([0.0, 0.6, -1.2, 1.2, 0.0, 0.0])
SERIALS = {"arm110": "348522076490", "arm111": "405622074504"}


def rig_file(tmp_path, cameras: dict | None = None, serials: dict | None = None, name: str = "rig.yaml"):
    data = yaml.safe_load(default_rig_path().read_text())
    for arm_id, serial in (serials or {}).items():
        data["arms"][arm_id]["camera_serial"] = serial
    data["hardware"] = {"arms": {"arm110": {"arm_ip": "192.168.123.110"},
                                 "arm111": {"controller_port": 8073, "sdk_port": 8074, "arm_ip": "192.168.123.111"}},
                        "cameras": cameras or {}}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def plug_in(fake_z1, fake_rs, arms=("arm110", "arm111"), cameras=("arm110", "arm111"),
            q0=None, **camera_kwargs):
    fake_z1.reset(multi_arm=True)
    ports = {"arm110": 8071, "arm111": 8073}
    controllers = {a: fake_z1.add_controller(PARK if q0 is None else q0.get(a, PARK), port=ports[a]) for a in arms}
    for arm_id in cameras:
        fake_rs.add_camera(SERIALS[arm_id], **camera_kwargs)
    return controllers


def check_json(path, capsys, *extra):
    rc = run(["hardware", "check", "--rig", str(path), "--json", "--timeout-s", "0.3", *extra])
    out, err = capsys.readouterr()
    report = json.loads(out)
    verdicts = {c["name"]: c["verdict"] for c in report["checks"]}
    details = {c["name"]: c["detail"] for c in report["checks"]}
    return rc, report, verdicts, details, err


def assert_one_line_per_failure(report, err):
    lines = err.strip().splitlines()
    failures = [c for c in report["checks"] if c["verdict"] == FAIL]
    more = [c["name"] for c in failures[1:]]
    also = f" (and {len(more)} more failed check(s): {', '.join(more)})" if more else ""
    assert lines == ([f"darp: error: {failures[0]['name']}: {failures[0]['detail']}{also}"] if failures else [])
    assert "Traceback" not in err


def test_all_present_is_all_ok_exit_0_and_nothing_moves(fake_z1, fake_rs, tmp_path, capsys):
    controllers = plug_in(fake_z1, fake_rs)
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path), capsys)
    assert rc == 0 and err == "" and report["ok"] is True
    assert set(verdicts.values()) == {OK}, verdicts
    for arm_id in SERIALS:
        for what in ("camera", "camera mapping", "USB", "streams", "IMU", "controller", "joints", "park"):
            assert f"{arm_id} {what}" in verdicts
        assert report["arms"][arm_id]["q_rad"] == pytest.approx(PARK, abs=1e-9)
        assert report["arms"][arm_id]["within_limits"] and report["arms"][arm_id]["at_park"]
    assert details["arm110 streams"] == "depth z16, IR1 y8, IR2 y8, colour bgr8 at 640x480@30"
    assert details["arm111 controller"].startswith("z1_ctrl at 127.0.0.1:8073 (SDK port 8074")
    assert {c["serial"]: c["usb"] for c in report["cameras"]} == dict.fromkeys(SERIALS.values(), "3.2")
    assert report["cameras"][0]["name"] == "Intel RealSense D435I" and report["cameras"][0]["firmware"] == "5.16.0.1"
    for controller in controllers.values():  # read-only: no FSM change, no joint command tracked
        assert controller.state == fake_z1.ArmFSMState.PASSIVE and controller.commands == []
    assert fake_rs.WORLD.streaming == {}  # cameras enumerated, never started


def test_the_table_lists_devices_and_checks(fake_z1, fake_rs, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "240")
    plug_in(fake_z1, fake_rs)
    assert run(["hardware", "check", "--rig", str(rig_file(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert "RealSense devices" in out and "348522076490" in out and "5.16.0.1" in out
    assert "arm111 joints" in out and "within the Z1 limits" in out
    assert "ok: 19 checks, 0 failed, 0 warning(s)" in out


def test_a_missing_camera_fails_with_one_line(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs, cameras=("arm110",))
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path), capsys)
    assert rc == 2 and report["ok"] is False
    assert verdicts["arm111 camera"] == FAIL and verdicts["arm110 camera"] == OK
    assert details["arm111 camera"].startswith("405622074504 is not connected (cameras found: 348522076490)")
    assert "arm111 streams" not in verdicts  # nothing to list on an absent camera
    assert verdicts["arm111 joints"] == OK  # the arms are still checked
    assert [c["name"] for c in report["checks"] if c["verdict"] == FAIL] == ["arm111 camera"]
    assert_one_line_per_failure(report, err)


def test_swapped_serials_and_a_stranger_are_warnings(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs)
    fake_rs.add_camera("111122223333", imu=False)
    swapped = {"arm110": SERIALS["arm111"], "arm111": SERIALS["arm110"]}
    rc, _, verdicts, details, err = check_json(rig_file(tmp_path, serials=swapped), capsys)
    assert rc == 0 and err == ""
    assert verdicts["arm110 camera mapping"] == verdicts["arm111 camera mapping"] == WARNING
    assert details["arm110 camera mapping"].startswith("405622074504 is arm111's camera in the packaged rig")
    assert verdicts["arm110 camera"] == OK  # present, just crossed
    assert verdicts["other cameras"] == WARNING and "111122223333 (Intel RealSense D435)" in details["other cameras"]


def test_an_unreachable_arm_fails(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs, arms=("arm110",))
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path), capsys)
    assert rc == 2
    assert verdicts["arm111 controller"] == FAIL and verdicts["arm110 controller"] == OK
    assert details["arm111 controller"].startswith("no answer from z1_ctrl at 127.0.0.1:8073 (SDK port 8074, "
                                                   "arm 192.168.123.111) within 0.3 s")
    assert "arm111" not in report["arms"] and "arm111 joints" not in verdicts
    assert_one_line_per_failure(report, err)


def test_the_stock_binding_cannot_reach_the_second_arm(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs)
    fake_z1.reset(multi_arm=False)
    fake_z1.add_controller(PARK, port=8071)
    fake_z1.add_controller(PARK, port=8073)
    rc, _, verdicts, details, _ = check_json(rig_file(tmp_path), capsys)
    assert rc == 2 and verdicts["unitree_arm_interface"] == OK and verdicts["arm110 joints"] == OK
    assert "needs a unitree_arm_interface built with darp's port patch" in details["arm111 controller"]


def test_a_missing_stream_profile_fails(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs)
    # the D435's colour sensor has 320x240@30, its stereo module does not
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path, {"width": 320, "height": 240}), capsys)
    assert rc == 2 and verdicts["arm110 streams"] == verdicts["arm111 streams"] == FAIL
    assert details["arm110 streams"] == "348522076490 offers no depth z16, IR1 y8, IR2 y8 profile at 320x240@30"
    assert_one_line_per_failure(report, err)


def test_imu_required_but_absent_fails_and_auto_warns(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs, imu=False)
    rc, _, verdicts, details, _ = check_json(rig_file(tmp_path, {"imu": "on"}), capsys)
    assert rc == 2 and verdicts["arm110 IMU"] == FAIL
    assert details["arm110 IMU"] == "Intel RealSense D435 offers no accel+gyro profiles, but cameras.imu is 'on'"
    rc, _, verdicts, _, _ = check_json(rig_file(tmp_path, {"imu": "auto"}), capsys)
    assert rc == 0 and verdicts["arm110 IMU"] == WARNING


def test_usb2_fails_when_the_streams_do_not_fit_else_warns(fake_z1, fake_rs, tmp_path, capsys):
    plug_in(fake_z1, fake_rs, usb="2.1")
    assert usb_load_mb_s(CameraSettings()) == pytest.approx(640 * 480 * 30 * 6 / 1e6)
    rc, _, verdicts, details, _ = check_json(rig_file(tmp_path), capsys)
    assert rc == 2 and verdicts["arm110 USB"] == FAIL and details["arm110 USB"].startswith("USB 2.1: the configured "
                                                                                           "streams need 55 MB/s")
    small = {"width": 424, "height": 240, "fps": 15}
    rc, _, verdicts, _, _ = check_json(rig_file(tmp_path, small), capsys)
    assert rc == 0 and verdicts["arm110 USB"] == WARNING


def test_a_joint_outside_its_limits_fails_and_off_park_warns(fake_z1, fake_rs, tmp_path, capsys):
    outside = PARK + np.array([0.0, -0.9, 0.0, 0.0, 0.0, 0.0])  # joint2 at -0.3 rad, below its 0 limit
    off_park = PARK + np.array([0.0, 0.0, 0.4, 0.0, 0.0, 0.0])
    plug_in(fake_z1, fake_rs, q0={"arm110": outside, "arm111": off_park})
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path), capsys)
    assert rc == 2
    assert verdicts["arm110 joints"] == FAIL
    assert details["arm110 joints"].startswith("joint2 -0.300 rad outside [+0.000, +2.880]")
    assert verdicts["arm111 joints"] == OK and verdicts["arm111 park"] == WARNING
    assert details["arm111 park"].startswith("not at the park pose: joint3 is 0.400 rad off")
    assert report["arms"]["arm110"]["within_limits"] is False and report["arms"]["arm111"]["at_park"] is False
    assert [c["name"] for c in report["checks"] if c["verdict"] == FAIL] == ["arm110 joints"]
    assert_one_line_per_failure(report, err)


def test_a_malformed_rig_file_is_one_line(fake_z1, fake_rs, tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("arms: [unclosed\n")
    assert run(["hardware", "check", "--rig", str(bad)]) == 2
    err = capsys.readouterr().err
    expected = (f"darp: error: rig file: {bad}: invalid YAML at line 2 column 1: expected ',' or ']', "
                "but got '<stream end>'")
    assert err.strip().splitlines() == [expected]
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path, {"fps": "thirty"}), capsys)
    assert rc == 2 and list(verdicts) == ["rig file"] and verdicts["rig file"] == FAIL
    assert details["rig file"].endswith("rig.yaml: hardware.cameras.fps: expected an integer, got 'thirty'")
    assert_one_line_per_failure(report, err)
    assert run(["hardware", "check", "--rig", str(tmp_path / "absent.yaml")]) == 2
    assert capsys.readouterr().err.strip().lower().endswith(f"'{tmp_path / 'absent.yaml'}' does not exist.".lower())


def test_missing_sdks_are_failures_not_tracebacks(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails
    monkeypatch.setitem(sys.modules, "unitree_arm_interface", None)
    rc, report, verdicts, details, err = check_json(rig_file(tmp_path), capsys)
    assert rc == 2 and verdicts["pyrealsense2"] == FAIL and verdicts["unitree_arm_interface"] == FAIL
    assert "pip install pyrealsense2" in details["pyrealsense2"]
    assert_one_line_per_failure(report, err)


def test_probe_arm_reads_without_commanding(fake_z1):
    fake_z1.reset()
    controller = fake_z1.add_controller(PARK)
    probe = probe_arm("arm110", Z1Connection(), timeout_s=1.0)
    assert probe.state == "PASSIVE" and probe.q_rad == pytest.approx(PARK)
    assert probe.upper_rad[1] == pytest.approx(2.879793)  # the SDK model's tighter joint-2 limit
    assert controller.commands == [] and controller.state == fake_z1.ArmFSMState.PASSIVE
    assert not any(ref() is not None and ref()._loop_on for ref in fake_z1.WORLD.interfaces)  # loop stopped
    again = check_rig(tmp := default_rig_path(), arm_timeout_s=0.2, sdk=fake_z1)  # packaged rig, no cameras module
    assert again.rig_path == tmp and any(c.name == "arm110 controller" and c.verdict == OK for c in again.checks)
