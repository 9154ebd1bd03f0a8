"""A contract-enforcing stand-in for ``pyrealsense2`` with simulated D435(i) cameras.

Enums and value types (``stream``, ``format``, ``option``, ``camera_info``, ``timestamp_domain``,
``distortion``, ``intrinsics``, ``extrinsics``, ``vector``) *are* the real pyrealsense2's, so names and
values cannot drift; only the hardware-facing classes are simulated, with the real names and call
rules (``tests/test_hardware_fakes.py`` checks every public name against the real module):

- ``config.enable_stream`` takes the real overloads (ints must be ints); ``pipeline.start`` resolves the
  requests against the D435's modes (depth/IR share one resolution and rate; facts/d400-sensor.md) and
  fails like librealsense ("Couldn't resolve requests"), refuses a camera already streaming ("Device or
  resource busy") and, with two cameras plugged in, a config without ``enable_device`` (the SDK would
  pick one arbitrarily: a contract violation).
- Frames arrive at the configured rate in wall time with increasing frame numbers. The timestamp domain
  follows each streaming sensor's ``global_time_enabled`` option: global time (host clock, ms) when on,
  hardware clock when off. Options set on a device from ``context.query_devices()`` do not reach a
  pipeline's device (librealsense issue #7614): they must be set on ``profile.get_device()``.
- ``enable_record_to_file``: version >= 2.58 accepts only ``.db3`` ("Output file must have .db3
  extension") and writes a genuine file through the real librealsense recorder; <= 2.57 writes a ROS1
  ``.bag``. As in librealsense, the file is finished only when the recording device is released
  (pipeline stopped *and* no ``pipeline_profile``/``device`` reference kept).
"""
from __future__ import annotations

import collections
import threading
import time
import weakref
from pathlib import Path

import numpy as np
import pyrealsense2 as _rs

from helpers.fakes import fake_rs_device as _dev

# pyrealsense2's hardware-facing classes, simulated (fake_rs_device), under their real names
(frame, video_frame, depth_frame, motion_frame, composite_frame, stream_profile, video_stream_profile, sensor,
 depth_sensor, device, recorder, device_list, context) = (
    _dev.frame, _dev.video_frame, _dev.depth_frame, _dev.motion_frame, _dev.composite_frame, _dev.stream_profile,
    _dev.video_stream_profile, _dev.sensor, _dev.depth_sensor, _dev.device, _dev.recorder, _dev.device_list,
    _dev.context)
WORLD, FakeCamera, violation = _dev.WORLD, _dev.FakeCamera, _dev.violation
KEYS, SENSOR_OF, EXPOSURE_LATENCY_MS = _dev.KEYS, _dev.SENSOR_OF, _dev.EXPOSURE_LATENCY_MS

stream, format, option, camera_info = _rs.stream, _rs.format, _rs.option, _rs.camera_info
timestamp_domain, distortion, intrinsics, extrinsics, vector = (
    _rs.timestamp_domain, _rs.distortion, _rs.intrinsics, _rs.extrinsics, _rs.vector)
__version__ = "2.59.1"


def reset(version: str = "2.59.1") -> None:
    """Unplug every camera, stop every pipeline, forget violations; set the SDK version to simulate."""
    global __version__
    for ref in WORLD.pipelines:
        pipe = ref()
        if pipe is not None and pipe._started:
            pipe.stop()
    WORLD.__init__(version)
    __version__ = version


def add_camera(serial: str, **kwargs) -> FakeCamera:
    """Plug in a simulated camera."""
    camera = FakeCamera(serial, **kwargs)
    WORLD.cameras[serial] = camera
    return camera


