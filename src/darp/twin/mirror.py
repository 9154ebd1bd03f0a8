"""Twin cameras for other arms: the twin's world and wrist cameras following arms it does not simulate.

:class:`MirrorTwin` is a :class:`~darp.twin.rig_backend.TwinRig` whose cameras render the scene (table,
object or ChArUco board, both arms) at the joint angles that *other* arm backends report, e.g. two Z1 arms
driven by Unitree's controller (darp.hardware with ``--twin-cameras``). Its arms' true angles are the
reported ones plus the true rig's joint-zero offsets (``q_true = q_sdk + dq``, as in the twin), so a
calibration taken through it solves for offsets, mounts and bases drawn from the twin's seed and is checked
against that truth; link deflection and encoder noise are not added (the arms' own states are used).

Time: the twin's simulated clock starts at the wall time of construction and is advanced to the wall
clock (:meth:`MirrorTwin.pump`) whenever the rig's clock sleeps or a camera is used, never past the newest
arm state collected, so frames are rendered from states that were really reported. A collector thread reads
each arm's state every few milliseconds into a history that the cameras interpolate. While the cameras
record, the clock stays where the recording started and the recorded frames are rendered when it stops
(rendering two cameras can be slower than real time on a small machine: rendered as it went, a survey
would wait for its frames, record more frames while waiting, and never end); live frames are rendered at
the wall clock meanwhile. Rendering never changes what the arms do.
:class:`MirrorClock` is that wall clock, :class:`MirrorCamera` a camera that pumps before it is used.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from darp.backend import ArmBackend, CameraBackend, Clock, LiveFrameSet
from darp.errors import TwinError
from darp.formats.realsense.types import Intrinsics
from darp.twin.clock import NS_PER_S
from darp.twin.rig_backend import TwinRig
from darp.twin.settings import TwinSettings

COLLECT_PERIOD_S = 0.004
KEEP_S = 2.0  # history kept before the simulated clock's present (IMU differences, the latest frame tick)


class _History:
    """One arm's reported joint angles over host time, interpolated linearly between samples."""

    def __init__(self, t_s: float, q: np.ndarray) -> None:
        self._t: list[float] = [t_s]
        self._q: list[np.ndarray] = [np.asarray(q, dtype=np.float64).copy()]
        self.frozen = False  # the arm stopped reporting (a fault): its last state holds from then on

    @property
    def last_t(self) -> float:
        return self._t[-1]

    def add(self, t_s: float, q: np.ndarray) -> None:
        if t_s > self._t[-1]:
            self._t.append(t_s)
            self._q.append(np.asarray(q, dtype=np.float64).copy())

    def q_at(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 6) angles at host times ``t_s`` (held constant outside the collected span)."""
        t = np.asarray(self._t)
        Q = np.asarray(self._q)
        return np.stack([np.interp(t_s, t, Q[:, j]) for j in range(6)], axis=1)

    def trim(self, before_s: float) -> None:
        k = int(np.searchsorted(np.asarray(self._t), before_s)) - 1
        if k > 0:
            del self._t[:k], self._q[:k]


class MirrorTwin(TwinRig):
    """The twin's world and cameras, driven by ``sources``' reported joint states (not by simulated arms).

    ``sources``: connected arm backends by arm id (one per arm of ``rig``); the other arguments are
    :class:`TwinRig`'s (object and placement for a survey, board and its pose for calibration captures).
    """

    def __init__(self, settings: TwinSettings, *, rig: Any, q_initial_rad: Mapping[str, np.ndarray],
                 obj: Any | None = None, placement: Any | None = None, board: Any | None = None,
                 T_world_board: np.ndarray | None = None, check_placement: bool = True) -> None:
        """Build the world and cameras with the arms at ``q_initial_rad`` (SDK angles, by arm id); then
        :meth:`follow` the arms. Building takes seconds of CPU (model compile, renderer) in this thread:
        do it before connecting arms whose control threads must keep running."""
        missing = set(rig.arm_ids) - set(q_initial_rad)
        if missing:
            raise TwinError(f"no starting joints for {', '.join(sorted(missing))}")
        now = time.time()
        settings = settings.with_timing(start_time_s=now)
        self._stop = threading.Event()
        self._collector: threading.Thread | None = None
        self._hist_lock = threading.Lock()
        self._finish_s: float | None = None
        super().__init__(settings, rig=rig, obj=obj, placement=placement, board=board, T_world_board=T_world_board,
                         q_initial_rad=dict(q_initial_rad), check_placement=check_placement)
        self.sources: dict[str, ArmBackend] = {}
        self._history = {a: _History(now, np.asarray(q_initial_rad[a], dtype=np.float64)) for a in rig.arm_ids}

    def follow(self, sources: Mapping[str, ArmBackend]) -> None:
        """Follow ``sources`` (connected arm backends, one per arm): collect their reported states from now on."""
        missing = set(self._history) - set(sources)
        if missing:
            raise TwinError(f"no reported states for {', '.join(sorted(missing))}")
        self.sources = {a: sources[a] for a in self._history}
        for arm_id, source in self.sources.items():
            state = source.read_state()
            with self._hist_lock:
                self._history[arm_id].add(state.time_s, state.q_rad)
        self._collector = threading.Thread(target=self._collect, name="twin-mirror", daemon=True)
        self._collector.start()

    # -- states -------------------------------------------------------------------------------------
    def _collect(self) -> None:
        while not self._stop.wait(COLLECT_PERIOD_S):
            for arm_id, source in self.sources.items():
                history = self._history[arm_id]
                if history.frozen:
                    continue
                try:
                    state = source.read_state()
                except Exception:  # a faulted arm reports no more: it is held at its last state
                    history.frozen = True
                    continue
                with self._hist_lock:
                    history.add(state.time_s, state.q_rad)

    def _q_true(self, arm_id: str, t_ns: np.ndarray) -> np.ndarray:
        host = self.clock.start_time_s + np.asarray(t_ns, dtype=np.float64) / NS_PER_S
        with self._hist_lock:
            q = self._history[arm_id].q_at(np.atleast_1d(host))
        q_true: np.ndarray = q + self.true_rig.arms[arm_id].joint_offsets_rad
        return q_true

    def prepare_world(self, t_ns: int) -> Any:
        if self._world_time_ns != t_ns:
            for arm_id in self._history:
                self.world.set_arm_q(arm_id, self._q_true(arm_id, np.array([t_ns]))[0])
            self.world.forward()
            self._world_time_ns = t_ns
        return self.world.data

    def true_camera_poses(self, arm_id: str, t_ns: np.ndarray) -> np.ndarray:
        poses: np.ndarray = self.true_rig.T_world_cam(arm_id, self._q_true(arm_id, np.atleast_1d(t_ns)))
        return poses

    def true_q(self, arm_id: str, t_ns: int) -> np.ndarray:
        q: np.ndarray = self._q_true(arm_id, np.array([t_ns]))[0]
        return q

    def _monitor_tick(self, now_ns: int) -> int:
        # the simulated arms never move here, and the reported arms' contacts are not monitored
        return now_ns + 3600 * NS_PER_S

    # -- time ---------------------------------------------------------------------------------------
    @property
    def recording(self) -> bool:
        return any(camera._recording for camera in self.cameras.values())

    def sim_time_ns(self, host_s: float) -> int:
        """Simulation nanoseconds of a host time."""
        return int((host_s - self.clock.start_time_s) * NS_PER_S)

    def newest_state_s(self) -> float:
        """The host time up to which every arm that still reports has reported (or now, if none does)."""
        with self._hist_lock:
            live = [h.last_t for h in self._history.values() if not h.frozen]
        return min([time.time(), *live])

    def finish_time_s(self) -> float:
        """Where recordings being stopped end: the newest states when the first of them was asked to stop (the
        cameras stopped one after the other all end there, however long the first one took to render)."""
        if self._finish_s is None:
            self._finish_s = self.newest_state_s()
        return self._finish_s

    def pump(self, *, finish_recordings: bool = False) -> None:
        """Advance the simulated clock to the present (the newest reported states). While a camera records,
        only with ``finish_recordings`` (to :meth:`finish_time_s`): recorded frames are rendered when the
        recording stops, from the collected states, so rendering slower than real time never holds up the
        arms' survey."""
        if self.recording and not finish_recordings:
            return
        until_s = self.finish_time_s() if finish_recordings else self.newest_state_s()
        target_ns = self.sim_time_ns(until_s)
        if target_ns > self.clock.elapsed_ns:
            self.clock.advance_to(target_ns)
        with self._hist_lock:
            for h in self._history.values():
                h.trim(self.clock.now() - KEEP_S)

    def close(self) -> None:
        self._stop.set()
        if self._collector is not None:
            self._collector.join(timeout=1.0)
        super().close()


