"""The backend interface between the acquisition procedure and a rig: the digital twin or real hardware.

One survey procedure drives both. A backend provides a clock, two arms and two cameras:

- :class:`Clock`: ``now()`` in seconds on the host clock and ``sleep(dt)``. The twin's clock is simulated
  time: sleeping advances the simulation (arm motion, the joint log, camera frames), so a survey runs as
  fast as rendering allows and is deterministic for a given seed. The hardware clock is the wall clock.
- :class:`ArmBackend`: read the joint state with its timestamp, command a joint target without blocking,
  report whether motion is done, stop.
- :class:`CameraBackend`: start and stop continuous recording to a file, and give the latest frame set
  for live decisions (localisation).
- :class:`RigBackend`: the two arms and cameras by arm id, plus the joint logger that writes
  ``arm_poses.csv`` at about 33 Hz for the whole survey.

Arm ids are ``arm110`` and ``arm111``; joint vectors are six angles in radians (Z1 SDK order).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Self

import numpy as np

from darp.formats.realsense.types import Intrinsics
from darp.kinematics.transforms import invert_transform


@dataclass(frozen=True)
class JointState:
    """Joint state of one arm at ``time_s`` (host clock)."""

    time_s: float
    q_rad: np.ndarray  # (6,)
    qd_rad_s: np.ndarray  # (6,)


@dataclass
class LiveFrameSet:
    """The latest frames of a camera, decoded for live decisions (not for the recording)."""

    timestamp_s: float  # host clock
    depth_m: np.ndarray  # (H, W) float32 metres, 0 where invalid
    depth_intrinsics: Intrinsics
    colour_bgr: np.ndarray | None = None  # (H, W, 3) uint8, colour camera's own intrinsics
    colour_intrinsics: Intrinsics | None = None
    T_color_depth: np.ndarray | None = None  # 4x4 librealsense extrinsic depth -> colour (the one stored)
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def T_depth_color(self) -> np.ndarray | None:
        """The colour camera's pose in the depth frame (colour -> depth): the inverse of ``T_color_depth``."""
        return None if self.T_color_depth is None else invert_transform(self.T_color_depth)


@dataclass(frozen=True)
class RigFault:
    """Why the rig stopped moving: a contact (twin) or a controller fault (hardware), and the arms involved."""

    message: str
    arms: tuple[str, ...] = ()


class Clock(ABC):
    """Host-clock time source. Both the joint log and camera timestamps use it."""

    @abstractmethod
    def now(self) -> float:
        """Seconds on the host clock."""

    @abstractmethod
    def sleep(self, duration_s: float) -> None:
        """Let ``duration_s`` seconds pass (the twin simulates them)."""


class ArmBackend(ABC):
    """One Z1 arm."""

    arm_id: str

    @abstractmethod
    def read_state(self) -> JointState:
        """Current joint state (as the SDK reports it: raw encoder angles, no joint-zero correction)."""

    @abstractmethod
    def move_to(self, q_target_rad: np.ndarray, max_speed_rad_s: float | None = None) -> None:
        """Start a joint-space move to ``q_target_rad``; returns at once (non-blocking)."""

    @abstractmethod
    def is_moving(self) -> bool:
        """True while a commanded move is under way."""

    @abstractmethod
    def stop(self) -> None:
        """Stop any motion as soon as possible (holds position)."""


class CameraBackend(ABC):
    """One wrist RealSense camera."""

    serial: str

    @abstractmethod
    def start_recording(self, path: Path) -> Path | None:
        """Start continuous recording of every stream to ``path`` (``cam<serial>.bag``).

        Returns the path actually written when it differs (pyrealsense2 >= 2.58 records ``.db3``).
        """

    @abstractmethod
    def stop_recording(self) -> Path | None:
        """Stop recording and close the file; a backend may return the finished file's path."""

    @abstractmethod
    def latest_frameset(self) -> LiveFrameSet:
        """The most recent frames, for localisation and checks during a survey."""

    @property
    @abstractmethod
    def depth_intrinsics(self) -> Intrinsics:
        """Intrinsics of the depth (left infrared) stream."""


class RigBackend(ABC):
    """Two arms, their cameras and a clock; owns the joint logger."""

    clock: Clock
    arms: Mapping[str, ArmBackend]  # read-only here, so a backend may hold its own arm type
    cameras: Mapping[str, CameraBackend]  # by arm id

    @abstractmethod
    def start_joint_log(self, path: Path) -> None:
        """Start logging both arms' joint states to ``arm_poses.csv`` at about 33 Hz."""

    @abstractmethod
    def stop_joint_log(self) -> None:
        """Stop the joint log and close the file."""

    def close(self) -> None:
        """Release hardware or simulation resources (default: nothing)."""
        return None

    def fault(self) -> RigFault | None:
        """The fault that stopped the rig's motion, if any (default: none is ever reported).

        The twin reports the first contact of a moving arm (and has stopped both arms by then); the hardware
        reports an arm whose controller left joint control (collision protection, emergency stop). Once a
        fault is reported no planned move may be commanded: the survey stops, parks what is safe to park
        and rejects the episode.
        """
        return None

    def wait_until_still(self, arm_id: str, timeout_s: float, poll_s: float = 0.01) -> bool:
        """Sleep on the rig's clock until ``arm_id`` stops moving; False on timeout or on a :meth:`fault`."""
        deadline = self.clock.now() + timeout_s
        arm = self.arms[arm_id]
        while arm.is_moving():
            if self.fault() is not None:
                return False
            if self.clock.now() >= deadline:
                return False
            self.clock.sleep(poll_s)
        return True

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
