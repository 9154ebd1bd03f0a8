"""Mistakes real pose data brings, found from the data itself, each reported in one line with the likely fix.

For hand-eye captures the check is the rotation-angle invariant of AX = XB: the flange's rotation
between two captures and the camera's (seen through the board) turn by the same angle whatever the
hand-eye is. So the declared reading of the poses is compared with the plausible misreadings — poses
inverted (flange-from-base, or camera-from-world, given as base-from-flange), the quaternion's scalar
at the other end, eye-to-hand data solved as eye-in-hand — and when a misreading fits much better the
solve stops and names it. Translations far beyond an arm's reach mean millimetres declared as metres
(and the reverse).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from darp.errors import CalibrationError
from darp.kinematics.transforms import invert_transform, quaternion_to_rotation, rotation_to_quaternion

if TYPE_CHECKING:
    from darp.calibration.anyarm import CaptureFolder
    from darp.calibration.model import Observations

MAX_REACH_M = 5.0  # flange positions beyond this from the base: not metres
MIN_SPREAD_M = 0.005  # all flange positions within 5 mm of each other when read as mm: not millimetres


def _angles(R: np.ndarray) -> np.ndarray:
    return np.asarray(np.degrees(np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))), float)


def invariant_residual_deg(A: np.ndarray, B: np.ndarray, invert_a: bool = False) -> float:
    """Median |angle(A_i^-1 A_j) - angle(B_i B_j^-1)| (deg) over capture pairs.

    A: base-from-flange, B: camera-from-board.
    """
    RA, RB = A[:, :3, :3], B[:, :3, :3]
    if invert_a:
        RA = np.transpose(RA, (0, 2, 1))
    i, j = np.triu_indices(len(A), 1)
    a = _angles(np.transpose(RA[i], (0, 2, 1)) @ RA[j])
    b = _angles(RB[i] @ np.transpose(RB[j], (0, 2, 1)))
    keep = (a > 2.0) | (b > 2.0)  # pairs with a real rotation
    return float(np.median(np.abs(a - b)[keep])) if np.any(keep) else 0.0


def swap_quaternion_order(R: np.ndarray, declared: str) -> np.ndarray:
    """The rotations the same numbers give when read with the other quaternion order."""
    q = rotation_to_quaternion(R)  # (..., 4) xyzw
    if declared == "xyzw":  # the file holds x y z w; read as w x y z
        alt = q[..., [1, 2, 3, 0]]
    else:  # the file holds w x y z; read as x y z w
        alt = q[..., [3, 0, 1, 2]]
    return np.asarray(quaternion_to_rotation(alt))


def check_translation_unit(T: np.ndarray, unit: str, source: object) -> None:
    """Raise when flange translations are impossible in the declared unit."""
    t = np.asarray(T)[:, :3, 3]
    r = float(np.median(np.linalg.norm(t, axis=1)))
    spread = float(np.max(np.ptp(t, axis=0))) if len(t) > 1 else 1.0
    if r > MAX_REACH_M:
        raise CalibrationError(f"{source}: flange positions are {r:.0f} m from the base (median) with unit "
                               f"'{unit}': they look like millimetres; declare unit: mm")
    if unit == "mm" and spread < MIN_SPREAD_M:
        raise CalibrationError(f"{source}: flange positions span only {spread * 1e3:.2f} mm with unit 'mm': they "
                               "look like metres; declare unit: m")


def check_pose_conventions(folder: CaptureFolder, obs: Observations, arm: str, ratio: float = 0.5,
                           min_deg: float = 2.0) -> dict[str, float]:
    """Raise a one-line :class:`CalibrationError` when a misreading of the poses fits much better.

    Returns the median invariant residual (deg) of the declared reading and each alternative.
    """
    sel = obs.for_arm(arm)
    F = obs.T_base_flange[sel] if obs.T_base_flange is not None else None
    if F is None:
        return {}
    B = obs.T_depth_board_pnp[sel]
    source = next((a.pose_source for a in folder.arms if a.arm == arm), folder.root)
    declared_F = invert_transform(F) if folder.eye_to_hand else F
    check_translation_unit(declared_F, folder.conventions.unit, source)
    res = {"declared": invariant_residual_deg(F, B)}
    res["inverted"] = invariant_residual_deg(F, B, invert_a=True)
    Fq = F.copy()
    Fq[:, :3, :3] = swap_quaternion_order(F[:, :3, :3], folder.conventions.quaternion)
    if source is not None and str(source).endswith(".csv"):
        res["quaternion"] = invariant_residual_deg(Fq, B)
    best = min(res, key=lambda k: res[k])
    if best != "declared" and res["declared"] > min_deg and res[best] < ratio * res["declared"]:
        other = "wxyz" if folder.conventions.quaternion == "xyzw" else "xyzw"
        fix = {"inverted": ("the poses look inverted (flange-from-base or camera-from-world); give base-from-flange "
                            "poses, or if the camera is fixed and the board on the flange, use --eye-to-hand"
                            if not folder.eye_to_hand else
                            "the poses fit as eye-in-hand, not eye-to-hand; drop --eye-to-hand / mode: eye_to_hand"),
               "quaternion": f"the quaternions look like {other}, not {folder.conventions.quaternion}; declare "
                             f"quaternion: {other}"}[best]
        raise CalibrationError(f"{source}: {fix} (rotation-angle mismatch {res['declared']:.1f} deg as declared, "
                               f"{res[best]:.1f} deg read that way)")
    return res


__all__ = ["check_pose_conventions", "check_translation_unit", "invariant_residual_deg", "swap_quaternion_order"]