class MirrorClock(Clock):
    """The wall clock (host seconds) of a rig whose cameras are a :class:`MirrorTwin`: sleeping renders."""

    def __init__(self, mirror: MirrorTwin) -> None:
        self.mirror = mirror

    def now(self) -> float:
        return time.time()

    def sleep(self, duration_s: float) -> None:
        end = time.time() + max(duration_s, 0.0)
        self.mirror.pump()
        remaining = end - time.time()
        if remaining > 0:
            time.sleep(remaining)


class MirrorCamera(CameraBackend):
    """A :class:`MirrorTwin` camera for another rig: the twin is brought up to the present before each use."""

    def __init__(self, mirror: MirrorTwin, arm_id: str) -> None:
        self.mirror = mirror
        self.arm_id = arm_id
        self.camera = mirror.cameras[arm_id]
        self.serial = self.camera.serial

    def start_recording(self, path: Path) -> Path | None:
        self.mirror.pump()
        self.camera.start_recording(path)
        return None

    def stop_recording(self) -> Path | None:
        self.mirror.pump(finish_recordings=True)  # render every frame of the recording up to the stop
        self.camera.stop_recording()
        if not self.mirror.recording:
            self.mirror._finish_s = None
        return None

    def latest_frameset(self) -> LiveFrameSet:
        """The latest frame tick on the wall clock (rendered now; while recording, ahead of the recording's
        rendering, which catches up when it stops)."""
        self.mirror.pump()
        if not self.mirror.recording:
            return self.camera.latest_frameset()
        t_ns = self.mirror.sim_time_ns(self.mirror.newest_state_s())
        n = max(0, (t_ns - self.camera.phase_ns) * self.camera.spec.fps // NS_PER_S)
        return self.camera.frameset_at(int(n), self.camera.frame_time_ns(int(n)))

    @property
    def depth_intrinsics(self) -> Intrinsics:
        return self.camera.depth_intrinsics

    def close(self) -> None:
        self.camera.abort_recording()


__all__ = ["MirrorCamera", "MirrorClock", "MirrorTwin"]
