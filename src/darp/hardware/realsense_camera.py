"""``RealSenseCamera``: one wrist RealSense D400 through pyrealsense2 as a :class:`CameraBackend`.

Streams (configurable, default 640x480 at 30 fps): depth Z16, infrared 1 and 2 Y8, colour BGR8, and the
IMU (accel + gyro at the device's lowest rates) when the camera has one. One ``rs.pipeline`` per camera,
bound to its serial with ``config.enable_device``.

Time: ``global_time_enabled`` is switched on for every sensor of the *streaming* device after
``pipeline.start`` (set before, on a device from the context, it does not reach the pipeline:
librealsense issue #7614), so frame timestamps are host-clock milliseconds ("Global Time"). Start-up
waits for a frame set in the global (or, without kernel metadata, system) time domain within
``max_clock_offset_s`` of ``time.time()`` and refuses otherwise.

Recording: ``start_recording(path)`` restarts the pipeline with ``config.enable_record_to_file``; the
recorder is paused until the first host-clock frame set has arrived, so a recording never begins with
hardware-clock frames. The container is the SDK's: pyrealsense2 <= 2.57 writes ROS1 ``.bag`` (the
survey format, ``cam<serial>.bag``); pyrealsense2 >= 2.58 can only write ROS2 ``.db3``, so with the
default ``recording_format: auto`` the camera records ``cam<serial>.db3`` (same name, ``.db3`` suffix;
darp reads both and the survey reader accepts both) and says so in the log; ``recording_format: bag``
refuses instead, telling to install pyrealsense2 < 2.58. :meth:`start_recording` returns the path
actually written. librealsense finishes the file when the recording device is released, so
:meth:`stop_recording` stops the pipeline and keeps no reference to its profile, device or frames.
While recording, frame sets keep arriving for :meth:`latest_frameset`; after it, the live pipeline
restarts lazily on the next call.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Self

import numpy as np

from darp.backend import CameraBackend, LiveFrameSet
from darp.errors import ConfigError, HardwareError
from darp.formats.realsense.types import Intrinsics
from darp.hardware import sdk as sdk_loader

log = logging.getLogger(__name__)

DISTORTION_NAMES = {"none": "None", "brown_conrady": "Brown Conrady", "inverse_brown_conrady": "Inverse Brown Conrady",
                    "modified_brown_conrady": "Modified Brown Conrady", "ftheta": "Ftheta",
                    "kannala_brandt4": "Kannala Brandt4"}
HOST_DOMAINS = ("global_time", "system_time")
IMU_MODES = ("auto", "on", "off")


@dataclass(frozen=True)
class CameraSettings:
    """Stream setup and health limits of a wrist camera."""

    width: int = 640
    height: int = 480
    fps: int = 30
    color: bool = True
    infrared: bool = True
    imu: str = "auto"  # auto: record the IMU when the camera has one; on: require it; off
    recording_format: str = "auto"  # auto (the SDK's container), bag or db3: sdk.recording_suffix
    start_timeout_s: float = 10.0  # first host-clock frame set after a (re)start
    stale_after_s: float = 2.0  # latest_frameset refuses frames older than this (camera stalled?)
    max_clock_offset_s: float = 1.0  # frame timestamps must be this close to time.time()

    def __post_init__(self) -> None:
        for name in ("width", "height", "fps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise ConfigError(f"cameras.{name}: must be a positive integer, got {value!r}")
        if self.imu not in IMU_MODES:
            raise ConfigError(f"cameras.imu: must be one of {', '.join(IMU_MODES)}, got {self.imu!r}")
        if self.recording_format not in sdk_loader.RECORDING_FORMATS:
            raise ConfigError(f"cameras.recording_format: must be one of {', '.join(sdk_loader.RECORDING_FORMATS)}, "
                              f"got {self.recording_format!r}")
        for name in ("start_timeout_s", "stale_after_s", "max_clock_offset_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"cameras.{name}: must be positive, got {getattr(self, name)!r}")


DEVICE_INFO_KEYS = ("name", "serial_number", "firmware_version", "usb_type_descriptor")

# pyrealsense2 has no type information: its objects (devices, frames, profiles, enums) are ``Any`` here.
VideoStream = tuple[Any, int, Any, int, int, int]
"""A video stream as pyrealsense2 names it: (stream, index, format, width, height, fps)."""


def video_streams(rs: ModuleType, s: CameraSettings) -> dict[str, VideoStream]:
    """The video streams darp records with settings ``s``: ``label -> (stream, index, format, width,
    height, fps)``; index -1 is "the sensor's only one" (depth, colour), as ``config.enable_stream`` takes it.
    One list for recording and for ``darp hardware check``, so the check asks for what a survey will."""
    wanted: dict[str, VideoStream] = {"depth z16": (rs.stream.depth, -1, rs.format.z16, s.width, s.height, s.fps)}
    if s.infrared:
        wanted["IR1 y8"] = (rs.stream.infrared, 1, rs.format.y8, s.width, s.height, s.fps)
        wanted["IR2 y8"] = (rs.stream.infrared, 2, rs.format.y8, s.width, s.height, s.fps)
    if s.color:
        wanted["colour bgr8"] = (rs.stream.color, -1, rs.format.bgr8, s.width, s.height, s.fps)
    return wanted


def device_info(rs: ModuleType, dev: Any) -> dict[str, str]:
    """The device's ``DEVICE_INFO_KEYS`` that it reports (camera_info name -> value)."""
    return {key: dev.get_info(getattr(rs.camera_info, key)) for key in DEVICE_INFO_KEYS
            if dev.supports(getattr(rs.camera_info, key))}


