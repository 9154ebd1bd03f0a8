"""Calibration captures on the digital twin (darp.calibration's capture plan run on darp.twin's rig).

Used by ``darp calib capture --twin``, the benchmarks, the studies and the tests. Builds the twin with a
ChArUco board lying face up on the table, plans the captures on the *nominal* rig, runs them on
:class:`darp.twin.rig_backend.TwinRig` and writes the capture folder plus ``truth/`` (the twin's true
calibration, its settings and the board pose), which ``darp calib solve`` uses to report errors against
truth. ``mount_offsets`` moves camera mounts (in the flange frame) to simulate a knocked camera for
``darp calib check``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from darp.calibration.board import DEFAULT_BOARD
from darp.calibration.capture_run import CaptureRunSettings, run_capture_plan
from darp.calibration.captures import CaptureSet, CaptureWriter
from darp.calibration.plan import CapturePlan, PlanSettings, default_board_pose, plan_captures
from darp.formats.atomic import write_json_atomic
from darp.formats.calibration import CharucoBoardSpec, write_calibration
from darp.kinematics.rig import Rig, load_rig


def moved_rig(rig: Rig, mount_offsets: dict[str, np.ndarray]) -> Rig:
    """``rig`` with camera mounts moved: ``T_wrist_cam <- T_offset @ T_wrist_cam`` per arm."""
    arms = {a: (dataclasses.replace(cfg, T_wrist_cam=np.asarray(mount_offsets[a]) @ cfg.T_wrist_cam)
                if a in mount_offsets else cfg) for a, cfg in rig.arms.items()}
    return dataclasses.replace(rig, arms=arms)


def capture_twin(out: str | Path, *, seed: int = 0, profile: str = "realistic", n_per_arm: int = 30,
                 board: CharucoBoardSpec = DEFAULT_BOARD, rig: Rig | None = None, plan: CapturePlan | None = None,
                 plan_seed: int | None = None, stream: str = "color", resolution: tuple[int, int] = (640, 480),
                 mount_offsets: dict[str, np.ndarray] | None = None, overwrite: bool = False,
                 on_capture: Callable[[str, int], None] | None = None, settings: Any | None = None) -> CaptureSet:
    """Plan (unless given) and run calibration captures on the twin; returns the capture folder.

    ``settings``: the twin's :class:`~darp.twin.settings.TwinSettings` (default: ``profile`` with ``seed``)."""
    from darp.twin.objects.board import BOARD_THICKNESS_M
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    nominal = rig or load_rig()
    T_world_board = plan.T_world_board if plan is not None else default_board_pose(
        nominal, board, thickness_m=BOARD_THICKNESS_M + 2e-4)
    if plan is None:
        plan = plan_captures(nominal, board, T_world_board, settings=PlanSettings(n_per_arm=n_per_arm),
                             seed=seed if plan_seed is None else plan_seed)
    if settings is None:
        settings = TwinSettings.from_profile(profile, seed=seed)
    settings = settings.with_camera(width=resolution[0], height=resolution[1], imu=False)
    true_rig = moved_rig(nominal, mount_offsets) if mount_offsets else nominal
    offsets = {a: np.asarray(T).tolist() for a, T in (mount_offsets or {}).items()}
    writer = CaptureWriter(out, board, source=f"twin:{profile}:seed{seed}", overwrite=overwrite,
                           notes={"profile": profile, "seed": seed, "plan_seed": plan.seed, "mount_offsets": offsets})
    twin = TwinRig(settings, rig=true_rig, board=board, T_world_board=T_world_board)
    with twin:
        park = {a: twin.park_q(a) for a in twin.arms}
        run_capture_plan(twin, plan, writer, park_q=park, settings=CaptureRunSettings(stream=stream, joint_reads=10),
                         on_capture=on_capture)
        truth = Path(out) / "truth"
        write_calibration(truth / "calibration.json", twin.true_rig.calibration(settings))
        settings.save(truth / "settings.yaml")
        write_json_atomic(truth / "board.json", {"T_world_board": np.asarray(T_world_board).tolist()})
    return writer.close()


__all__ = ["capture_twin", "moved_rig"]
