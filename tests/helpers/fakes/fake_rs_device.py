"""The simulated D435(i) behind the fake pyrealsense2: cameras, frames, stream profiles, sensors, devices.

Split from :mod:`helpers.fakes.fake_pyrealsense2` (which re-exports every name here under pyrealsense2's names);
see that module for the contract it enforces.
"""

from __future__ import annotations

import threading
import time
import weakref
from pathlib import Path

import numpy as np
import pyrealsense2 as _rs

from helpers.fakes.fake_rs_recorders import BagRecorder, Db3Recorder

stream, format, option, camera_info = _rs.stream, _rs.format, _rs.option, _rs.camera_info
timestamp_domain, distortion, intrinsics, extrinsics, vector = (
    _rs.timestamp_domain, _rs.distortion, _rs.intrinsics, _rs.extrinsics, _rs.vector)

STEREO_MODES = {(1280, 720): (6, 15, 30), (848, 480): (6, 15, 30, 60, 90), (640, 480): (6, 15, 30, 60, 90),
                (640, 360): (6, 15, 30, 60, 90), (480, 270): (6, 15, 30, 60, 90), (424, 240): (6, 15, 30, 60, 90)}
COLOR_MODES = {(1920, 1080): (6, 15, 30), (1280, 720): (6, 15, 30), (960, 540): (6, 15, 30, 60),
               (848, 480): (6, 15, 30, 60), (640, 480): (6, 15, 30, 60), (640, 360): (6, 15, 30, 60),
               (424, 240): (6, 15, 30, 60), (320, 240): (6, 30, 60), (320, 180): (6, 30, 60)}
COLOR_FORMATS = (format.bgr8, format.rgb8, format.bgra8, format.rgba8, format.yuyv)
GYRO_RATES = (200, 400)
KEYS = {(stream.depth, 0): "depth", (stream.infrared, 1): "ir1", (stream.infrared, 2): "ir2",
        (stream.color, 0): "color", (stream.accel, 0): "accel", (stream.gyro, 0): "gyro"}
SENSOR_OF = {"depth": 0, "ir1": 0, "ir2": 0, "color": 1, "accel": 2, "gyro": 2}
SENSOR_NAMES = ("Stereo Module", "RGB Camera", "Motion Module")
EXPOSURE_LATENCY_MS = 5.0


class _World:
    def __init__(self, version: str = "2.59.1") -> None:
        self.cameras: dict[str, FakeCamera] = {}
        self.streaming: dict[str, object] = {}  # serial -> the pipeline streaming it
        self.violations: list[str] = []
        self.pipelines: list[weakref.ref] = []
        self.version = version


WORLD = _World()


def violation(message: str) -> None:
    WORLD.violations.append(message)
    raise RuntimeError(message)


def _version_tuple() -> tuple[int, int]:
    major, minor = WORLD.version.split(".")[:2]
    return int(major), int(minor)


