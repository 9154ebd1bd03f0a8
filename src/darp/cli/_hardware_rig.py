"""The hardware commands' rig: real Z1 arms with RealSense cameras, or with twin cameras (``--twin-cameras``).

With twin cameras the arms are the rig file's Z1 arms (real ones, or Unitree's controller with simulated
motors: docs/hardware.md, "Vendor in the loop") and the cameras are the digital twin's, rendering the
table, the object or board and both arms at the joint angles the arms report
(:class:`darp.twin.mirror.MirrorTwin`). The arms are connected first; everything is closed if a later step
fails.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from darp.hardware.rig import HardwareRig
    from darp.twin.mirror import MirrorTwin


def twin_board_pose(rig: Any, board: Any) -> Any:
    """Where the twin's board lies (on the table, its thickness included), as ``darp calib capture --twin``."""
    from darp.calibration.plan import default_board_pose
    from darp.twin.objects.board import BOARD_THICKNESS_M

    return default_board_pose(rig, board, thickness_m=BOARD_THICKNESS_M + 2e-4)


def write_capture_truth(out: Path, mirror: MirrorTwin, T_world_board: Any) -> None:
    """``out/truth/``: the twin's true calibration, settings and board pose (read by ``darp calib solve``)."""
    import numpy as np

    from darp.formats.atomic import write_json_atomic
    from darp.formats.calibration import write_calibration

    truth = Path(out) / "truth"
    write_calibration(truth / "calibration.json", mirror.true_rig.calibration(mirror.settings))
    mirror.settings.save(truth / "settings.yaml")
    write_json_atomic(truth / "board.json", {"T_world_board": np.asarray(T_world_board).tolist()})


def open_hardware(rig_file: Path | None, *, twin_settings: Any = None,
                  **twin_scene: Any) -> tuple[HardwareRig, MirrorTwin | None]:
    """Connect the rig of ``rig_file`` (default: the packaged rig), with its RealSense cameras, or, given
    ``twin_settings`` (the twin's :class:`~darp.twin.settings.TwinSettings`), with twin cameras;
    ``twin_scene`` goes to :class:`~darp.twin.mirror.MirrorTwin` (``obj`` and ``placement``, or ``board`` and
    ``T_world_board``)."""
    from darp.hardware.rig import HardwareRig

    if twin_settings is None:
        return HardwareRig.open(rig_file), None
    from darp.hardware.settings import load_hardware_settings
    from darp.hardware.z1_arm import Z1Arm, probe_arm
    from darp.kinematics.rig import default_rig_path, load_rig
    from darp.twin.mirror import MirrorCamera, MirrorClock, MirrorTwin

    path = default_rig_path() if rig_file is None else Path(rig_file)
    rig = load_rig(path)
    settings = load_hardware_settings(path, rig.arm_ids)
    # Read where the arms are (no command), build the twin (seconds of CPU in this thread), then connect:
    # once connected, each arm's control thread must keep exchanging with its controller.
    q0 = {arm_id: probe_arm(arm_id, settings.arms[arm_id]).q_rad for arm_id in rig.arm_ids}
    mirror = MirrorTwin(twin_settings, rig=rig, q_initial_rad=q0, **twin_scene)
    arms = {arm_id: Z1Arm(arm_id, settings.arms[arm_id], motion=settings.motion) for arm_id in rig.arm_ids}
    hardware = HardwareRig(rig, settings, arms=dict(arms), cameras={a: MirrorCamera(mirror, a) for a in rig.arm_ids},
                           clock=MirrorClock(mirror), companions=[mirror])
    try:
        hardware.connect()
        mirror.follow(arms)
    except BaseException:
        hardware.close()
        raise
    return hardware, mirror


__all__ = ["open_hardware", "twin_board_pose", "write_capture_truth"]