def find_device(rs: ModuleType, ctx: Any, serial: str) -> tuple[Any | None, list[str]]:
    """``(the connected device with this serial or None, the serials of every connected device)``."""
    serials: list[str] = []
    for dev in ctx.query_devices():
        found = dev.get_info(rs.camera_info.serial_number)
        if found == serial:
            return dev, serials
        serials.append(found)
    return None, serials


def _intrinsics(rs_intr: Any) -> Intrinsics:
    model = DISTORTION_NAMES.get(str(rs_intr.model).split(".")[-1], str(rs_intr.model))
    k1, k2, k3, k4, k5 = (float(c) for c in list(rs_intr.coeffs)[:5])
    return Intrinsics(int(rs_intr.width), int(rs_intr.height), float(rs_intr.fx), float(rs_intr.fy),
                      float(rs_intr.ppx), float(rs_intr.ppy), model, (k1, k2, k3, k4, k5))


def _transform(rs_extr: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(rs_extr.rotation, dtype=np.float64).reshape(3, 3).T  # stored column-major
    T[:3, 3] = np.asarray(rs_extr.translation, dtype=np.float64)
    return T


class RealSenseCamera(CameraBackend):
    """A RealSense camera by serial; live frames from a reader thread, recording through the SDK."""

    def __init__(self, serial: str, settings: CameraSettings | None = None, *, arm_id: str | None = None,
                 rs: ModuleType | None = None) -> None:
        self.serial = str(serial)
        self.arm_id = arm_id
        self.settings = settings or CameraSettings()
        self._rs = rs
        self._ctx: Any = None  # rs.context
        self._pipe: Any = None  # rs.pipeline while streaming
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._latest: Any = None  # the newest rs.composite_frame with depth
        self._reader_error: BaseException | None = None
        self._recording_path: Path | None = None
        self._depth_intrinsics: Intrinsics | None = None
        self._colour_intrinsics: Intrinsics | None = None
        self._T_color_depth: np.ndarray | None = None
        self.depth_scale: float | None = None
        self.device_info: dict[str, str] = {}
        self.imu_rates_hz: tuple[int, int] | None = None
        self.frames_received = 0

    def _label(self) -> str:
        return f"camera {self.serial}" + (f" ({self.arm_id})" if self.arm_id else "")

    # -- lifecycle --------------------------------------------------------------------------------
    @property
    def streaming(self) -> bool:
        return self._pipe is not None

    @property
    def recording(self) -> bool:
        return self._recording_path is not None

    @property
    def recording_path(self) -> Path | None:
        """The file being recorded (its suffix is the SDK's container), or None."""
        return self._recording_path

    def open(self) -> None:
        """Start live streaming without recording (done lazily by :meth:`latest_frameset`)."""
        if self._pipe is None:
            self._start(None)

    def close(self) -> None:
        """Finish any recording and stop streaming (idempotent)."""
        if self.recording:
            self.stop_recording()
        self._stop_streaming()

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- CameraBackend ----------------------------------------------------------------------------
    def start_recording(self, path: Path) -> Path:
        """Record every stream to ``path`` (``cam<serial>.bag``); returns the path actually written.

        With pyrealsense2 >= 2.58 and ``recording_format: auto`` that is ``cam<serial>.db3``.
        """
        if self.recording:
            raise HardwareError(f"{self._label()} is already recording to {self._recording_path}")
        rs = self._module()
        version = sdk_loader.realsense_version(rs)
        target = Path(path).with_suffix(sdk_loader.recording_suffix(self.settings.recording_format, version))
        if target != Path(path):
            log.warning("%s: pyrealsense2 %s records only %s files: writing %s instead of %s", self._label(),
                        ".".join(map(str, version)), target.suffix, target.name, Path(path).name)
        if target.exists():
            raise HardwareError("already exists: refusing to overwrite a recording", target)
        target.parent.mkdir(parents=True, exist_ok=True)
        self._stop_streaming()
        self._start(target)
        self._recording_path = target
        log.info("%s: recording to %s", self._label(), target)
        return target

    def stop_recording(self) -> Path | None:
        """Stop the recording and let the SDK finish the file; returns its path (None if not recording)."""
        path = self._recording_path
        if path is None:
            return None
        self._recording_path = None
        self._stop_streaming()
        gc.collect()  # drop any cycle still holding the recording device, so the SDK closes the file now
        if not path.is_file():
            raise HardwareError(f"{self._label()}: the SDK did not write the recording (no file after stopping)",
                                path)
        return path

    def latest_frameset(self) -> LiveFrameSet:
        """Depth in metres, colour and intrinsics of the newest frame set (starts streaming if needed)."""
        if self._pipe is None:
            self.open()
        fs = self._wait_latest(self.settings.start_timeout_s)
        depth = fs.get_depth_frame()
        stamp_ms = float(depth.get_timestamp())
        domain = str(depth.get_frame_timestamp_domain()).split(".")[-1]
        if domain not in HOST_DOMAINS:
            raise HardwareError(f"{self._label()}: frame timestamps are in the {domain} domain, not the host clock")
        age_s = time.time() - stamp_ms / 1e3
        if age_s > self.settings.stale_after_s:
            raise HardwareError(f"{self._label()}: the newest frame is {age_s:.1f} s old: the camera stopped "
                                f"streaming (USB disconnect? power?)")
        raw = np.asanyarray(depth.get_data())
        depth_m = raw.astype(np.float32) * np.float32(self.depth_scale)
        color = fs.get_color_frame()
        colour_bgr = np.array(np.asanyarray(color.get_data()), copy=True) if color else None
        extra: dict[str, object] = {"serial": self.serial, "frame_number": int(depth.get_frame_number()),
                                    "timestamp_domain": domain, "depth_scale": self.depth_scale}
        ir1 = fs.get_infrared_frame(1) if self.settings.infrared else None
        if ir1:
            extra["ir1"] = np.array(np.asanyarray(ir1.get_data()), copy=True)
        return LiveFrameSet(timestamp_s=stamp_ms / 1e3, depth_m=depth_m, depth_intrinsics=self.depth_intrinsics,
                            colour_bgr=colour_bgr, colour_intrinsics=self._colour_intrinsics if color else None,
                            T_color_depth=None if self._T_color_depth is None else self._T_color_depth.copy(),
                            extra=extra)

    @property
    def depth_intrinsics(self) -> Intrinsics:
        """Intrinsics of the depth (left infrared) stream (starts streaming if needed)."""
        intrinsics = self._depth_intrinsics
        if intrinsics is None:
            self.open()
            intrinsics = self._depth_intrinsics
        if intrinsics is None:  # open() reads them or raises
            raise HardwareError(f"{self._label()}: the depth stream reported no intrinsics")
        return intrinsics

    # -- streaming --------------------------------------------------------------------------------
    def _module(self) -> ModuleType:
        if self._rs is None:
            self._rs = sdk_loader.load_realsense()
        return self._rs

    def _find_device(self) -> Any:
        rs = self._module()
        if self._ctx is None:
            self._ctx = rs.context()
        dev, serials = find_device(rs, self._ctx, self.serial)
        if dev is not None:
            return dev
        found = ", ".join(serials) if serials else "none"
        raise HardwareError(f"{self._label()} is not connected (cameras found: {found}): check the USB 3 cable and "
                            f"the udev rules (docs/hardware.md)")

    def _imu_rates(self, dev: Any) -> tuple[int, int] | None:
        if self.settings.imu == "off":
            return None
        rs = self._module()
        for sensor in dev.query_sensors():
            if sensor.is_motion_sensor():
                rates: dict[str, list[int]] = {"accel": [], "gyro": []}
                for profile in sensor.get_stream_profiles():
                    kind = str(profile.stream_type()).split(".")[-1]
                    if kind in rates and profile.format() == rs.format.motion_xyz32f:
                        rates[kind].append(int(profile.fps()))
                if rates["accel"] and rates["gyro"]:
                    return min(rates["accel"]), min(rates["gyro"])
        if self.settings.imu == "on":
            raise HardwareError(f"{self._label()} ({dev.get_info(rs.camera_info.name)}) has no IMU, but cameras.imu "
                                f"is 'on'")
        return None

    def _config(self, imu: tuple[int, int] | None, record_to: Path | None) -> Any:
        rs, s = self._module(), self.settings
        cfg = rs.config()
        cfg.enable_device(self.serial)
        for stream, index, fmt, width, height, fps in video_streams(rs, s).values():
            cfg.enable_stream(stream, index, width, height, fmt, fps)
        if imu is not None:
            cfg.enable_stream(rs.stream.accel, rs.format.motion_xyz32f, imu[0])
            cfg.enable_stream(rs.stream.gyro, rs.format.motion_xyz32f, imu[1])
        if record_to is not None:
            cfg.enable_record_to_file(str(record_to))
        return cfg

    def _start(self, record_to: Path | None) -> None:
        rs = self._module()
        dev = self._find_device()
        self.device_info = device_info(rs, dev)
        if self.device_info.get("usb_type_descriptor", "3").startswith("2"):
            log.warning("%s is on USB %s: all streams at %dx%d@%d need USB 3", self._label(),
                        self.device_info["usb_type_descriptor"], self.settings.width, self.settings.height,
                        self.settings.fps)
        self.imu_rates_hz = self._imu_rates(dev)
        del dev
        pipe = rs.pipeline(self._ctx)
        s = self.settings
        try:
            profile = pipe.start(self._config(self.imu_rates_hz, record_to))
        except RuntimeError as err:
            raise HardwareError(f"{self._label()}: cannot start {s.width}x{s.height}@{s.fps} streaming: {err}") from err
        self._pipe = pipe
        try:
            self._prepare(rs, profile, record_to is not None)
            del profile
            self._reader_error = None
            self._stop.clear()
            self._reader = threading.Thread(target=self._read_loop, args=(pipe,), daemon=True,
                                             name=f"rs-{self.serial}")
            self._reader.start()
            self._wait_host_clock()
            if record_to is not None:
                pipe.get_active_profile().get_device().as_recorder().resume()
        except BaseException:
            self._stop_streaming()
            raise

    def _prepare(self, rs: ModuleType, profile: Any, recording: bool) -> None:
        """Pause the recorder, switch every sensor to global time, read intrinsics and depth scale."""
        dev = profile.get_device()
        try:
            if recording:
                dev.as_recorder().pause()
            for sensor in dev.query_sensors():
                if sensor.supports(rs.option.global_time_enabled):
                    sensor.set_option(rs.option.global_time_enabled, 1.0)
            self.depth_scale = float(dev.first_depth_sensor().get_depth_scale())
            depth_p = profile.get_stream(rs.stream.depth).as_video_stream_profile()
            self._depth_intrinsics = _intrinsics(depth_p.get_intrinsics())
            if self.settings.color:
                colour_p = profile.get_stream(rs.stream.color).as_video_stream_profile()
                self._colour_intrinsics = _intrinsics(colour_p.get_intrinsics())
                self._T_color_depth = _transform(depth_p.get_extrinsics_to(colour_p))
        except RuntimeError as err:
            raise HardwareError(f"{self._label()}: cannot configure the streaming device: {err}") from err

    def _read_loop(self, pipe: Any) -> None:
        while not self._stop.is_set():
            try:
                ok, fs = pipe.try_wait_for_frames(200)
            except RuntimeError as err:
                self._reader_error = err
                return
            if not ok or not fs.get_depth_frame():  # timeout, or an IMU-only frame set
                continue
            with self._lock:
                self._latest = fs
                self.frames_received += 1

    def _wait_latest(self, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            if self._reader_error is not None:
                raise HardwareError(f"{self._label()}: streaming failed: {self._reader_error}")
            with self._lock:
                fs = self._latest
            if fs is not None:
                return fs
            if time.monotonic() > deadline:
                raise HardwareError(f"{self._label()}: no frames within {timeout_s:g} s of starting the stream")
            time.sleep(0.005)

    def _wait_host_clock(self) -> None:
        """Wait for a frame set stamped on the host clock (after global time was switched on)."""
        deadline = time.monotonic() + self.settings.start_timeout_s
        last = "none"
        while time.monotonic() < deadline:
            fs = self._wait_latest(max(deadline - time.monotonic(), 0.01))
            depth = fs.get_depth_frame()
            domain = str(depth.get_frame_timestamp_domain()).split(".")[-1]
            offset_s = depth.get_timestamp() / 1e3 - time.time()
            if domain in HOST_DOMAINS and abs(offset_s) <= self.settings.max_clock_offset_s:
                if domain == "system_time":
                    log.warning("%s: timestamps are arrival times (system time), not global time: frame "
                                "metadata is unavailable (kernel patch / udev rules, docs/hardware.md)", self._label())
                return
            last = f"{domain}, {offset_s:+.3f} s from the host clock"
            time.sleep(0.005)
        raise HardwareError(f"{self._label()}: frame timestamps are not on the host clock (last frame: {last}); "
                            f"global time is unsupported or failed on this camera")

    def _stop_streaming(self) -> None:
        """Stop the reader and the pipeline and drop every reference to frames, profile and device."""
        self._stop.set()
        if self._reader is not None:
            self._reader.join(timeout=2.0)
            self._reader = None
        with self._lock:
            self._latest = None
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError as err:
                log.warning("%s: stopping the pipeline: %s", self._label(), err)


__all__ = ["DEVICE_INFO_KEYS", "CameraSettings", "RealSenseCamera", "VideoStream", "device_info", "find_device",
           "video_streams"]
