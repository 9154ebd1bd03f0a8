"""The calibrated world frame: the rig's convention, realised from what the calibration measured.

darp's world frame (docs/rig-and-poses.md) is: origin on the table surface midway between the two
base origins, x from arm110's base towards arm111's, z up. A calibration solves in the first arm's
base frame (:mod:`darp.calibration.model`) and then places the world by that definition, using only
measured quantities:

- **z** = the normal of the board, which lies flat on the table (its printed face points up; the
  sign is chosen on the side of the bases' +z);
- **origin** = the midpoint of the two calibrated base origins (the Z1 base origin is the underside
  of its base, which stands on the table, so the midpoint lies on the table surface);
- **x** = the direction from the first base origin to the second, made orthogonal to z; y = z x x.

Why not "the first base is the world": joint 1's zero offset cannot be separated from the base yaw
(:mod:`darp.calibration.refine`), so the first base's yaw is not measurable; the line between the base
origins is, to a fraction of a millimetre. The twin draws its truth in the same definition
(:func:`darp.twin.truth.draw_true_rig`), so errors against truth measure the calibration, not the convention.
"""

from __future__ import annotations

import numpy as np

from darp.errors import CalibrationError, KinematicsError
from darp.kinematics.transforms import world_from_base_origins

WORLD_FRAME_TEXT = (
    "origin on the table surface midway between the base origins, x from arm110's base towards arm111's, "
    "z up (the table normal, measured as the normal of the calibration board lying on the table); "
    "realised from the calibrated base origins and board pose (darp.calibration.world_frame)"
)


def canonical_world(origin_a: np.ndarray, origin_b: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_frame_world`` of the world defined by two base origins and the up direction (all in one frame)."""
    try:
        return world_from_base_origins(origin_a, origin_b, up)
    except KinematicsError as err:
        raise CalibrationError(str(err)) from None


def board_up(T_ref_board: np.ndarray, T_ref_base_first: np.ndarray | None = None) -> np.ndarray:
    """Unit normal of the board's printed face (board -z), on the side of the first base's +z."""
    n = -np.asarray(T_ref_board, float)[:3, 2]
    z_base = np.array([0.0, 0.0, 1.0]) if T_ref_base_first is None else np.asarray(T_ref_base_first)[:3, 2]
    return n if n @ z_base >= 0 else -n


def world_from_reference(T_ref_base: dict[str, np.ndarray], T_ref_board: np.ndarray,
                         arms: tuple[str, ...]) -> np.ndarray:
    """``T_ref_world`` for a solve in the reference frame (first arm's base)."""
    if len(arms) != 2:
        raise CalibrationError(f"the world frame needs two arms, got {len(arms)}")
    a, b = arms
    return canonical_world(T_ref_base[a][:3, 3], T_ref_base[b][:3, 3], board_up(T_ref_board, T_ref_base[a]))


def tilt_deg(T_world_x: np.ndarray) -> float:
    """Angle (deg) between a frame's z axis and the world's z axis (how far a base leans)."""
    return float(np.degrees(np.arccos(np.clip(np.asarray(T_world_x)[2, 2], -1.0, 1.0))))


__all__ = ["WORLD_FRAME_TEXT", "board_up", "canonical_world", "tilt_deg", "world_from_reference"]
