"""Staleness check: do a few new captures still agree with a calibration?

The calibration's chain (eq. 1 with its bases, hand-eyes and joint offsets) predicts where each new
capture sees the board. The board may have been put back elsewhere since, so its pose is re-fitted
to all new captures of both arms at once (robust least squares, 6 unknowns; ``board_unmoved=True``
uses the pose stored in the calibration instead). Each capture's corners are then compared with the
prediction exactly like the held-out evaluation (:mod:`darp.calibration.evaluate`): 3-D corner error
(mm) and reprojection error (px).

An arm fails when its median error exceeds a limit derived from the calibration's *own* held-out
statistics (``residuals.heldout`` of each arm): ``max(k_median x held-out median, k_p90 x held-out
p90, floor)``. A moved camera mount, a shifted base or a changed joint zero shows as errors far above
what the calibration achieved on captures it had not seen; an unchanged rig stays at that level.
The board is also fitted to each arm's captures alone: an arm whose own captures disagree with each
other (error above its limit even then) has itself changed (mount or joint zeros); the two arms'
boards disagreeing while each is self-consistent points at a base that moved (or a mount, seen from
too few directions to tell). With one board and two arms, a change between the arms cannot always be
blamed on one of them: both arms are then reported stale.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from scipy.optimize import least_squares

from darp.calibration.captures import CaptureSet
from darp.calibration.detect import Detection, DetectionSettings, detect_captures
from darp.calibration.evaluate import corner_errors, summarise
from darp.calibration.geometry import delta, mean_pose
from darp.calibration.model import ChainParams, Observations, build_observations, camera_poses, predict_pixels
from darp.errors import CalibrationError
from darp.formats.calibration import Calibration
from darp.kinematics.transforms import pose_error


@dataclass(frozen=True)
class CheckSettings:
    """Limits of the staleness check, relative to the calibration's held-out errors."""

    k_median: float = 3.0
    k_p90: float = 1.5
    floor_mm: float = 0.5
    floor_px: float = 0.5
    min_captures: int = 1  # per arm present in the captures
    board_unmoved: bool = False
    wrist_frame: str = "flange"
    detection: DetectionSettings = field(default_factory=DetectionSettings)


@dataclass
class ArmCheck:
    """Verdict and numbers for one arm."""

    arm: str
    n_captures: int
    corner_3d_mm: dict[str, float]
    reprojection_px: dict[str, float]
    limit_mm: float
    limit_px: float
    ok: bool
    reasons: list[str]
    self_consistency_mm: float | None = None  # median 3-D error with the board fitted to this arm alone


@dataclass
class CheckResult:
    """The check's verdict: ``ok`` when every arm with captures agrees with the calibration."""

    ok: bool
    arms: dict[str, ArmCheck]
    board_disagreement: dict[str, float] | None
    T_world_board: np.ndarray
    rejected: dict[str, str]
    per_capture: dict[str, dict[str, float]]

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "verdict": "calibration holds" if self.ok else "calibration is stale",
                "arms": {a: vars(c) for a, c in self.arms.items()},
                "board_disagreement": self.board_disagreement, "T_world_board": self.T_world_board.tolist(),
                "rejected": self.rejected, "per_capture": self.per_capture}


def chain_from_calibration(cal: Calibration, arms: tuple[str, ...], T_world_board: np.ndarray) -> ChainParams:
    """The calibration as chain parameters whose reference frame is the world."""
    return ChainParams(arms=arms, T_ref_base={a: cal.arms[a].T_world_base.copy() for a in arms},
                       T_wrist_cam={a: cal.arms[a].T_wrist_cam.copy() for a in arms},
                       dq={a: np.asarray(cal.arms[a].joint_offsets_rad, float).copy() for a in arms},
                       T_ref_board=np.asarray(T_world_board, float).copy())


def fit_board(params: ChainParams, obs: Observations, wrist_frame: str = "flange") -> np.ndarray:
    """Board pose (reference frame) best explaining ``obs`` with every other unknown held (robust LSQ)."""
    start = mean_pose(camera_poses(params, obs, wrist_frame) @ obs.T_depth_board_pnp)
    p = params.copy()

    def fun(x: np.ndarray) -> np.ndarray:
        p.T_ref_board = start @ delta(x)
        return cast(np.ndarray, (predict_pixels(p, obs, wrist_frame) - obs.uv).ravel())

    res = least_squares(fun, np.zeros(6), loss="soft_l1", f_scale=1.0, x_scale=[1e-3] * 3 + [1e-3] * 3)
    return cast(np.ndarray, start @ delta(res.x))


def _limits(cal: Calibration, arm: str, s: CheckSettings, cal_path: Path | None = None) -> tuple[float, float]:
    held = cal.arms[arm].residuals.get("heldout") if cal.arms[arm].residuals else None
    if not held or "corner_3d_mm" not in held or "reprojection_px" not in held:
        raise CalibrationError(f"arms.{arm}.residuals: no held-out statistics "
                               "(solve with --folds >= 2 to make a calibration that can be checked)", cal_path)
    mm, px = held["corner_3d_mm"], held["reprojection_px"]
    return (max(s.k_median * float(mm["median"]), s.k_p90 * float(mm["p90"]), s.floor_mm),
            max(s.k_median * float(px["median"]), s.k_p90 * float(px["p90"]), s.floor_px))


