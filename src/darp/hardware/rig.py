"""``HardwareRig``: the real dual-arm rig as a :class:`RigBackend` (two Z1 arms, two wrist RealSense
cameras, the wall clock, the ~33 Hz joint logger), assembled from a rig YAML file.

The geometry (arm ids, camera serials, park poses) comes from :func:`darp.kinematics.rig.load_rig`;
how to reach the hardware comes from the file's optional ``hardware:`` section
(:mod:`darp.hardware.settings`). :meth:`HardwareRig.open` connects everything or nothing: a failure
part-way closes what was already connected. :meth:`HardwareRig.close` finishes recordings and the joint
log, brakes and holds the arms and stops the SDK loops (it never makes an arm passive).

Time is the host's ``time.time()``: the joint log's ``time_s`` and the cameras' global timestamps
(milliseconds) are on the same clock, as darp's survey format requires.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from darp.backend import ArmBackend, CameraBackend, Clock, RigBackend, RigFault
from darp.errors import DarpError, HardwareError
from darp.hardware.joint_logger import JointLogger
from darp.hardware.realsense_camera import RealSenseCamera
from darp.hardware.settings import HardwareSettings, load_hardware_settings
from darp.hardware.z1_arm import Z1Arm
from darp.kinematics.rig import Rig, default_rig_path, load_rig

log = logging.getLogger(__name__)


class WallClock(Clock):
    """The host clock: Unix time in seconds (the clock of RealSense global timestamps)."""

    def now(self) -> float:
        return time.time()

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            time.sleep(duration_s)


class HardwareRig(RigBackend):
    """Two Z1 arms and their wrist cameras. Use :meth:`open` (connects) and ``with``/:meth:`close`."""

    def __init__(self, rig: Rig, settings: HardwareSettings | None = None, *,
                 arms: dict[str, ArmBackend] | None = None, cameras: dict[str, CameraBackend] | None = None,
                 clock: Clock | None = None, companions: Sequence[Any] = ()) -> None:
        """Build (not connect) the backends; ``arms``/``cameras`` replace the SDK-backed ones (tests, or twin
        cameras following these arms); ``clock`` replaces the wall clock (one that renders such cameras as
        time passes); ``companions`` are closed after everything else (e.g. the twin those cameras belong to)."""
        self.rig = rig
        self.settings = settings or HardwareSettings.defaults(rig.arm_ids)
        self.clock = clock if clock is not None else WallClock()
        self.companions = list(companions)
        s = self.settings
        self.arms = arms if arms is not None else {
            arm_id: Z1Arm(arm_id, s.arms[arm_id], motion=s.motion) for arm_id in rig.arm_ids}
        self.cameras = cameras if cameras is not None else {
            arm_id: RealSenseCamera(rig.arms[arm_id].camera_serial, s.cameras, arm_id=arm_id) for arm_id in rig.arm_ids}
        self._logger: JointLogger | None = None
        self.recordings: dict[str, Path] = {}

    @classmethod
    def open(cls, rig_path: str | Path | None = None, *, connect_timeout_s: float = 3.0) -> HardwareRig:
        """Load ``rig_path`` (default: the packaged rig), connect both arms and start both cameras."""
        path = default_rig_path() if rig_path is None else Path(rig_path)
        rig = load_rig(path)
        hardware = cls(rig, load_hardware_settings(path, rig.arm_ids))
        hardware.connect(connect_timeout_s)
        return hardware

    def connect(self, timeout_s: float = 3.0) -> None:
        """Connect the arms (holding their poses) and start the cameras' live streams; all or nothing.

        ``timeout_s``: how long each arm's controller may take to answer.
        """
        try:
            for arm_id, arm in self.arms.items():
                if hasattr(arm, "connect"):
                    arm.connect(timeout_s)
                log.info("%s connected", arm_id)
            for camera in self.cameras.values():
                if hasattr(camera, "open"):
                    camera.open()
        except BaseException:
            self.close()
            raise

    # -- recording helpers ------------------------------------------------------------------------
    def start_recordings(self, folder: str | Path) -> dict[str, Path]:
        """Start every camera recording to ``folder/cam<serial>.bag``; returns the paths actually written."""
        folder = Path(folder)
        for arm_id, camera in self.cameras.items():
            written = camera.start_recording(folder / f"cam{camera.serial}.bag")
            self.recordings[arm_id] = Path(written) if written is not None else folder / f"cam{camera.serial}.bag"
        return dict(self.recordings)

    def stop_recordings(self) -> dict[str, Path]:
        """Stop every camera's recording; returns the finished files by arm id."""
        for camera in self.cameras.values():
            camera.stop_recording()
        done, self.recordings = self.recordings, {}
        return done

    # -- RigBackend -------------------------------------------------------------------------------
    def start_joint_log(self, path: Path) -> None:
        """Log both arms to ``path`` (``arm_poses.csv``) at the configured rate (~33 Hz)."""
        if self._logger is not None:
            raise HardwareError("the joint log is already running", self._logger.path)
        logger = JointLogger(self.arms, path, rate_hz=self.settings.joint_log_hz)
        logger.start()
        self._logger = logger

    def stop_joint_log(self) -> None:
        """Stop the joint log and close the file (raises if the logger failed while running)."""
        logger, self._logger = self._logger, None
        if logger is not None:
            logger.stop()

    @property
    def joint_logger(self) -> JointLogger | None:
        return self._logger

    def fault(self) -> RigFault | None:
        """The first arm whose control loop stopped (its controller left joint control: collision
        protection, an emergency stop), or None. Arms without a ``fault_error`` never report one."""
        faulted = [(arm_id, err) for arm_id, arm in self.arms.items()
                   if (err := getattr(arm, "fault_error", None)) is not None]
        if not faulted:
            return None
        return RigFault("; ".join(str(err) for _, err in faulted), tuple(a for a, _ in faulted))

    def park_q(self, arm_id: str) -> np.ndarray:
        """The rig file's park configuration of ``arm_id`` (SDK angles)."""
        return np.array(self.rig.arm(arm_id).park_q_rad, dtype=np.float64)

    def close(self) -> None:
        """Stop the log and recordings, brake and release the arms, stop the cameras (every step runs;
        the first failure is raised at the end)."""
        errors: list[BaseException] = []

        def attempt(action: Callable[[], object], what: str) -> None:
            try:
                action()
            except Exception as err:  # collected; the first is raised at the end
                log.error("closing the rig: %s: %s", what, err)
                errors.append(err)

        attempt(self.stop_joint_log, "joint log")
        for arm_id, camera in self.cameras.items():
            attempt(camera.close if hasattr(camera, "close") else camera.stop_recording, f"camera of {arm_id}")
        for arm_id, arm in self.arms.items():
            if hasattr(arm, "close"):
                attempt(arm.close, arm_id)
        for companion in self.companions:
            attempt(companion.close, type(companion).__name__)
        self.recordings = {}
        if errors:
            first = errors[0]
            if isinstance(first, DarpError):
                raise first
            raise HardwareError(f"closing the rig failed: {type(first).__name__}: {first}") from first


def open_rig(rig: Rig | str | Path | None = None, *, connect_timeout_s: float = 3.0) -> HardwareRig:
    """Connect the real rig described by ``rig``: a loaded :class:`Rig` (its ``hardware:`` section is read
    from ``rig.source`` when it came from a file, else defaults), a rig file, or None (the packaged rig)."""
    if not isinstance(rig, Rig):
        return HardwareRig.open(rig, connect_timeout_s=connect_timeout_s)
    if rig.source is not None and Path(rig.source).is_file():
        settings = load_hardware_settings(rig.source, rig.arm_ids)
    else:
        settings = HardwareSettings.defaults(rig.arm_ids)
    hardware = HardwareRig(rig, settings)
    hardware.connect(connect_timeout_s)
    return hardware


__all__ = ["HardwareRig", "WallClock", "open_rig"]