# -- config and pipeline ----------------------------------------------------------------------------------
class config:
    def __init__(self) -> None:
        self._serial: str | None = None
        self._requests: dict[tuple, tuple] = {}
        self._record: str | None = None

    def enable_device(self, serial) -> None:
        if not isinstance(serial, str):
            raise TypeError("enable_device(): incompatible function arguments (serial: str)")
        self._serial = serial

    def enable_stream(self, *args) -> None:
        kinds = [type(a) for a in args]
        if not args or not isinstance(args[0], stream):
            raise TypeError("enable_stream(): incompatible function arguments")
        def ints(xs):
            return all(isinstance(x, int) and not isinstance(x, bool) for x in xs)
        st, rest = args[0], args[1:]
        if len(rest) == 0:
            idx, w, h, fmt, fps = -1, 0, 0, None, 0
        elif len(rest) == 1 and ints(rest):
            idx, w, h, fmt, fps = rest[0], 0, 0, None, 0
        elif len(rest) == 2 and isinstance(rest[0], format) and ints(rest[1:]):
            idx, w, h, fmt, fps = -1, 0, 0, rest[0], rest[1]
        elif len(rest) == 3 and ints(rest[:1]) and isinstance(rest[1], format) and ints(rest[2:]):
            idx, w, h, fmt, fps = rest[0], 0, 0, rest[1], rest[2]
        elif len(rest) == 4 and ints(rest[:2]) and isinstance(rest[2], format) and ints(rest[3:]):
            idx, w, h, fmt, fps = -1, rest[0], rest[1], rest[2], rest[3]
        elif len(rest) == 5 and ints(rest[:3]) and isinstance(rest[3], format) and ints(rest[4:]):
            idx, w, h, fmt, fps = rest
        else:
            raise TypeError(f"enable_stream(): incompatible function arguments: {[k.__name__ for k in kinds]}")
        self._requests[(st, idx)] = (w, h, fmt, fps)

    def disable_all_streams(self) -> None:
        self._requests.clear()

    def enable_record_to_file(self, file_name) -> None:
        if not isinstance(file_name, str):
            raise TypeError("enable_record_to_file(): incompatible function arguments (file_name: str)")
        self._record = file_name

    def _resolve(self) -> tuple[FakeCamera, dict]:
        if self._serial is None and len(WORLD.cameras) > 1:
            violation("pipeline started without config.enable_device() while several cameras are connected: "
                      "librealsense picks one arbitrarily")
        serial = self._serial or next(iter(WORLD.cameras), None)
        camera = WORLD.cameras.get(serial) if serial else None
        if camera is None:
            raise RuntimeError("No device connected" if not WORLD.cameras else "Couldn't resolve requests")
        chosen: dict[str, dict] = {}
        for (st, idx), (w, h, fmt, fps) in self._requests.items():
            indices = [idx] if idx >= 0 else ([1] if st == stream.infrared else [0])
            key = KEYS.get((st, indices[0]))
            if key is None:
                raise RuntimeError("Couldn't resolve requests")
            chosen[key] = {"width": w, "height": h, "format": fmt, "fps": fps}
        if not chosen:
            chosen = {"depth": {"width": 0, "height": 0, "format": None, "fps": 0}}
        for key, req in chosen.items():
            sensor_profiles = device(camera).query_sensors()
            matches = [p for s in sensor_profiles for p in s.get_stream_profiles() if p._key == key
                       and (req["format"] is None or p.format() == req["format"])
                       and (req["fps"] == 0 or p.fps() == req["fps"])
                       and (req["width"] == 0 or p._w == req["width"])
                       and (req["height"] == 0 or p._h == req["height"])]
            if not matches:
                raise RuntimeError("Couldn't resolve requests")
            prefer = [p for p in matches if (p._w, p._h, p.fps()) == (640, 480, 30)] or matches
            p = prefer[0]
            chosen[key] = {"width": p._w, "height": p._h, "format": p.format(), "fps": p.fps()}
        stereo = {(v["width"], v["height"], v["fps"]) for k, v in chosen.items() if SENSOR_OF[k] == 0}
        motion = {v["fps"] for k, v in chosen.items() if k in ("accel", "gyro")}
        if len(stereo) > 1:
            raise RuntimeError("Couldn't resolve requests")  # one sensor streams one resolution and rate
        del motion
        return camera, chosen

    def resolve(self, p: pipeline) -> pipeline_profile:
        camera, chosen = self._resolve()
        return pipeline_profile(device(camera), camera, chosen)

    def can_resolve(self, p: pipeline) -> bool:
        try:
            self._resolve()
        except RuntimeError:
            return False
        return True


class pipeline_profile:
    def __init__(self, dev: device, camera: FakeCamera, chosen: dict) -> None:
        self._device, self._camera, self._chosen = dev, camera, chosen

    def get_device(self) -> device:
        return self._device

    def get_streams(self) -> list[stream_profile]:
        return [self._profile(k) for k in self._chosen]

    def _profile(self, key: str) -> stream_profile:
        c = self._chosen[key]
        cls = stream_profile if key in ("accel", "gyro") else video_stream_profile
        return cls(self._camera, key, c["format"], c["fps"], c["width"], c["height"])

    def get_stream(self, stream_type, stream_index: int = -1) -> stream_profile:
        for key in self._chosen:
            p = self._profile(key)
            if p.stream_type() == stream_type and stream_index in (-1, p.stream_index()):
                return p
        raise RuntimeError(f"Profile not found for {stream_type} index {stream_index}")


