"""Mistakes real pose data brings, found from the data itself, each reported in one line with the likely fix.

For hand-eye captures the check is that back-projected boards agree: with the right reading of the
poses, every capture places the board at the same spot in the base (``F_i X T_cam_board_i``). The
declared reading is solved (OpenCV's PARK, the board averaged) and so are the plausible misreadings:
poses inverted (flange-from-base, or camera-from-world, given as base-from-flange; also eye-to-hand
data solved as eye-in-hand and the reverse) and the quaternion's scalar at the other end. When a
misreading places the boards together much better, the solve stops and says by how much. (The screw
invariants of AX = XB, rotation angle and pitch, cannot see an inversion: both are unchanged by it,
which is why the test is the boards' agreement.) Translations far beyond an arm's reach mean
millimetres declared as metres (and the reverse).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from darp.errors import CalibrationError
from darp.kinematics.transforms import (
    invert_transform,
    quaternion_to_rotation,
    rotation_to_quaternion,
)

if TYPE_CHECKING:
    from darp.calibration.board import Board
    from darp.calibration.model import Observations
    from darp.formats.captures import CaptureFolder

MAX_REACH_M = 5.0  # flange positions beyond this from the base: not metres
MIN_SPREAD_M = 0.005  # all flange positions within 5 mm of each other when read as mm: not millimetres


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


def consistency_mm(F: np.ndarray, B: np.ndarray) -> float:
    """Median distance (mm) of the board origin placed by each capture from their mean, after a PARK solve."""
    try:
        R, t = cv2.calibrateHandEye([f[:3, :3] for f in F], [f[:3, 3] for f in F], [b[:3, :3] for b in B],
                                    [b[:3, 3] for b in B], method=cv2.CALIB_HAND_EYE_PARK)
    except cv2.error:
        return float("inf")
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, np.asarray(t).reshape(3)
    if not np.all(np.isfinite(X)):
        return float("inf")
    p = (F @ X @ B)[:, :3, 3]
    return float(1e3 * np.median(np.linalg.norm(p - np.median(p, axis=0), axis=1)))


def check_pose_conventions(folder: CaptureFolder[Board], obs: Observations, arm: str, ratio: float = 0.5,
                           min_mm: float = 3.0) -> dict[str, float]:
    """Raise a one-line :class:`CalibrationError` when a misreading of the poses places the boards much closer.

    Returns the median board disagreement (mm) of the declared reading and each alternative.
    """
    sel = obs.for_arm(arm)
    if obs.T_base_flange is None:
        return {}
    F = obs.T_base_flange[sel]
    B = obs.T_depth_board_pnp[sel]
    source = next((a.pose_source for a in folder.arms if a.arm == arm), folder.root)
    declared_F = invert_transform(F) if folder.eye_to_hand else F
    check_translation_unit(declared_F, folder.conventions.unit, source)
    res = {"declared": consistency_mm(F, B), "inverted": consistency_mm(invert_transform(F), B)}
    is_csv = source is not None and str(source).endswith(".csv")
    if is_csv:
        Fq = declared_F.copy()
        Fq[:, :3, :3] = swap_quaternion_order(declared_F[:, :3, :3], folder.conventions.quaternion)
        res["quaternion"] = consistency_mm(invert_transform(Fq) if folder.eye_to_hand else Fq, B)
    d = res["declared"]
    best = min(res, key=lambda k: res[k])
    if best != "declared" and d > min_mm and res[best] < ratio * d:
        other = "wxyz" if folder.conventions.quaternion == "xyzw" else "xyzw"
        fix = {"inverted": ("the poses fit as eye-in-hand, not eye-to-hand; drop --eye-to-hand / mode: eye_to_hand"
                            if folder.eye_to_hand else
                            "the poses look inverted (flange-from-base, or camera-from-world, given as "
                            "base-from-flange); give base-from-flange poses, or if the camera is fixed and the "
                            "board on the flange, use --eye-to-hand"),
               "quaternion": f"the quaternions look like {other}, not {folder.conventions.quaternion}; declare "
                             f"quaternion: {other}"}[best]
        read = "inverted" if best == "inverted" else f"read as {other}"
        raise CalibrationError(f"{source}: {fix} (back-projected boards disagree by {d:.1f} mm median as declared, "
                               f"{res[best]:.1f} mm {read})")
    return res


__all__ = ["check_pose_conventions", "check_translation_unit", "consistency_mm", "swap_quaternion_order"]
