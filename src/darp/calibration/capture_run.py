"""Execute a capture plan on a rig backend (twin or hardware) and write the capture folder.

One arm moves at a time; the other waits at its park pose. At each planned pose the arm is commanded
(non-blocking MoveJ), the runner waits until it reports still plus ``settle_s`` (controller settling
and at least one fresh camera frame), then averages ``joint_reads`` joint readings taken
``read_interval_s`` apart (encoder noise averages down; the arm is at rest) and takes the camera's
latest frame set.

Which image: **colour** by default. The D435's left IR imager (ir1) shares the depth frame and has a
global shutter, but with the emitter on its image carries the projector's dots, which disturb corner
detection (the twin simulates them too); colour has a higher resolution and, captured at rest, its
rolling shutter does not matter. The depth-to-colour factory extrinsic is recorded with each capture
(``T_depth_stream``) so that the hand-eye is estimated for the depth optical frame, the frame every
survey pose uses. ``stream="ir1"`` is available for rigs that switch the emitter off.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from darp.backend import RigBackend
from darp.calibration.captures import CaptureWriter
from darp.calibration.plan import CapturePlan
from darp.errors import CalibrationError

MOVED_RAD = 1e-6  # a joint commanded further than this moved (its direction is recorded)


@dataclass(frozen=True)
class CaptureRunSettings:
    """Timing of the capture loop."""

    stream: str = "color"
    settle_s: float = 0.25
    joint_reads: int = 5
    read_interval_s: float = 0.02
    move_timeout_s: float = 60.0
    max_speed_rad_s: float | None = None
    depth: bool = True  # also store the depth image (for the depth correction, darp.calibration.depth_fit)


def _grab_image(frameset: Any, stream: str) -> tuple[np.ndarray, Any, np.ndarray]:
    """(image, intrinsics, T_depth_stream) of ``stream`` from a live frame set."""
    if stream == "color":
        if frameset.colour_bgr is None or frameset.colour_intrinsics is None:
            raise CalibrationError("the camera gave no colour image; capture with stream='ir1'")
        if frameset.T_color_depth is None:
            raise CalibrationError("the camera gave no depth-to-colour extrinsic; capture with stream='ir1'")
        return frameset.colour_bgr, frameset.colour_intrinsics, np.asarray(frameset.T_depth_color, dtype=float)
    if stream == "ir1":
        ir1 = frameset.extra.get("ir1") if isinstance(frameset.extra, dict) else None
        if ir1 is None:
            raise CalibrationError("the camera gave no infrared image (ir1)")
        return np.asarray(ir1), frameset.depth_intrinsics, np.eye(4)
    raise CalibrationError(f"unknown capture stream {stream!r} (color, ir1)")


@dataclass
class _MoveDirections:
    """Each arm's last commanded target (from the park pose, where the arms are assumed to start) and the
    direction each joint last moved in (-1 / 0 / +1: what backlash depends on)."""

    target: dict[str, np.ndarray]
    direction: dict[str, np.ndarray] = field(default_factory=dict)

    def command(self, arm: str, q: np.ndarray) -> None:
        if arm not in self.target:
            return
        step = q - self.target[arm]
        self.direction[arm] = np.where(np.abs(step) > MOVED_RAD, np.sign(step), self.of(arm))
        self.target[arm] = q.copy()

    def of(self, arm: str) -> np.ndarray:
        return self.direction.get(arm, np.zeros(6))


def _move(rig: RigBackend, arm: str, q: np.ndarray, s: CaptureRunSettings,
          moves: _MoveDirections | None = None) -> None:
    """Command ``arm`` to ``q`` and wait until still; ``moves`` tracks the joints' move directions. No extra
    joint reading is taken, so a run's readings (and the twin's noise draws) are those of a run without it."""
    q = np.asarray(q, dtype=float)
    if moves is not None:
        moves.command(arm, q)
    rig.arms[arm].move_to(q, s.max_speed_rad_s)
    if not rig.wait_until_still(arm, s.move_timeout_s):
        rig.arms[arm].stop()
        raise CalibrationError(f"{arm} did not reach its capture pose within {s.move_timeout_s} s")


def run_capture_plan(rig: RigBackend, plan: CapturePlan, writer: CaptureWriter, *,
                     park_q: dict[str, np.ndarray], settings: CaptureRunSettings | None = None,
                     on_capture: Callable[[str, int], None] | None = None) -> int:
    """Move through every planned pose, one arm at a time, writing one capture per pose; returns the count.

    ``park_q``: park joints per arm (the rig file's). ``on_capture(arm, k)`` is called after each capture.
    """
    s = settings or CaptureRunSettings()
    count = 0
    moves = _MoveDirections({a: np.asarray(q, dtype=float).copy() for a, q in park_q.items()})
    for arm, poses in plan.poses.items():
        if arm not in rig.arms or arm not in rig.cameras:
            raise CalibrationError(f"the plan names arm {arm!r} but the rig has {', '.join(rig.arms)}")
        for other in rig.arms:
            if other != arm:
                _move(rig, other, park_q[other], s, moves)
        camera = rig.cameras[arm]
        for k, pose in enumerate(poses):
            if pose.via_park:
                _move(rig, arm, park_q[arm], s, moves)
            _move(rig, arm, pose.q_rad, s, moves)
            rig.clock.sleep(s.settle_s)
            reads = []
            for _ in range(max(1, s.joint_reads)):
                reads.append(rig.arms[arm].read_state())
                rig.clock.sleep(s.read_interval_s)
            q = np.array([r.q_rad for r in reads])
            frameset = camera.latest_frameset()
            image, intr, T_depth_stream = _grab_image(frameset, s.stream)
            depth = frameset.depth_m if s.depth and frameset.depth_m is not None else None
            writer.add(depth_m=depth, depth_intrinsics=frameset.depth_intrinsics if depth is not None else None,
                       arm=arm, camera_serial=camera.serial, time_s=float(np.mean([r.time_s for r in reads])),
                       q_rad=q.mean(axis=0), q_std_rad=q.std(axis=0), image=image, intrinsics=intr,
                       T_depth_stream=T_depth_stream, stream=s.stream,
                       extra={"planned_q_rad": pose.q_rad.tolist(), "frame_time_s": float(frameset.timestamp_s),
                              "move_direction": moves.of(arm).astype(int).tolist()})
            count += 1
            if on_capture is not None:
                on_capture(arm, k)
        _move(rig, arm, park_q[arm], s, moves)
    return count


__all__ = ["CaptureRunSettings", "run_capture_plan"]
