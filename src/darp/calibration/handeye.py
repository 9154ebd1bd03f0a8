"""Initial hand-eye per arm with OpenCV, and the OpenCV-only calibrations used for comparison.

Per arm, with the logged joints (no joint-zero correction: unknown at this stage) and the single-image
board poses from PnP:

- ``cv2.calibrateHandEye`` (AX = XB) with TSAI, PARK, HORAUD, ANDREFF and DANIILIDIS. Methods disagree
  on noisy data, and one of them can fail outright on a given set, so each is *scored*: the board pose
  in the base implied by every capture (``fk(q) @ X @ T_cam_board``) is averaged and every corner is
  re-predicted through the chain; the method with the smallest median reprojection error wins.
- ``cv2.calibrateRobotWorldHandEye`` (AX = ZB) with SHAH and LI, which estimate the hand-eye and the
  board pose in the base together; scored the same way.

The winner initialises the joint refinement; all of them are kept for the side-by-side table.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from darp.calibration.geometry import mean_pose
from darp.calibration.model import ChainParams, Observations, flange_poses, reprojection_errors
from darp.errors import CalibrationError
from darp.kinematics.transforms import invert_transform

HAND_EYE_METHODS: dict[str, int] = {
    "TSAI": cv2.CALIB_HAND_EYE_TSAI, "PARK": cv2.CALIB_HAND_EYE_PARK, "HORAUD": cv2.CALIB_HAND_EYE_HORAUD,
    "ANDREFF": cv2.CALIB_HAND_EYE_ANDREFF, "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
ROBOT_WORLD_METHODS: dict[str, int] = {"SHAH": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
                                       "LI": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI}
MIN_CAPTURES = 3


@dataclass
class HandEyeEstimate:
    """One OpenCV solution for one arm: hand-eye, board in that arm's base, and its score."""

    arm: str
    method: str  # e.g. "calibrateHandEye/TSAI"
    T_wrist_cam: np.ndarray
    T_base_board: np.ndarray
    median_px: float  # median reprojection error of every corner through the chain (dq = 0)
    ok: bool = True


def _rt(T: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    return [t[:3, :3].copy() for t in T], [t[:3, 3].reshape(3, 1).copy() for t in T]


def _to_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t).reshape(3)
    return T


def _single_arm_params(arm: str, X: np.ndarray, T_base_board: np.ndarray) -> ChainParams:
    return ChainParams(arms=(arm,), T_ref_base={arm: np.eye(4)}, T_wrist_cam={arm: X},
                       dq={arm: np.zeros(6)}, T_ref_board=T_base_board)


def _arm_obs(obs: Observations, arm: str) -> Observations:
    sub = obs.subset(obs.for_arm(arm))
    sub.arms = (arm,)
    sub.arm_index = np.zeros(sub.n_captures, dtype=int)
    return sub


def score(obs_arm: Observations, arm: str, X: np.ndarray, T_base_board: np.ndarray | None = None,
          wrist_frame: str = "flange") -> tuple[np.ndarray, float]:
    """(board pose in the base, median reprojection px) for hand-eye ``X`` on one arm's observations.

    Without ``T_base_board`` the board pose is the mean of the per-capture predictions.
    """
    A = flange_poses(obs_arm, np.arange(obs_arm.n_captures), np.zeros(6), wrist_frame)
    if T_base_board is None:
        T_base_board = mean_pose(A @ X @ obs_arm.T_depth_board_pnp)
    err = reprojection_errors(_single_arm_params(arm, X, T_base_board), obs_arm, wrist_frame)
    return T_base_board, float(np.median(err)) if err.size else float("inf")


def _valid(T: np.ndarray, max_translation_m: float = 1.0) -> bool:
    R = T[:3, :3]
    return bool(np.all(np.isfinite(T)) and abs(np.linalg.det(R) - 1.0) < 1e-3
                and np.linalg.norm(T[:3, 3]) < max_translation_m)