class FakeCamera:
    """One physical D435(i): identity, calibration, deterministic images."""

    def __init__(self, serial: str, *, imu: bool = True, usb: str = "3.2", global_time_default: bool = True,
                 accel_rates: tuple[int, ...] = (100, 200), depth_scale: float = 0.001) -> None:
        self.serial = serial
        self.name = "Intel RealSense D435I" if imu else "Intel RealSense D435"
        self.product_id = "0B3A" if imu else "0B07"
        self.firmware, self.usb = "5.16.0.1", usb
        self.imu, self.accel_rates = imu, accel_rates
        self.global_time_default = global_time_default
        self.depth_scale = depth_scale
        self.boot = time.monotonic() - 1234.5

    def intrinsics(self, key: str, w: int, h: int) -> dict:
        s = w / 640.0
        if key == "color":
            return {"fx": 610.25 * s, "fy": 609.75 * s, "ppx": w / 2 - 1.3, "ppy": h / 2 + 2.1,
                    "model": distortion.inverse_brown_conrady, "model_name": "Inverse Brown Conrady",
                    "coeffs": [0.0] * 5}
        return {"fx": 383.5 * s, "fy": 383.5 * s, "ppx": (w - 1) / 2 + 0.7, "ppy": (h - 1) / 2 - 1.9,
                "model": distortion.brown_conrady, "model_name": "Brown Conrady", "coeffs": [0.0] * 5}

    def T_stream_depth(self, key: str) -> np.ndarray:
        """Maps points of the depth frame into stream ``key``'s frame."""
        T = np.eye(4)
        if key == "ir2":
            T[0, 3] = -0.0501
        elif key == "color":
            a = 0.004
            T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
            T[:3, 3] = [0.0148, 0.0001, 0.0004]
        elif key in ("accel", "gyro"):
            T[:3, 3] = [-0.0057, -0.0052, -0.0118]
        return T

    def image(self, key: str, w: int, h: int, n: int) -> np.ndarray:
        """Depth: a slanted plane 0.5-0.9 m (raw units) with an invalid band on the left; IR, colour: patterns."""
        yy, xx = np.mgrid[0:h, 0:w]
        if key == "depth":
            raw = (np.round((0.5 + 0.3 * xx / w + 0.1 * yy / h) / self.depth_scale)).astype(np.uint16)
            raw[:, : max(1, w // 32)] = 0
            return raw
        if key in ("ir1", "ir2"):
            return ((xx * 3 + yy * 5 + n * (7 if key == "ir1" else 11)) % 256).astype(np.uint8)
        return np.stack([(xx + n) % 256, (yy * 2) % 256, (xx + yy + 3 * n) % 256], axis=-1).astype(np.uint8)


# -- frames ---------------------------------------------------------------------------------------------
class frame:
    def __init__(self, profile=None, data=None, timestamp_ms: float = 0.0, domain=None, number: int = 0):
        self._profile, self._data = profile, data
        if data is not None:
            data.setflags(write=False)
        self._ts, self._domain, self._number = timestamp_ms, domain, number

    def __bool__(self) -> bool:
        return self._profile is not None

    def _check(self) -> None:
        if self._profile is None:
            raise RuntimeError('null pointer passed for argument "frame_ref"')

    def get_data(self) -> np.ndarray:
        self._check()
        return self._data

    def get_timestamp(self) -> float:
        self._check()
        return self._ts

    def get_frame_timestamp_domain(self):
        self._check()
        return self._domain

    def get_frame_number(self) -> int:
        self._check()
        return self._number

    def get_profile(self):
        self._check()
        return self._profile

    data = property(get_data)
    timestamp = property(get_timestamp)
    frame_number = property(get_frame_number)
    profile = property(get_profile)

    def is_video_frame(self) -> bool:
        return isinstance(self, video_frame)

    def is_depth_frame(self) -> bool:
        return isinstance(self, depth_frame)

    def is_motion_frame(self) -> bool:
        return isinstance(self, motion_frame)

    def is_frameset(self) -> bool:
        return isinstance(self, composite_frame)

    def keep(self) -> None:
        pass


class video_frame(frame):
    def get_width(self) -> int:
        return int(self.get_data().shape[1])

    def get_height(self) -> int:
        return int(self.get_data().shape[0])

    width = property(get_width)
    height = property(get_height)


class depth_frame(video_frame):
    def get_units(self) -> float:
        self._check()
        return self._units

    def get_distance(self, x: int, y: int) -> float:
        return float(self.get_data()[y, x]) * self.get_units()


class motion_frame(frame):
    def get_motion_data(self):
        v = vector()
        v.x, v.y, v.z = (float(c) for c in self.get_data())
        return v


class composite_frame(frame):
    def __init__(self, frames: list[frame]) -> None:
        first = frames[0]
        super().__init__(first._profile, None, first._ts, first._domain, first._number)
        self._frames = frames

    def _find(self, key: str, cls: type) -> frame:
        for f in self._frames:
            if f._profile is not None and f._profile._key == key:
                return f
        return cls()

    def get_depth_frame(self) -> depth_frame:
        return self._find("depth", depth_frame)

    def get_color_frame(self) -> video_frame:
        return self._find("color", video_frame)

    def get_infrared_frame(self, index: int = 0) -> video_frame:
        if not isinstance(index, int):
            raise TypeError("get_infrared_frame(): incompatible function arguments")
        keys = ("ir1", "ir2") if index == 0 else (f"ir{index}",)
        for key in keys:
            f = self._find(key, video_frame)
            if f:
                return f
        return video_frame()

    def size(self) -> int:
        return len(self._frames)

    def __len__(self) -> int:
        return len(self._frames)

    def __iter__(self):
        return iter(self._frames)

    def __getitem__(self, i: int) -> frame:
        return self._frames[i]


# -- profiles, sensors, devices -------------------------------------------------------------------------
class stream_profile:
    def __init__(self, camera: FakeCamera, key: str, fmt, fps: int, width: int = 0, height: int = 0) -> None:
        self._camera, self._key, self._fmt, self._fps = camera, key, fmt, fps
        self._w, self._h = width, height

    def stream_type(self):
        return {"depth": stream.depth, "ir1": stream.infrared, "ir2": stream.infrared, "color": stream.color,
                "accel": stream.accel, "gyro": stream.gyro}[self._key]

    def stream_index(self) -> int:
        return {"ir1": 1, "ir2": 2}.get(self._key, 0)

    def format(self):
        return self._fmt

    def fps(self) -> int:
        return self._fps

    def unique_id(self) -> int:
        return list(KEYS.values()).index(self._key)

    def stream_name(self) -> str:
        return {"depth": "Depth", "ir1": "Infrared 1", "ir2": "Infrared 2", "color": "Color", "accel": "Accel",
                "gyro": "Gyro"}[self._key]

    def is_video_stream_profile(self) -> bool:
        return self._key not in ("accel", "gyro")

    def is_motion_stream_profile(self) -> bool:
        return not self.is_video_stream_profile()

    def as_video_stream_profile(self) -> video_stream_profile:
        if not self.is_video_stream_profile():
            raise RuntimeError("Object does not support \"librealsense::video_stream_profile_interface\"")
        return video_stream_profile(self._camera, self._key, self._fmt, self._fps, self._w, self._h)

    def get_extrinsics_to(self, to: stream_profile):
        T = self._camera.T_stream_depth(to._key) @ np.linalg.inv(self._camera.T_stream_depth(self._key))
        e = extrinsics()
        e.rotation = [float(v) for v in T[:3, :3].T.reshape(-1)]  # column-major, as librealsense
        e.translation = [float(v) for v in T[:3, 3]]
        return e

    def __eq__(self, other: object) -> bool:
        return isinstance(other, stream_profile) and (self._key, self._fmt, self._fps, self._w, self._h) == (
            other._key, other._fmt, other._fps, other._w, other._h)

    __hash__ = None


class video_stream_profile(stream_profile):
    def width(self) -> int:
        return self._w

    def height(self) -> int:
        return self._h

    def get_intrinsics(self):
        k = self._camera.intrinsics(self._key, self._w, self._h)
        out = intrinsics()
        out.width, out.height, out.fx, out.fy, out.ppx, out.ppy = self._w, self._h, k["fx"], k["fy"], k["ppx"], k["ppy"]
        out.model, out.coeffs = k["model"], list(k["coeffs"])
        return out


class sensor:
    def __init__(self, camera: FakeCamera, index: int) -> None:
        self._camera, self._index = camera, index
        self._options = {option.global_time_enabled: 1.0 if camera.global_time_default else 0.0}
        if index == 0:
            self._options[option.depth_units] = camera.depth_scale
        self._read_only = {option.depth_units}

    @property
    def name(self) -> str:
        return SENSOR_NAMES[self._index]

    def get_info(self, info):
        if info == camera_info.name:
            return self.name
        raise RuntimeError(f"object doesn't support {info}")

    def supports(self, what) -> bool:
        if isinstance(what, option):
            return what in self._options
        return what == camera_info.name

    def get_option(self, opt) -> float:
        if opt not in self._options:
            raise RuntimeError(f"object doesn't support option #{int(opt)}")
        return self._options[opt]

    def set_option(self, opt, value) -> None:
        if not isinstance(opt, option) or isinstance(value, str) or not isinstance(value, (int, float)):
            raise TypeError("set_option(): incompatible function arguments")
        if opt not in self._options:
            raise RuntimeError(f"object doesn't support option #{int(opt)}")
        if opt in self._read_only:
            raise RuntimeError(f"option {opt} is read-only")
        if opt == option.global_time_enabled and value not in (0, 1):
            raise RuntimeError(f"set_option: value {value} out of range [0, 1] for {opt}")
        self._options[opt] = float(value)

    def get_stream_profiles(self) -> list[stream_profile]:
        cam, out = self._camera, []
        if self._index == 0:
            for (w, h), rates in STEREO_MODES.items():
                for fps in rates:
                    out.append(video_stream_profile(cam, "depth", format.z16, fps, w, h))
                    out += [video_stream_profile(cam, k, format.y8, fps, w, h) for k in ("ir1", "ir2")]
        elif self._index == 1:
            for (w, h), rates in COLOR_MODES.items():
                out += [video_stream_profile(cam, "color", f, fps, w, h) for fps in rates for f in COLOR_FORMATS]
        else:
            out += [stream_profile(cam, "accel", format.motion_xyz32f, r) for r in cam.accel_rates]
            out += [stream_profile(cam, "gyro", format.motion_xyz32f, r) for r in GYRO_RATES]
        return out

    profiles = property(get_stream_profiles)

    def is_depth_sensor(self) -> bool:
        return self._index == 0

    def is_color_sensor(self) -> bool:
        return self._index == 1

    def is_motion_sensor(self) -> bool:
        return self._index == 2

    def as_depth_sensor(self) -> depth_sensor:
        if not self.is_depth_sensor():
            raise RuntimeError("Object does not support \"librealsense::depth_sensor\"")
        return self


class depth_sensor(sensor):
    def get_depth_scale(self) -> float:
        return float(self._options[option.depth_units])


class device:
    def __init__(self, camera: FakeCamera) -> None:
        self._camera = camera
        self._sensors = [depth_sensor(camera, 0), sensor(camera, 1)] + ([sensor(camera, 2)] if camera.imu else [])

    def _infos(self) -> dict:
        c = self._camera
        return {camera_info.name: c.name, camera_info.serial_number: c.serial, camera_info.firmware_version: c.firmware,
                camera_info.product_id: c.product_id, camera_info.product_line: "D400",
                camera_info.usb_type_descriptor: c.usb}

    def get_info(self, info):
        if not isinstance(info, camera_info):
            raise TypeError("get_info(): incompatible function arguments")
        if info not in self._infos():
            raise RuntimeError(f"Device does not support {info}")
        return self._infos()[info]

    def supports(self, info) -> bool:
        return info in self._infos()

    def query_sensors(self) -> list[sensor]:
        return list(self._sensors)

    sensors = property(query_sensors)

    def first_depth_sensor(self) -> depth_sensor:
        return self._sensors[0]

    def first_color_sensor(self) -> sensor:
        return self._sensors[1]

    def first_motion_sensor(self) -> sensor:
        if len(self._sensors) < 3:
            raise RuntimeError("Could not find requested sensor type!")
        return self._sensors[2]

    def is_recorder(self) -> bool:
        return isinstance(self, recorder)

    def as_recorder(self) -> recorder:
        if not self.is_recorder():
            raise RuntimeError("Object does not support \"librealsense::record_device\"")
        return self


class recorder(device):
    """The recording device a pipeline creates for ``enable_record_to_file``; the file closes when it dies."""

    def __init__(self, camera: FakeCamera, path: Path, profiles: dict) -> None:
        super().__init__(camera)
        if _version_tuple() >= (2, 58):
            if path.suffix != ".db3":
                raise RuntimeError("Output file must have .db3 extension")
            writer = Db3Recorder(path, camera, profiles, _rs)
        else:
            if path.suffix != ".bag":
                raise RuntimeError(f"fake pyrealsense2 {WORLD.version}: librealsense <= 2.57 writes ROS1 bags (.bag)")
            writer = BagRecorder(path, camera, profiles)
        self._writer, self._paused, self._start_ns = writer, False, time.monotonic_ns()
        self._lock = threading.Lock()
        weakref.finalize(self, writer.close)

    def pause(self) -> None:
        self._paused = True

    def resume(self) -> None:
        self._paused = False

    def _write(self, key: str, data: np.ndarray, ts_ms: float, number: int, domain) -> None:
        if self._paused:
            return
        name = str(domain).split(".")[-1]
        with self._lock:
            self._writer.write(key, data, ts_ms, number, name, time.monotonic_ns() - self._start_ns + 1_000_000)


class device_list(list):
    pass


class context:
    def query_devices(self) -> device_list:
        return device_list(device(camera) for camera in WORLD.cameras.values())

    devices = property(query_devices)

    def query_all_sensors(self) -> list[sensor]:
        return [s for d in self.query_devices() for s in d.query_sensors()]
