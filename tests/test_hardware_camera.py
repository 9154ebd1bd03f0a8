"""RealSenseCamera against the contract-enforcing pyrealsense2 fake (simulated D435i cameras).

With pyrealsense2 >= 2.58 semantics the fake records through the real librealsense recorder, so the
.db3 files read here are genuine; with 2.57 semantics it writes a ROS1 .bag.
"""

from __future__ import annotations

import logging
import time
from itertools import pairwise

import numpy as np
import pytest

from darp.errors import HardwareError
from darp.formats.realsense.recording import open_recording
from darp.hardware.realsense_camera import CameraSettings, RealSenseCamera

SERIAL = "348522076490"
SMALL = CameraSettings(width=424, height=240, fps=15)


def expected_depth_m(fake, w: int = 424, h: int = 240) -> np.ndarray:
    return fake.WORLD.cameras[SERIAL].image("depth", w, h, 0).astype(np.float64) * 0.001


def test_latest_frameset_gives_metric_depth_colour_and_calibration(fake_rs):
    fake_rs.add_camera(SERIAL)
    with RealSenseCamera(SERIAL, SMALL, arm_id="arm110") as camera:
        before = time.time()
        fs = camera.latest_frameset()
        assert fs.depth_m.dtype == np.float32 and fs.depth_m.shape == (240, 424)
        assert np.allclose(fs.depth_m, expected_depth_m(fake_rs), atol=1e-6)  # raw units x depth scale
        assert np.all(fs.depth_m[:, :13] == 0)  # invalid pixels stay 0
        assert abs(fs.timestamp_s - before) < 1.0  # host clock, seconds
        assert fs.extra["timestamp_domain"] == "global_time"
        k = fs.depth_intrinsics
        assert (k.width, k.height) == (424, 240) and k.fx == pytest.approx(383.5 * 424 / 640)
        assert k.model == "Brown Conrady"
        assert fs.colour_bgr.shape == (240, 424, 3) and fs.colour_intrinsics.model == "Inverse Brown Conrady"
        T_color_depth = fake_rs.WORLD.cameras[SERIAL].T_stream_depth("color")
        assert np.allclose(fs.T_color_depth, T_color_depth, atol=1e-7)
        assert np.allclose(fs.T_depth_color, np.linalg.inv(T_color_depth), atol=1e-7)
        assert camera.depth_intrinsics == k
        numbers = [fs.extra["frame_number"]]
        deadline = time.monotonic() + 5.0
        while len(numbers) < 4 and time.monotonic() < deadline:  # live: newer frames keep coming
            number = camera.latest_frameset().extra["frame_number"]
            assert number >= numbers[-1]
            if number > numbers[-1]:
                numbers.append(number)
            time.sleep(0.01)
        assert len(numbers) == 4


def test_global_time_is_switched_on_for_the_streaming_device(fake_rs):
    fake_rs.add_camera(SERIAL, global_time_default=False)  # a camera whose sensors start in hardware clock
    with RealSenseCamera(SERIAL, SMALL) as camera:
        fs = camera.latest_frameset()
        assert fs.extra["timestamp_domain"] == "global_time"
        assert abs(fs.timestamp_s - time.time()) < 1.0


def record(camera: RealSenseCamera, path, seconds: float = 0.6):
    t0 = time.time()
    written = camera.start_recording(path)
    assert camera.recording and camera.recording_path == written
    time.sleep(seconds)
    live = camera.latest_frameset()  # frames keep flowing to the caller while recording
    finished = camera.stop_recording()
    return written, finished, live, t0, time.time()


def check_recording(path, fake, t0: float, t1: float, imu: bool = True, early_frames: int = 0) -> None:
    """``early_frames``: how many frames per stream may precede the switch to global time (see below)."""
    with open_recording(path) as rec:
        assert rec.device.serial == SERIAL
        assert rec.depth_scale == pytest.approx(0.001)
        assert {"depth", "color", "ir1", "ir2"} <= set(rec.streams)
        assert ({"accel", "gyro"} <= set(rec.streams)) == imu
        infos = rec.frame_infos("depth")
        assert len(infos) >= 4
        numbers = [i.frame_number for i in infos]
        assert all(b > a for a, b in pairwise(numbers))
        for key in rec.streams:
            domains = [i.timestamp_domain for i in rec.frame_infos(key)]
            first_global = domains.index("Global Time")
            assert set(domains[first_global:]) == {"Global Time"}, key  # never back to another clock
            assert key in ("accel", "gyro") or first_global <= early_frames, key
        infos = [i for i in infos if i.timestamp_domain == "Global Time"]
        stamps_s = np.array([i.timestamp_ms for i in infos]) / 1e3
        assert np.all((stamps_s > t0 - 0.1) & (stamps_s < t1 + 0.1))  # host clock, during the recording
        frame = rec.read_frame("depth", 1)
        assert np.allclose(frame.data * rec.depth_scale, expected_depth_m(fake), atol=1e-6)
        assert rec.stream("depth").intrinsics.fx == pytest.approx(383.5 * 424 / 640, rel=1e-6)