def check_calibration(cal: Calibration, captures: CaptureSet, settings: CheckSettings | None = None,
                      detections: list[Detection] | None = None, *, cal_path: Path | None = None) -> CheckResult:
    """Compare new captures with the calibration's predictions; see the module docstring. ``cal_path``
    (the calibration's file) is named in the errors that are the calibration's."""
    s = settings or CheckSettings()
    for arm in cal.arms:
        if arm in captures.arms:
            _limits(cal, arm, s, cal_path)  # before the detection's seconds
    for arm in captures.arms:
        if arm not in cal.arms:
            raise CalibrationError(f"captures of {arm}, which the calibration does not have "
                                   f"(arms: {', '.join(cal.arms)})", captures.folder)
        serial = next(c.camera_serial for c in captures.captures if c.arm == arm)
        if cal.arms[arm].serial != serial:
            raise CalibrationError(f"{arm}: captures are from camera {serial} but the calibration is for "
                                   f"camera {cal.arms[arm].serial}", captures.folder)
    dets = detections if detections is not None else detect_captures(captures, s.detection)
    arms = tuple(a for a in sorted(cal.arms) if any(d.ok and d.arm == a for d in dets))
    if not arms:
        raise CalibrationError("no new capture has a usable board detection", captures.folder)
    blind = [a for a in captures.arms if a not in arms]
    if blind:
        n = sum(1 for c in captures.captures if c.arm == blind[0])
        raise CalibrationError(f"none of the {n} captures of {blind[0]} shows the board (blank or unreadable "
                               f"images?): {blind[0]} cannot be checked", captures.folder)
    obs = build_observations(dets, captures.board, arms)
    stored = cal.report.get("T_world_board") if isinstance(cal.report, dict) else None
    if s.board_unmoved:
        if stored is None:
            raise CalibrationError("the calibration does not store the board pose (report.T_world_board)")
        T_board = np.asarray(stored, float)
    else:
        T_board = fit_board(chain_from_calibration(cal, arms, np.eye(4)), obs, s.wrist_frame)
    params = chain_from_calibration(cal, arms, T_board)
    errs = corner_errors(params, obs, s.wrist_frame)
    arm_of_corner = obs.arm_index[obs.corner_capture]
    results: dict[str, ArmCheck] = {}
    for a, arm in enumerate(arms):
        n = int(np.count_nonzero(obs.arm_index == a))
        mm = summarise(errs["corner_3d_mm"][arm_of_corner == a])
        px = summarise(errs["reprojection_px"][arm_of_corner == a])
        lim_mm, lim_px = _limits(cal, arm, s, cal_path)
        reasons = []
        if n < s.min_captures:
            reasons.append(f"only {n} usable captures")
        if mm["median"] > lim_mm:
            reasons.append(f"median 3-D corner error {mm['median']:.2f} mm > {lim_mm:.2f} mm")
        if px["median"] > lim_px:
            reasons.append(f"median reprojection error {px['median']:.2f} px > {lim_px:.2f} px")
        results[arm] = ArmCheck(arm, n, mm, px, lim_mm, lim_px, not reasons, reasons)
    disagreement = None
    if not s.board_unmoved:
        boards = []
        for a, arm in enumerate(arms):
            own = obs.subset(obs.arm_index == a)
            p_own = chain_from_calibration(cal, arms, fit_board(params, own, s.wrist_frame))
            boards.append(p_own.T_ref_board)
            own_mm = float(np.median(corner_errors(p_own, own, s.wrist_frame)["corner_3d_mm"]))
            check = results[arm]
            check.self_consistency_mm = own_mm
            if own_mm > check.limit_mm:
                check.reasons.append(f"inconsistent on its own ({own_mm:.2f} mm with the board fitted to "
                                     f"{arm} alone): its camera mount or joint zeros changed")
        if len(arms) == 2:
            t, r = pose_error(boards[0], boards[1])
            disagreement = {"translation_mm": 1e3 * float(t), "rotation_deg": float(np.degrees(r))}
    for check in results.values():
        check.ok = not check.reasons
    per_capture = {cid: {k: float(np.median(v[obs.corner_capture == m])) for k, v in errs.items()}
                   for m, cid in enumerate(obs.capture_ids)}
    return CheckResult(ok=all(r.ok for r in results.values()), arms=results, board_disagreement=disagreement,
                       T_world_board=T_board, rejected={d.capture_id: d.reason for d in dets if not d.ok},
                       per_capture=per_capture)


__all__ = ["ArmCheck", "CheckResult", "CheckSettings", "chain_from_calibration", "check_calibration", "fit_board"]