def opencv_hand_eye(obs: Observations, arm: str, wrist_frame: str = "flange") -> list[HandEyeEstimate]:
    """Every ``calibrateHandEye`` and ``calibrateRobotWorldHandEye`` method on one arm, scored."""
    sub = _arm_obs(obs, arm)
    if sub.n_captures < MIN_CAPTURES:
        raise CalibrationError(f"{arm}: {sub.n_captures} usable captures; hand-eye needs at least {MIN_CAPTURES}")
    A = flange_poses(sub, np.arange(sub.n_captures), np.zeros(6), wrist_frame)  # T_base_flange
    B = sub.T_depth_board_pnp  # T_cam_board
    # A wrist camera sits within 1 m of the flange; measured poses (any arm) may be eye-to-hand, where the
    # solved "hand-eye" is the camera in the base, metres away.
    reach = 1.0 if sub.T_base_flange is None else 20.0
    R_a, t_a = _rt(A)
    R_b, t_b = _rt(B)
    out: list[HandEyeEstimate] = []
    for name, flag in HAND_EYE_METHODS.items():
        try:
            R, t = cv2.calibrateHandEye(R_a, t_a, R_b, t_b, method=flag)
            X = _to_T(R, t)
        except cv2.error:
            X = np.full((4, 4), np.nan)
        ok = _valid(X, reach)
        T_bb, px = score(sub, arm, X, None, wrist_frame) if ok else (np.full((4, 4), np.nan), float("inf"))
        out.append(HandEyeEstimate(arm, f"calibrateHandEye/{name}", X, T_bb, px, ok))
    R_fb, t_fb = _rt(invert_transform(A))  # base -> gripper
    for name, flag in ROBOT_WORLD_METHODS.items():
        try:
            R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(R_b, t_b, R_fb, t_fb, method=flag)
            X = invert_transform(_to_T(R_gc, t_gc))
            T_board_base = _to_T(R_bw, t_bw)
            T_bb = invert_transform(T_board_base)
        except cv2.error:
            X, T_bb = np.full((4, 4), np.nan), np.full((4, 4), np.nan)
        ok = _valid(X, reach) and bool(np.all(np.isfinite(T_bb)))
        px = score(sub, arm, X, T_bb, wrist_frame)[1] if ok else float("inf")
        out.append(HandEyeEstimate(arm, f"calibrateRobotWorldHandEye/{name}", X, T_bb, px, ok))
    return out


def best(estimates: list[HandEyeEstimate], family: str | None = None) -> HandEyeEstimate:
    """The lowest-scoring valid estimate (of one family, e.g. ``"calibrateHandEye"``)."""
    pool = [e for e in estimates if e.ok and (family is None or e.method.startswith(family + "/"))]
    if not pool:
        arm = estimates[0].arm if estimates else "?"
        raise CalibrationError(f"{arm}: every OpenCV hand-eye method failed on these captures")
    return min(pool, key=lambda e: e.median_px)


def chain_from_estimates(chosen: dict[str, HandEyeEstimate], arms: tuple[str, ...]) -> ChainParams:
    """Joint-refinement start (and the OpenCV-only calibration): reference = first arm's base.

    The board pose from the reference arm places the board; each other base follows from its own
    board estimate: ``T_ref_base = T_ref_board @ inv(T_base_board)``. Joint offsets are zero.
    """
    ref = arms[0]
    T_ref_board = chosen[ref].T_base_board
    return ChainParams(
        arms=arms,
        T_ref_base={a: (np.eye(4) if a == ref else T_ref_board @ invert_transform(chosen[a].T_base_board))
                    for a in arms},
        T_wrist_cam={a: chosen[a].T_wrist_cam.copy() for a in arms},
        dq={a: np.zeros(6) for a in arms},
        T_ref_board=T_ref_board.copy(),
    )


__all__ = ["HAND_EYE_METHODS", "ROBOT_WORLD_METHODS", "HandEyeEstimate", "best", "chain_from_estimates",
           "opencv_hand_eye", "score"]
