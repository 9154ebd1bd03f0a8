"""The twin's wrist camera as a :class:`CameraBackend`: streams on the simulated clock, records ``.bag``.

The camera streams from the start of the simulation, like a device that was started before the
survey: a frame tick every ``1/fps`` s (frame counter = ticks since the stream started; the second
camera is staggered by a few milliseconds). Only while recording does a tick render anything: the
world is put in its state at that instant (both arms at their true joint angles), the
:class:`~darp.twin.camera.sensor.TwinCamera` renders depth, both infrared images and colour at the camera's
true pose, and the frames go to ``cam<serial>.bag`` through :class:`~darp.formats.realsense.bag.writer.BagWriter`
with "Global Time" timestamps in milliseconds on the host clock (plus the optional simulated clock
offset). Accelerometer and gyroscope samples since the previous tick are written first, in time
order, so the file is written in time order. The true pose of every recorded frame is kept for
``truth/camera_poses_<arm>.npz``.

:meth:`TwinCameraBackend.latest_frameset` renders the most recent frame tick on demand with a second
``TwinCamera`` (its own noise stream), so live queries never change what is recorded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypedDict

import numpy as np

from darp.backend import CameraBackend, LiveFrameSet
from darp.errors import RecordingError, TwinError
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile
from darp.kinematics.transforms import compose, matvec
from darp.twin.camera.spec import CameraSpec
from darp.twin.clock import NS_PER_S, SimClock, s_to_ns
from darp.twin.truth import CameraPoseTruth

if TYPE_CHECKING:  # imported for their types only: the sensor imports MuJoCo and OpenGL
    from darp.twin.camera.imu import ImuSimulator
    from darp.twin.camera.sensor import TwinCamera
    from darp.twin.camera.worker import CameraWorker

IMAGE_ORDER = ("depth", "ir1", "ir2", "color")
FIRMWARE = "5.13.0.50"
PRODUCT_ID = "0B3A"  # D435i
# LZ4 fast mode for the bags: 30 % less compression time than the default level for 3 % larger files
# (the simulated images carry sensor noise and compress to about 74 % either way); same LZ4 frames.
LZ4_ACCELERATION = 2


class _BagOptions(TypedDict):
    """Keyword arguments of the bag writer (in this process or in a worker)."""

    depth_scale: float
    extrinsics: dict[str, np.ndarray]
    compression: str
    lz4_acceleration: int
    start_ms: float


class CameraHost(Protocol):
    """What the rig provides to its cameras."""

    def prepare_world(self, t_ns: int) -> Any:
        """Put the scene in its state at ``t_ns`` (ns since the simulation start); return the MjData."""

    def true_camera_poses(self, arm_id: str, t_ns: np.ndarray) -> np.ndarray:
        """True ``T_world_cam`` (N, 4, 4) of an arm's camera at simulation times (ns)."""

    def true_q(self, arm_id: str, t_ns: int) -> np.ndarray:
        """True joint angles (6,) of an arm at ``t_ns``."""