class pipeline:
    def __init__(self, ctx: context | None = None) -> None:
        if ctx is not None and not isinstance(ctx, context):
            raise TypeError("pipeline(): incompatible constructor arguments")
        self._started = False
        self._queue: collections.deque = collections.deque(maxlen=16)
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._profile: pipeline_profile | None = None
        self._device: device | None = None
        WORLD.pipelines.append(weakref.ref(self))

    def start(self, config_: config | None = None) -> pipeline_profile:
        if not isinstance(config_, config):
            raise TypeError("fake pipeline.start() takes a config (callbacks and queues are not simulated)")
        if self._started:
            raise RuntimeError("start() cannot be called before stop()")
        camera, chosen = config_._resolve()
        if camera.serial in WORLD.streaming:
            raise RuntimeError("xioctl(VIDIOC_S_FMT) failed, errno=16 Last Error: Device or resource busy")
        if config_._record is not None:
            path = Path(config_._record)
            if not path.parent.is_dir():
                raise RuntimeError(f"Failed to create file {path}: no such directory")
            dev: device = recorder(camera, path, chosen)
        else:
            dev = device(camera)
        self._device = dev
        self._profile = pipeline_profile(dev, camera, chosen)
        WORLD.streaming[camera.serial] = self
        self._started = True
        self._stop.clear()
        self._queue.clear()
        self._thread = threading.Thread(target=self._produce, args=(camera, chosen), daemon=True,
                                        name=f"fake-rs-{camera.serial}")
        self._thread.start()
        return self._profile

    def stop(self) -> None:
        if not self._started:
            raise RuntimeError("stop() cannot be called before start()")
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._thread = None
        WORLD.streaming.pop(self._profile._camera.serial, None)
        self._started = False
        self._profile = self._device = None
        self._queue.clear()

    def get_active_profile(self) -> pipeline_profile:
        if not self._started:
            raise RuntimeError("get_active_profile() can only be called between a start() and a following stop()")
        return self._profile

    def _produce(self, camera: FakeCamera, chosen: dict) -> None:
        dev = self._device
        stereo_sensor, color_sensor = dev._sensors[0], dev._sensors[1]
        motion_sensor = dev._sensors[2] if len(dev._sensors) > 2 else None
        video = {k: v for k, v in chosen.items() if k in ("depth", "ir1", "ir2", "color")}
        motion = {k: v for k, v in chosen.items() if k in ("accel", "gyro")}
        fps = max(v["fps"] for v in video.values()) if video else 100
        counters = dict.fromkeys(chosen, 0)
        next_due = {k: time.monotonic() for k in chosen}
        latest_color = None
        while not self._stop.is_set():
            now = time.monotonic()
            frames = []
            for key, req in video.items():
                if now + 1e-4 < next_due[key]:
                    continue
                next_due[key] += 1.0 / req["fps"]
                counters[key] += 1
                s = stereo_sensor if SENSOR_OF[key] == 0 else color_sensor
                ts, domain = self._stamp(camera, s, EXPOSURE_LATENCY_MS)
                data = camera.image(key, req["width"], req["height"], counters[key])
                profile = video_stream_profile(camera, key, req["format"], req["fps"], req["width"], req["height"])
                f = (depth_frame if key == "depth" else video_frame)(profile, data, ts, domain, counters[key])
                if key == "depth":
                    f._units = camera.depth_scale
                if key == "color":
                    latest_color = f
                frames.append(f)
                if isinstance(dev, recorder):
                    dev._write(key, data, ts, counters[key], domain)
            if frames:
                if latest_color is not None and latest_color not in frames:
                    frames.append(latest_color)
                self._push(composite_frame(frames))
            for key, req in motion.items():
                while next_due[key] <= now:
                    next_due[key] += 1.0 / req["fps"]
                    counters[key] += 1
                    ts, domain = self._stamp(camera, motion_sensor, 0.0)
                    data = np.array([0.01, -9.81, 0.05], dtype=np.float32) if key == "accel" else np.array(
                        [0.001, -0.002, 0.0005], dtype=np.float32)
                    profile = stream_profile(camera, key, req["format"], req["fps"])
                    self._push(composite_frame([motion_frame(profile, data, ts, domain, counters[key])]))
                    if isinstance(dev, recorder):
                        dev._write(key, data, ts, counters[key], domain)
            wake = min(next_due.values())
            self._stop.wait(max(0.0, min(wake - time.monotonic(), 1.0 / fps)))

    @staticmethod
    def _stamp(camera: FakeCamera, s: sensor, latency_ms: float) -> tuple[float, object]:
        if s.get_option(option.global_time_enabled) >= 0.5:
            return time.time() * 1e3 - latency_ms, timestamp_domain.global_time
        return (time.monotonic() - camera.boot) * 1e3 - latency_ms, timestamp_domain.hardware_clock

    def _push(self, fs: composite_frame) -> None:
        with self._cond:
            self._queue.append(fs)
            self._cond.notify_all()

    def _check_started(self, what: str) -> None:
        if not self._started:
            raise RuntimeError(f"{what} cannot be called before start()")

    def try_wait_for_frames(self, timeout_ms: int = 5000) -> tuple[bool, composite_frame]:
        self._check_started("try_wait_for_frames")
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._queue) or not self._started, timeout_ms / 1e3):
                return False, composite_frame([frame()])
            if not self._queue:
                return False, composite_frame([frame()])
            return True, self._queue.popleft()

    def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
        ok, fs = self.try_wait_for_frames(timeout_ms)
        if not ok:
            raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
        return fs

    def poll_for_frames(self) -> composite_frame:
        self._check_started("poll_for_frames")
        with self._cond:
            return self._queue.popleft() if self._queue else composite_frame([frame()])