def test_recording_with_a_db3_only_sdk_writes_cam_serial_db3(fake_rs, tmp_path, caplog):
    fake_rs.add_camera(SERIAL)
    with RealSenseCamera(SERIAL, SMALL) as camera, caplog.at_level(logging.WARNING):
        written, finished, live, t0, t1 = record(camera, tmp_path / "survey" / f"cam{SERIAL}.bag")
        assert live.extra["timestamp_domain"] == "global_time"
    assert written == finished == tmp_path / "survey" / f"cam{SERIAL}.db3"
    assert "records only .db3" in caplog.text and f"cam{SERIAL}.db3 instead of cam{SERIAL}.bag" in caplog.text
    assert not (tmp_path / "survey" / f"cam{SERIAL}.bag").exists()
    check_recording(finished, fake_rs, t0, t1)


def test_a_camera_starting_in_hardware_clock_records_on_the_host_clock(fake_rs, tmp_path):
    # librealsense records from pipeline.start(); darp pauses the recorder right after, switches the
    # streaming sensors to global time and resumes on the first host-clock frame set. Only frames that
    # arrive between start() returning and pause() (none on a real D400, whose first frame takes ~100 ms;
    # possible on this fake under heavy load) keep the device's default domain.
    fake_rs.add_camera(SERIAL, global_time_default=False)
    with RealSenseCamera(SERIAL, SMALL) as camera:
        _, finished, live, t0, t1 = record(camera, tmp_path / f"cam{SERIAL}.bag")
        assert live.extra["timestamp_domain"] == "global_time"
    check_recording(finished, fake_rs, t0, t1, early_frames=2)


def test_recording_with_a_bag_sdk_writes_the_survey_format(fake_rs, tmp_path):
    fake_rs.reset(version="2.57.7")
    fake_rs.add_camera(SERIAL)
    with RealSenseCamera(SERIAL, SMALL) as camera:
        written, finished, _, t0, t1 = record(camera, tmp_path / f"cam{SERIAL}.bag")
        # the device is free again: a second recording starts right away
        again, _, _, _, _ = record(camera, tmp_path / "second" / f"cam{SERIAL}.bag", 0.3)
    assert written == finished == tmp_path / f"cam{SERIAL}.bag"
    assert not (tmp_path / f"cam{SERIAL}.bag.partial").exists()  # the SDK finished the file
    check_recording(finished, fake_rs, t0, t1)
    with open_recording(again) as rec:
        assert rec.frame_count("depth") >= 2


def test_insisting_on_bag_with_a_db3_only_sdk_is_refused_with_the_fix(fake_rs, tmp_path):
    fake_rs.add_camera(SERIAL)
    settings = CameraSettings(width=424, height=240, fps=15, recording_format="bag")
    with RealSenseCamera(SERIAL, settings) as camera:
        with pytest.raises(HardwareError, match=r"pyrealsense2 2\.59\.1 records only ROS2 \.db3.*pyrealsense2<2\.58"):
            camera.start_recording(tmp_path / f"cam{SERIAL}.bag")
        assert not camera.recording and list(tmp_path.iterdir()) == []
        assert camera.latest_frameset().depth_m.shape == (240, 424)  # still streaming live


def test_an_existing_recording_is_never_overwritten(fake_rs, tmp_path):
    fake_rs.add_camera(SERIAL)
    (tmp_path / f"cam{SERIAL}.db3").write_bytes(b"precious")
    with RealSenseCamera(SERIAL, SMALL) as camera, pytest.raises(HardwareError, match="refusing to overwrite"):
        camera.start_recording(tmp_path / f"cam{SERIAL}.bag")
    assert (tmp_path / f"cam{SERIAL}.db3").read_bytes() == b"precious"


def test_a_camera_without_imu_records_without_motion_streams(fake_rs, tmp_path):
    fake_rs.add_camera(SERIAL, imu=False)
    with RealSenseCamera(SERIAL, SMALL) as camera:
        assert camera.imu_rates_hz is None
        _, finished, _, t0, t1 = record(camera, tmp_path / f"cam{SERIAL}.bag", 0.4)
    check_recording(finished, fake_rs, t0, t1, imu=False)
    required = CameraSettings(width=424, height=240, fps=15, imu="on")
    with pytest.raises(HardwareError, match="has no IMU"):
        RealSenseCamera(SERIAL, required).open()


def test_imu_rates_follow_the_device(fake_rs):
    fake_rs.add_camera(SERIAL, accel_rates=(63, 250))  # older firmware: accel 63/250 Hz instead of 100/200
    with RealSenseCamera(SERIAL, SMALL) as camera:
        assert camera.imu_rates_hz == (63, 200)


def test_hardware_problems_are_clear_errors(fake_rs):
    fake_rs.add_camera("405622074504")
    with pytest.raises(HardwareError, match=f"camera {SERIAL} is not connected \\(cameras found: 405622074504\\)"):
        RealSenseCamera(SERIAL).open()
    fake_rs.add_camera(SERIAL)
    odd = CameraSettings(width=500, height=300, fps=30)
    with pytest.raises(HardwareError, match="cannot start 500x300@30 streaming: Couldn't resolve requests"):
        RealSenseCamera(SERIAL, odd).open()
    with RealSenseCamera(SERIAL, SMALL), pytest.raises(HardwareError, match="Device or resource busy"):
        RealSenseCamera(SERIAL, SMALL).open()  # the same camera twice
    assert fake_rs.WORLD.streaming == {}  # nothing left streaming after the failures
