"""A minimal analytic rig for fast acquisition tests (``tests/test_acquisition_fakes.py`` holds it to
Open3D's ray caster).

The fake world is the nominal rig (no calibration error) with upright cylinders on the table. Depth is
ray-cast analytically (table plane, cylinder side, top cap); with OpenCV pixel centres and a ray
direction whose camera z is 1, the ray parameter *is* the depth. The fake backend implements the
acquisition interface: a simple event clock, arms that move linearly in joint space at a fixed speed,
cameras that render live frames and record real ``.bag`` files (darp's writer), and a 33 Hz joint log.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from darp.backend import ArmBackend, CameraBackend, Clock, JointState, LiveFrameSet, RigBackend
from darp.formats.arm_poses import ArmPoseWriter
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile
from darp.kinematics.rig import Rig, load_rig

INTRINSICS = Intrinsics(width=160, height=120, fx=110.0, fy=110.0, ppx=79.5, ppy=59.5)


@dataclass(frozen=True)
class Cylinder:
    """An upright cylinder standing on the table."""

    x_m: float
    y_m: float
    radius_m: float
    height_m: float


_RAYS: dict[Intrinsics, np.ndarray] = {}


def _rays(intr: Intrinsics) -> np.ndarray:
    """Camera-frame ray directions with z = 1 through every pixel centre (cached)."""
    if intr not in _RAYS:
        v, u = np.mgrid[0:intr.height, 0:intr.width].astype(float)
        _RAYS[intr] = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones_like(u)], axis=-1)
    return _RAYS[intr]


def render_depth(T_world_cam: np.ndarray, intr: Intrinsics, objects: list[Cylinder], rig: Rig) -> np.ndarray:
    """Exact depth (m, 0 = no surface) of the table top and the cylinders seen from ``T_world_cam``."""
    d_cam = _rays(intr)
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = d_cam @ R.T  # ray directions in the world; parameter t along d equals the depth
    z0 = rig.table.height_m
    depth = np.full(d_cam.shape[:2], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z0 - o[2]) / d[..., 2]
        p = o + t[..., None] * d
        (x0, x1), (y0, y1) = rig.table.x_range_m, rig.table.y_range_m
        on_table = (t > 0) & (p[..., 0] >= x0) & (p[..., 0] <= x1) & (p[..., 1] >= y0) & (p[..., 1] <= y1)
        depth = np.where(on_table, t, depth)
        for cyl in objects:
            ox, oy = o[0] - cyl.x_m, o[1] - cyl.y_m
            a = d[..., 0] ** 2 + d[..., 1] ** 2
            b = 2 * (ox * d[..., 0] + oy * d[..., 1])
            c = ox ** 2 + oy ** 2 - cyl.radius_m ** 2
            disc = b ** 2 - 4 * a * c
            t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
            z_side = o[2] + t_side * d[..., 2]
            side = (disc >= 0) & (t_side > 0) & (z_side >= z0) & (z_side <= z0 + cyl.height_m)
            depth = np.where(side & (t_side < depth), t_side, depth)
            t_top = (z0 + cyl.height_m - o[2]) / d[..., 2]
            q = o + t_top[..., None] * d
            top = (t_top > 0) & ((q[..., 0] - cyl.x_m) ** 2 + (q[..., 1] - cyl.y_m) ** 2 <= cyl.radius_m ** 2)
            depth = np.where(top & (t_top < depth), t_top, depth)
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


class FakeClock(Clock):
    """Simulated time with periodic processes (run in time order while sleeping)."""

    def __init__(self, start_s: float = 1_000_000.0) -> None:
        self.t = start_s
        self._queue: list[tuple[float, int, int]] = []
        self._procs: dict[int, tuple[float, Callable[[float], None]]] = {}
        self._ids = itertools.count()

    def now(self) -> float:
        return self.t

    def every(self, period_s: float, fn: Callable[[float], None]) -> int:
        pid = next(self._ids)
        self._procs[pid] = (period_s, fn)
        heapq.heappush(self._queue, (self.t, pid, pid))
        return pid

    def cancel(self, pid: int) -> None:
        self._procs.pop(pid, None)

    def sleep(self, duration_s: float) -> None:
        end = self.t + duration_s
        while self._queue and self._queue[0][0] <= end:
            due, _, pid = heapq.heappop(self._queue)
            if pid not in self._procs:
                continue
            self.t = max(self.t, due)
            period, fn = self._procs[pid]
            fn(self.t)
            if pid in self._procs:
                heapq.heappush(self._queue, (due + period, pid, pid))
        self.t = end


class FakeArm(ArmBackend):
    """Moves linearly in joint space at ``speed``; reports angles plus an optional bias (a faulty encoder)."""

    def __init__(self, arm_id: str, clock: FakeClock, q0: np.ndarray, speed_rad_s: float = 1.0,
                 reported_bias_rad: np.ndarray | None = None) -> None:
        self.arm_id, self.clock, self.speed = arm_id, clock, speed_rad_s
        self.q0 = self.q1 = np.asarray(q0, float).copy()
        self.t0 = self.t1 = clock.now()
        self.bias = np.zeros(6) if reported_bias_rad is None else np.asarray(reported_bias_rad, float)
        self.moves: list[np.ndarray] = []
        self.intervals: list[tuple[float, float]] = []  # (start, end) of every commanded move
        self.stops = 0
        self.on_move: Callable[[int], None] | None = None  # called with the move count (fault injection)

    def true_q(self) -> np.ndarray:
        t = self.clock.now()
        if t >= self.t1 or self.t1 <= self.t0:
            return self.q1.copy()
        return self.q0 + (self.q1 - self.q0) * (t - self.t0) / (self.t1 - self.t0)

    def read_state(self) -> JointState:
        return JointState(self.clock.now(), self.true_q() + self.bias, np.zeros(6))

    def move_to(self, q_target_rad: np.ndarray, max_speed_rad_s: float | None = None) -> None:
        if self.on_move is not None:
            self.on_move(len(self.moves))
        q = np.asarray(q_target_rad, float)
        self.q0, self.t0 = self.true_q(), self.clock.now()
        self.q1 = q.copy()
        self.t1 = self.t0 + float(np.max(np.abs(q - self.q0))) / (max_speed_rad_s or self.speed)
        self.moves.append(q.copy())
        self.intervals.append((self.t0, self.t1))

    def is_moving(self) -> bool:
        return self.clock.now() < self.t1

    def stop(self) -> None:
        self.q1, self.t1 = self.true_q(), self.clock.now()
        self.stops += 1


class FakeCamera(CameraBackend):
    """Renders the analytic world at the arm's true camera pose; records real .bag files."""

    def __init__(self, rig_backend: FakeRig, arm_id: str, serial: str, fps: int = 5,
                 glitch: Callable[[int], Cylinder | None] | None = None, drop_every: int = 0) -> None:
        self.rb, self.arm_id, self.serial, self.fps = rig_backend, arm_id, serial, fps
        self.glitch = glitch  # live frame count -> a replacement object for that frame (a fluke)
        self.drop_every = drop_every
        self.live_frames = 0
        self.writer: BagWriter | None = None
        self.frames_written = 0
        self._tick: int | None = None
        self._n = 0

    @property
    def depth_intrinsics(self) -> Intrinsics:
        return INTRINSICS

    def _pose(self) -> np.ndarray:
        return self.rb.rig.T_world_cam(self.arm_id, self.rb.arms[self.arm_id].true_q())

    def _render(self, objects: list[Cylinder]) -> np.ndarray:
        return render_depth(self._pose(), INTRINSICS, objects, self.rb.rig)

    def latest_frameset(self) -> LiveFrameSet:
        objects = self.rb.objects
        if self.glitch is not None:
            replacement = self.glitch(self.live_frames)
            if replacement is not None:
                objects = [replacement]
        self.live_frames += 1
        return LiveFrameSet(self.rb.clock.now(), self._render(objects), INTRINSICS)

    def start_recording(self, path: Path) -> None:
        profiles = [StreamProfile("depth", "Depth", 0, 0, "z16", self.fps, 160, 120, INTRINSICS),
                    StreamProfile("ir1", "Infrared", 1, 0, "y8", self.fps, 160, 120, INTRINSICS),
                    StreamProfile("ir2", "Infrared", 2, 0, "y8", self.fps, 160, 120, INTRINSICS),
                    StreamProfile("color", "Color", 0, 1, "bgr8", self.fps, 160, 120, INTRINSICS)]
        self.writer = BagWriter(path, DeviceInfo("Fake D435", self.serial), profiles, depth_scale=0.001,
                                start_ms=self.rb.clock.now() * 1e3 - 1.0)
        self._tick = self.rb.clock.every(1.0 / self.fps, self._frame)

    def _frame(self, t: float) -> None:
        self._n += 1
        if self.writer is None or (self.drop_every and self._n % self.drop_every == 0):
            return
        depth_mm = np.rint(self._render(self.rb.objects) * 1000).astype(np.uint16)
        grey = np.full((120, 160), 128, np.uint8)
        for key, image in (("depth", depth_mm), ("ir1", grey), ("ir2", grey),
                           ("color", np.dstack([grey] * 3))):
            self.writer.write_image(key, image, t * 1e3, self._n)
        self.frames_written += 1

    def stop_recording(self) -> None:
        if self._tick is not None:
            self.rb.clock.cancel(self._tick)
            self._tick = None
        if self.writer is not None:
            writer, self.writer = self.writer, None
            writer.close()


