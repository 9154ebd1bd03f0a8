"""What the fake pyrealsense2 records with: the container the real SDK version would write.

- pyrealsense2 <= 2.57 semantics: a ROS1 ``.bag`` in librealsense's layout, written by darp's own
  :class:`~darp.formats.realsense.bag.writer.BagWriter` (itself checked against pyrealsense2 playback elsewhere).
- pyrealsense2 >= 2.58 semantics: a genuine ROS2 ``.db3`` written by the *real* librealsense recorder
  (``rs.recorder`` over an ``rs.software_device`` that replays the fake camera's frames), so the file is
  exactly what the SDK writes.

Both take frames as the fake device produces them and are finished by :meth:`close`, which the fake
calls when the recording device object is garbage collected (as librealsense closes the file when the
last reference to the recorder goes away).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile

# darp stream key -> (librealsense stream name, index, sensor index, format, bytes per pixel)
STREAMS = {"depth": ("Depth", 0, 0, "z16", 2), "ir1": ("Infrared", 1, 0, "y8", 1), "ir2": ("Infrared", 2, 0, "y8", 1),
           "color": ("Color", 0, 1, "bgr8", 3), "accel": ("Accel", 0, 2, "motion_xyz32f", 0),
           "gyro": ("Gyro", 0, 2, "motion_xyz32f", 0)}
DOMAIN_NAMES = {"hardware_clock": "Hardware Clock", "system_time": "System Time", "global_time": "Global Time"}


class BagRecorder:
    """ROS1 bag, as pyrealsense2 <= 2.57 records."""

    def __init__(self, path: Path, camera, profiles: dict) -> None:
        streams = []
        for key, p in profiles.items():
            name, index, sensor, fmt, _ = STREAMS[key]
            if key in ("accel", "gyro"):
                streams.append(StreamProfile(key, name, index, sensor, fmt, p["fps"]))
            else:
                k = camera.intrinsics(key, p["width"], p["height"])
                streams.append(StreamProfile(key, name, index, sensor, fmt, p["fps"], p["width"], p["height"],
                                             Intrinsics(p["width"], p["height"], k["fx"], k["fy"], k["ppx"],
                                                        k["ppy"], k["model_name"], tuple(k["coeffs"]))))
        extrinsics = {key: camera.T_stream_depth(key) for key in profiles if key != "depth"}
        device = DeviceInfo(camera.name, camera.serial, camera.firmware, camera.product_id)
        self._writer = BagWriter(path, device, streams, depth_scale=camera.depth_scale,
                                 extrinsics=extrinsics if "depth" in profiles else None, overwrite=True,
                                 start_ms=0.0)

    def write(self, key: str, data: np.ndarray, timestamp_ms: float, number: int, domain: str,
              recording_ns: int) -> None:
        domain = DOMAIN_NAMES[domain]
        if key in ("accel", "gyro"):
            self._writer.write_motion(key, data, timestamp_ms, number, timestamp_domain=domain,
                                      recording_time_ns=recording_ns)
        else:
            self._writer.write_image(key, data, timestamp_ms, number, timestamp_domain=domain,
                                     recording_time_ns=recording_ns)

    def close(self) -> None:
        self._writer.close()


class Db3Recorder:
    """ROS2 .db3 written by the real librealsense recorder, as pyrealsense2 >= 2.58 records."""

    def __init__(self, path: Path, camera, profiles: dict, rs) -> None:
        self._rs = rs
        self._depth_scale = camera.depth_scale
        dev = rs.software_device()
        for info, value in ((rs.camera_info.name, camera.name), (rs.camera_info.serial_number, camera.serial),
                            (rs.camera_info.firmware_version, camera.firmware),
                            (rs.camera_info.product_id, camera.product_id)):
            dev.register_info(info, value)
        self._sensors = {name: dev.add_sensor(name) for name in ("Stereo Module", "RGB Camera", "Motion Module")}
        sensor_of = {0: "Stereo Module", 1: "RGB Camera", 2: "Motion Module"}
        self._profiles = {}
        for uid, (key, p) in enumerate(profiles.items()):
            name, index, sensor_index, fmt, bpp = STREAMS[key]
            sensor = self._sensors[sensor_of[sensor_index]]
            stream_type = getattr(rs.stream, name.lower())
            if key in ("accel", "gyro"):
                ms = rs.motion_stream()
                ms.type, ms.index, ms.uid, ms.fps, ms.fmt = stream_type, 0, uid, p["fps"], rs.format.motion_xyz32f
                mi = rs.motion_device_intrinsic()
                mi.data = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
                mi.noise_variances, mi.bias_variances = [0.0] * 3, [0.0] * 3
                ms.intrinsics = mi
                self._profiles[key] = sensor.add_motion_stream(ms, True)
                continue
            k = camera.intrinsics(key, p["width"], p["height"])
            intr = rs.intrinsics()
            intr.width, intr.height, intr.fx, intr.fy = p["width"], p["height"], k["fx"], k["fy"]
            intr.ppx, intr.ppy, intr.model, intr.coeffs = k["ppx"], k["ppy"], k["model"], list(k["coeffs"])
            vs = rs.video_stream()
            vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp = (
                stream_type, index, uid, p["width"], p["height"], p["fps"], bpp)
            vs.fmt = getattr(rs.format, fmt)
            vs.intrinsics = intr
            self._profiles[key] = sensor.add_video_stream(vs, True)
        self._sensors["Stereo Module"].add_read_only_option(rs.option.depth_units, camera.depth_scale)
        if "depth" in self._profiles:
            for key, profile in self._profiles.items():
                if key != "depth":
                    T = camera.T_stream_depth(key)  # maps depth points into this stream
                    e = rs.extrinsics()
                    e.rotation = [float(v) for v in T[:3, :3].T.reshape(-1)]  # librealsense: column-major
                    e.translation = [float(v) for v in T[:3, 3]]
                    self._profiles["depth"].register_extrinsics_to(profile, e)
        self._recorder = rs.recorder(str(path), dev, True)
        self._device = dev
        self._open = []
        for name, sensor in self._sensors.items():
            mine = [prof for key, prof in self._profiles.items() if sensor_of[STREAMS[key][2]] == name]
            if mine:
                sensor.open(mine)
                sensor.start(lambda frame: None)
                self._open.append(sensor)
        self._keep_alive: list[np.ndarray] = []  # librealsense reads pixel buffers after on_video_frame returns

    def write(self, key: str, data: np.ndarray, timestamp_ms: float, number: int, domain: str,
              recording_ns: int) -> None:
        rs = self._rs
        domain_value = getattr(rs.timestamp_domain, domain)
        sensor = self._sensors[{0: "Stereo Module", 1: "RGB Camera", 2: "Motion Module"}[STREAMS[key][2]]]
        if key in ("accel", "gyro"):
            frame = rs.software_motion_frame()
            sample = rs.vector()
            sample.x, sample.y, sample.z = (float(v) for v in data)
            frame.data = sample
            frame.timestamp, frame.domain, frame.frame_number = timestamp_ms, domain_value, int(number)
            frame.profile = self._profiles[key].as_motion_stream_profile()
            sensor.on_motion_frame(frame)
            return
        pixels = np.ascontiguousarray(data)
        self._keep_alive.append(pixels)
        bpp = STREAMS[key][4]
        frame = rs.software_video_frame()
        frame.pixels, frame.bpp, frame.stride = pixels, bpp, bpp * pixels.shape[1]
        frame.timestamp, frame.domain, frame.frame_number = timestamp_ms, domain_value, int(number)
        frame.profile = self._profiles[key].as_video_stream_profile()
        if key == "depth":
            frame.depth_units = self._depth_scale
        sensor.on_video_frame(frame)

    def close(self) -> None:
        for sensor in self._open:
            sensor.stop()
        for sensor in self._open:
            sensor.close()
        self._open = []
        self._recorder = None  # the file is finished when the recorder goes away
        self._device = None
        self._profiles = {}
        self._sensors = {}
        self._keep_alive = []