class TwinCameraBackend(CameraBackend):
    """One simulated wrist camera on the rig's clock."""

    def __init__(self, arm_id: str, spec: CameraSpec, clock: SimClock, host: CameraHost, *,
                 camera: TwinCamera | None, live_camera: Callable[[], TwinCamera], imu: ImuSimulator | None = None,
                 phase_ns: int = 0, clock_offset_ms: float = 0.0, compression: str = "lz4",
                 worker: CameraWorker | None = None,
                 lz4_acceleration: int = LZ4_ACCELERATION, factory_spec: CameraSpec | None = None,
                 latency_ms: float = 0.0, jitter_ms: float = 0.0, exposure_ms: float = 0.0,
                 jitter_seed: int = 0) -> None:
        """``camera``: the :class:`~darp.twin.camera.sensor.TwinCamera` that renders recorded frames (None when a
        :class:`~darp.twin.camera.worker.CameraWorker` ``worker`` does); ``live_camera``: a factory of the
        camera for live queries (built on first use); ``imu``: an :class:`~darp.twin.camera.imu.ImuSimulator` or
        None (no motion streams); ``lz4_acceleration``: LZ4 fast mode of the bag chunks (see
        :class:`~darp.formats.realsense.bag.writer.BagWriter`); ``factory_spec``: the intrinsics the camera
        reports and records (its factory calibration; default ``spec``, the true ones it renders with);
        ``latency_ms`` and ``jitter_ms``: image frame stamps are the exposure instant plus the latency plus
        Gaussian jitter (seeded per frame by ``jitter_seed``); ``exposure_ms``: the colour image is blurred
        over the camera's motion during it."""
        self.arm_id = arm_id
        self.serial = spec.serial
        self.spec = spec
        self.factory_spec = factory_spec if factory_spec is not None else spec
        self.latency_ms = float(latency_ms)
        self.jitter_ms = float(jitter_ms)
        self.exposure_ms = float(exposure_ms)
        self.jitter_seed = int(jitter_seed)
        self.clock = clock
        self.host = host
        if (camera is None) == (worker is None):
            raise TwinError("a twin camera renders either in this process (camera) or in a worker, not both")
        self.camera = camera
        self.worker = worker
        self._live_factory = live_camera
        self._live: TwinCamera | None = None
        self.imu = imu
        self.clock_offset_ms = float(clock_offset_ms)
        self.compression = compression
        self.lz4_acceleration = int(lz4_acceleration)
        self.phase_ns = int(phase_ns)
        self._writer: BagWriter | None = None
        self._recording = False
        self.truth = CameraPoseTruth()
        self.frames_recorded = 0
        # Wall seconds of capture, IMU and writing; cpu: the worker's CPU seconds; *_cpu: CPU seconds of a stage.
        self.timings_s = {"capture": 0.0, "imu": 0.0, "write": 0.0, "cpu": 0.0, "imu_cpu": 0.0, "write_cpu": 0.0}
        self._imu_from_ns: int | None = None
        self._tick = 0
        clock.add_process(f"{arm_id}:camera", self._frame_tick, first_due_ns=max(self.phase_ns, clock.elapsed_ns))

    # -- clock ------------------------------------------------------------------------------------
    def frame_time_ns(self, n: int) -> int:
        """Simulation time of frame tick ``n`` (exact integer arithmetic, no drift)."""
        return self.phase_ns + (n * NS_PER_S) // self.spec.fps

    def timestamp_ms(self, t_ns: int) -> float:
        """The bag timestamp of a simulation instant: host-clock ms plus the camera clock offset."""
        return self.clock.start_time_s * 1e3 + t_ns / 1e6 + self.clock_offset_ms

    def frame_stamp_ms(self, n: int, t_ns: int) -> float:
        """The bag timestamp of image frame ``n`` exposed at ``t_ns``: latency and per-frame jitter added."""
        stamp = self.timestamp_ms(t_ns)
        if self.latency_ms or self.jitter_ms:
            jitter = (np.random.default_rng([self.jitter_seed, n]).normal(0.0, self.jitter_ms)
                      if self.jitter_ms > 0 else 0.0)
            stamp += self.latency_ms + float(jitter)
        return stamp

    def motion_px(self, t_ns: int) -> np.ndarray | None:
        """Colour image motion (dx, dy) in pixels over the exposure around ``t_ns`` (None: no exposure set).

        Measured on the point 0.5 m in front of the camera: where it is seen at the exposure's start and end.
        """
        if self.exposure_ms <= 0:
            return None
        half = s_to_ns(0.5 * self.exposure_ms / 1e3)
        T = self.host.true_camera_poses(self.arm_id, np.array([t_ns - half, t_ns + half]))
        T_cd = self.spec.T_depth_stream("color")
        a, b = compose(T[0], T_cd), compose(T[1], T_cd)
        p = matvec(a[:3, :3], np.array([0.0, 0.0, 0.5])) + a[:3, 3]
        q = matvec(b[:3, :3].T, p - b[:3, 3])
        c = self.spec.color
        return np.array([c.fx * q[0] / q[2], c.fy * q[1] / q[2]])

    def _frame_tick(self, now_ns: int) -> int:
        while self.frame_time_ns(self._tick) < now_ns:  # registered late: skip ticks already past
            self._tick += 1
        if self._recording:
            self._record_frame(self._tick, now_ns)
        self._tick += 1
        return self.frame_time_ns(self._tick)

    # -- recording --------------------------------------------------------------------------------
    def stream_profiles(self) -> list[StreamProfile]:
        profiles = self.factory_spec.stream_profiles()
        keys = [*IMAGE_ORDER, *(("accel", "gyro") if self.imu is not None else ())]
        return [profiles[k] for k in keys]

    def start_recording(self, path: Path) -> None:
        """Open ``path`` (``cam<serial>.bag``) and record every frame tick from now on."""
        if self._recording:
            raise TwinError(f"camera {self.serial} is already recording")
        path = Path(path)
        device = DeviceInfo(name=self.spec.name, serial=self.serial, firmware=FIRMWARE, product_id=PRODUCT_ID,
                            info={"Product Line": "D400", "Usb Type Descriptor": "3.2", "Camera Locked": "YES"})
        extrinsics = {key: self.spec.extrinsics("depth", key) for key in ("ir1", "ir2", "color")}
        if self.imu is not None:
            extrinsics.update({key: self.spec.extrinsics("depth", key) for key in ("accel", "gyro")})
        args = (path, device, self.stream_profiles())
        kwargs: _BagOptions = {"depth_scale": self.spec.depth_unit_m, "extrinsics": extrinsics,
                               "compression": self.compression, "lz4_acceleration": self.lz4_acceleration,
                               "start_ms": self.timestamp_ms(self.clock.elapsed_ns) - 1.0}
        if self.worker is not None:
            for target in (path, path.with_name(path.name + ".partial")):
                if target.exists():
                    raise RecordingError("already exists (pass overwrite=True to replace it)", target)
            self.worker.open(*args, **kwargs)
        else:
            self._writer = BagWriter(*args, **kwargs)
        self._recording = True
        self._imu_from_ns = self.clock.elapsed_ns
        self.truth = CameraPoseTruth()
        self.frames_recorded = 0

    def stop_recording(self) -> None:
        """Finish the bag (every frame written, index written, renamed from ``.partial``)."""
        if not self._recording:
            return
        self._recording = False
        if self.worker is not None:
            self.worker.close_recording()
            for key, value in self.worker.timings_s.items():
                self.timings_s[key] += value
                self.worker.timings_s[key] = 0.0
        else:
            writer, self._writer = self._writer, None
            assert writer is not None
            writer.close()

    def abort_recording(self) -> None:
        """Stop without finishing the file (after an error): the ``.partial`` file stays."""
        if not self._recording:
            return
        self._recording = False
        if self.worker is not None:
            self.worker.close_recording(abort=True)
        elif self._writer is not None:
            writer, self._writer = self._writer, None
            writer.abort()

    def _record_frame(self, n: int, t_ns: int) -> None:
        stamp_ms = self.frame_stamp_ms(n, t_ns)
        motion = self._imu_samples(t_ns) if self.imu is not None else []
        data = self.host.prepare_world(t_ns)
        T_world_cam = self.host.true_camera_poses(self.arm_id, np.array([t_ns]))[0]
        t0 = time.perf_counter()
        if self.worker is not None:
            self.worker.frame(n, stamp_ms, data.qpos.copy(), T_world_cam, motion, IMAGE_ORDER, self.motion_px(t_ns))
        else:
            assert self._writer is not None and self.camera is not None
            c0 = time.process_time()
            for key, values, stamp, index in motion:
                self._writer.write_motion(key, values, stamp, index)
            t1, c1 = time.perf_counter(), time.process_time()
            frames = self.camera.capture(data, T_world_cam, timestamp_s=stamp_ms / 1e3, motion_px=self.motion_px(t_ns))
            t2, c2 = time.perf_counter(), time.process_time()
            for key in IMAGE_ORDER:
                self._writer.write_image(key, frames[key], stamp_ms, n)
            self.timings_s["capture"] += t2 - t1
            self.timings_s["write"] += (t1 - t0) + (time.perf_counter() - t2)
            self.timings_s["write_cpu"] += (c1 - c0) + (time.process_time() - c2)
        self.truth.append(n, stamp_ms, self.clock.host_time_s(t_ns), T_world_cam, self.host.true_q(self.arm_id, t_ns))
        self.frames_recorded += 1

    def _imu_samples(self, until_ns: int) -> list[tuple[str, np.ndarray, float, int]]:
        """Accel and gyro samples in [last tick, ``until_ns``) on their own rates, in time order."""
        assert self._imu_from_ns is not None and self.imu is not None
        t0, c0 = time.perf_counter(), time.process_time()
        samples = []
        for key, rate in (("accel", self.spec.accel_hz), ("gyro", self.spec.gyro_hz)):
            first = -(-(self._imu_from_ns - self.phase_ns) * rate // NS_PER_S)  # ceil
            last = -(-(until_ns - self.phase_ns) * rate // NS_PER_S)
            k = np.arange(first, last, dtype=np.int64)
            if k.size == 0:
                continue
            t_ns = self.phase_ns + (k * NS_PER_S) // rate
            t_s = t_ns / NS_PER_S
            values = (self.imu.accel(t_s, self._imu_pose, rate) if key == "accel"
                      else self.imu.gyro(t_s, self._imu_pose, rate))
            samples += [(int(t), key, int(i), v) for t, i, v in zip(t_ns, k, values, strict=True)]
        samples.sort(key=lambda s: (s[0], s[1]))
        self._imu_from_ns = until_ns
        self.timings_s["imu"] += time.perf_counter() - t0
        self.timings_s["imu_cpu"] += time.process_time() - c0
        return [(key, value, self.timestamp_ms(t), index) for t, key, index, value in samples]

    def _imu_pose(self, t_s: np.ndarray) -> np.ndarray:
        t_ns = np.rint(np.asarray(t_s, dtype=np.float64) * NS_PER_S).astype(np.int64)
        return self.host.true_camera_poses(self.arm_id, t_ns)

    @property
    def stage_cpu_s(self) -> dict[str, float]:
        """CPU seconds spent so far per stage of the recorded frames: the camera's capture stages
        (``darp.twin.camera.sensor.CAPTURE_STAGES``; from a worker: as of its last finished recording), the
        bag writing and the IMU samples."""
        if self.worker is not None:
            capture = self.worker.stage_cpu_s
        else:
            assert self.camera is not None
            capture = self.camera.stage_cpu_s
        return {**capture, "write": self.timings_s["write_cpu"], "imu": self.timings_s["imu_cpu"]}

    # -- live frames ------------------------------------------------------------------------------
    def latest_frameset(self) -> LiveFrameSet:
        """The most recent frame tick, rendered now (depth quantised to the depth unit, as recorded)."""
        now = self.clock.elapsed_ns
        n = max(0, self._tick - 1)
        while n > 0 and self.frame_time_ns(n) > now:
            n -= 1
        return self.frameset_at(n, min(self.frame_time_ns(n), now))

    def frameset_at(self, n: int, t_ns: int) -> LiveFrameSet:
        """Frame tick ``n`` at simulation time ``t_ns``, rendered now by the live camera (not recorded)."""
        data = self.host.prepare_world(t_ns)
        T_world_cam = self.host.true_camera_poses(self.arm_id, np.array([t_ns]))[0]
        stamp_ms = self.frame_stamp_ms(n, t_ns)
        if self._live is None:
            self._live = self._live_factory()
        frames = self._live.capture(data, T_world_cam, timestamp_s=stamp_ms / 1e3, motion_px=self.motion_px(t_ns))
        depth_m = frames["depth"].astype(np.float32) * np.float32(self.spec.depth_unit_m)
        return LiveFrameSet(
            timestamp_s=stamp_ms / 1e3,
            depth_m=depth_m,
            depth_intrinsics=self.factory_spec.depth,
            colour_bgr=frames["color"],
            colour_intrinsics=self.factory_spec.color,
            T_color_depth=self.spec.T_color_depth,
            extra={"ir1": frames["ir1"], "ir2": frames["ir2"], "frame_number": n},
        )

    @property
    def depth_intrinsics(self) -> Intrinsics:
        return self.factory_spec.depth

    def close(self) -> None:
        """Abort an unfinished recording and free the cameras' resources (idempotent)."""
        try:
            self.abort_recording()
        finally:
            for cam in (self.camera, self._live):
                if cam is not None:
                    cam.close()
            self._live = None
            if self.worker is not None:
                self.worker.shutdown()


__all__ = ["CameraHost", "TwinCameraBackend"]