class FakeRig(RigBackend):
    """The nominal rig with analytic cylinders, simple arms and cameras, and a 33 Hz joint log."""

    def __init__(self, objects: list[Cylinder], *, rig: Rig | None = None, speed_rad_s: float = 1.0,
                 fps: int = 4, biases: dict[str, np.ndarray] | None = None) -> None:
        self.rig = rig if rig is not None else load_rig()
        self.objects = list(objects)
        self.clock = FakeClock()
        self.arms = {a: FakeArm(a, self.clock, self.rig.arms[a].park_q_rad, speed_rad_s, (biases or {}).get(a))
                     for a in self.rig.arm_ids}
        self.cameras = {a: FakeCamera(self, a, self.rig.arms[a].camera_serial, fps) for a in self.rig.arm_ids}
        self.log: ArmPoseWriter | None = None
        self._log_tick: int | None = None
        self.closed = False

    def start_joint_log(self, path: Path) -> None:
        self.log = ArmPoseWriter(path, known_arms=tuple(self.arms))
        self._log_tick = self.clock.every(1 / 33.0, self._log_row)

    def _log_row(self, t: float) -> None:
        if self.log is not None:
            for arm_id, arm in self.arms.items():
                self.log.write(t, arm_id, arm.read_state().q_rad)

    def stop_joint_log(self) -> None:
        if self._log_tick is not None:
            self.clock.cancel(self._log_tick)
            self._log_tick = None
        if self.log is not None:
            log, self.log = self.log, None
            log.close()

    def close(self) -> None:
        self.closed = True
