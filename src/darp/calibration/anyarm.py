"""Hand-eye calibration for any arm: a documented captures folder, detection, darp's solver, held-out checks.

The folder (docs/any-arm.md) is read by :mod:`darp.formats.captures` (its poses by :mod:`darp.formats.poses`,
intrinsics by :mod:`darp.formats.intrinsics`); its board is a :class:`darp.calibration.board.Board`, whose
corners :func:`darp.calibration.detect.detect_corners` finds.

The solve reuses darp's calibration chain (:mod:`darp.calibration.model`, ``handeye``, ``refine``) with
measured flange poses in place of the Z1's forward kinematics (``Observations.T_base_flange``) and no
joint-zero offsets. Eye-to-hand (camera fixed, board on the flange) is the same problem with the flange
poses inverted: the solver's "hand-eye" is then the camera in the base and its "board" the board on the
flange.

Quality: k-fold over captures, each fold calibrated without its captures, and for each withheld capture
(a) its corners' errors (:func:`darp.calibration.anyarm_heldout.heldout_corners`) and (b) **board consistency**:
the board placed in the base by that capture alone (``F_i X T_cam_board_i``) against the calibration's
board, as the distance of the board's centre (mm) and the rotation angle (deg).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from darp.calibration import handeye
from darp.calibration.anyarm_checks import check_capture_pairing, disagreeing_captures, marker_diagnosis
from darp.calibration.anyarm_heldout import (
    board_consistency,
    board_in_reference,
    fold_split,
    heldout_consistency,
    heldout_corners,
)
from darp.calibration.anyarm_refine import anyarm_solver, anyarm_solver_no_sag, corrected_observations
from darp.calibration.board import Board, parse_board
from darp.calibration.detect import board_pose_pnp, detect_corners, ideal_pixels
from darp.calibration.evaluate import summarise
from darp.calibration.model import ChainParams, Observations, flange_poses, reprojection_errors
from darp.calibration.refine import RefineSettings, refine
from darp.errors import CalibrationError, FormatError
from darp.formats.calibration import ArmCalibration, Calibration
from darp.formats.captures import CaptureFolder, PairingOptions, read_capture_folder
from darp.formats.intrinsics import CameraModel
from darp.formats.io_input import decode_image
from darp.formats.pairing import describe_pairs, natural_key
from darp.kinematics.transforms import invert_transform

BOARD_POSES = "board_poses"  # a detection's source prefix when the capture is a board pose, not an image
OPENCV_METHODS = tuple(f"calibrateHandEye/{m}" for m in handeye.HAND_EYE_METHODS)


def load_capture_folder(root: str | Path, intrinsics: str | Path | None = None,
                        eye_to_hand: bool | None = None, how: PairingOptions | None = None) -> CaptureFolder[Board]:
    """Read a generic captures folder (:func:`darp.formats.captures.read_capture_folder`) with its board."""
    return read_capture_folder(root, parse_board, intrinsics, eye_to_hand, how or PairingOptions())


# -- detections -> observations -----------------------------------------------------------------------

@dataclass
class GenericDetection:
    """One capture's corners (ideal pixels) and single-image board pose."""

    arm: str
    capture_id: str
    ids: np.ndarray
    corners_px: np.ndarray
    ok: bool
    reason: str = ""
    T_cam_board: np.ndarray | None = None
    pnp_rms_px: float = float("nan")
    source: str = ""


def solve_intrinsics(board: Board, found: list[tuple[np.ndarray, np.ndarray]], size: tuple[int, int]
                     ) -> tuple[CameraModel, float]:
    """OpenCV ``calibrateCamera`` on the detected corners of every image; (model, RMS px)."""
    P = board.corners_m()
    obj = [P[ids].astype(np.float32).reshape(-1, 1, 3) for ids, _ in found if len(ids) >= 8]
    img = [uv.astype(np.float32).reshape(-1, 1, 2) for ids, uv in found if len(ids) >= 8]
    if len(obj) < 4:
        raise CalibrationError(f"solving the intrinsics needs at least 4 images with 8+ corners, got {len(obj)} "
                               "(give intrinsics with --intrinsics)")
    w, h = size
    K0 = np.array([[max(w, h), 0, w / 2 - 0.5], [0, max(w, h), h / 2 - 0.5], [0, 0, 1]], np.float64)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), K0, np.zeros(5),
                                             flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    return CameraModel(K, dist.reshape(-1), "solved from the images (cv2.calibrateCamera)"), float(rms)


def detect_folder(folder: CaptureFolder[Board], min_corners: int = 8, max_pnp_rms_px: float = 2.0
                  ) -> tuple[list[GenericDetection], dict[str, CameraModel], dict[str, Any]]:
    """Corners and board poses of every capture; intrinsics (per arm) solved from the images when not given."""
    raw: list[tuple[str, str, np.ndarray, np.ndarray, str]] = []
    size: tuple[int, int] | None = None
    for arm in folder.arms:
        for key, img_path in sorted(arm.images.items(), key=lambda kv: natural_key(kv[0])):
            grey = decode_image(img_path, cv2.IMREAD_GRAYSCALE, "a board image")
            if grey is None:
                raise FormatError("cannot read the image", img_path)
            if size is None:
                size = (grey.shape[1], grey.shape[0])
            elif size != (grey.shape[1], grey.shape[0]):
                raise FormatError(f"image is {grey.shape[1]} x {grey.shape[0]}, the others {size[0]} x {size[1]}",
                                  img_path)
            ids, uv = detect_corners(folder.board, grey)
            raw.append((arm.arm, key, ids, uv, str(img_path)))
    info: dict[str, Any] = {}
    cameras: dict[str, CameraModel] = {}
    for arm in folder.arms:
        camera = arm.camera or folder.camera
        if camera is None:
            mine = [(i, u) for a, _, i, u, _ in raw if a == arm.arm and len(i) >= min_corners]
            if not mine or size is None:
                raise CalibrationError("board poses without intrinsics: give intrinsics (3x3) to weight them",
                                       arm.folder)
            camera, rms = solve_intrinsics(folder.board, mine, size)
            info.setdefault("intrinsics_rms_px", {})[arm.arm] = rms
        cameras[arm.arm] = camera
    info["intrinsics_source"] = {a: c.source for a, c in cameras.items()}
    P = folder.board.corners_m()
    dets: list[GenericDetection] = []
    for arm_name, key, ids, uv, src in raw:
        camera = cameras[arm_name]
        d = GenericDetection(arm_name, key, ids, ideal_pixels(camera, uv), False, source=src)
        if len(ids) < min_corners:
            d.reason = f"too few corners ({len(ids)} < {min_corners})"
            if folder.board.kind == "charuco":
                d.reason += marker_diagnosis(folder.board, src)
        else:
            T, rms = board_pose_pnp(P[ids], d.corners_px, camera.K)
            d.T_cam_board, d.pnp_rms_px = T, rms
            d.ok = T is not None and rms <= max_pnp_rms_px
            d.reason = "" if d.ok else f"PnP reprojection error {rms:.2f} px > {max_pnp_rms_px} px"
        dets.append(d)
    for arm in folder.arms:  # board poses given instead of images: their corners, seen through K
        camera = cameras[arm.arm]
        names = {k: o for k, o, _ in arm.pairing.pairs} if arm.pairing is not None else {}
        for key, T in sorted(arm.board_poses.items(), key=lambda kv: natural_key(kv[0])):
            if key in arm.images:
                continue
            Pc = P @ T[:3, :3].T + T[:3, 3]
            uv = (Pc[:, :2] / Pc[:, 2:3]) * np.diag(camera.K)[:2] + camera.K[:2, 2]
            dets.append(GenericDetection(arm.arm, key, np.arange(len(P)), uv, bool(np.all(Pc[:, 2] > 0)),
                                         "" if np.all(Pc[:, 2] > 0) else "board behind the camera", T, 0.0,
                                         f"{BOARD_POSES}/{names.get(key, key)}"))
    return dets, cameras, info


def build_generic_observations(folder: CaptureFolder[Board], dets: list[GenericDetection],
                               cameras: dict[str, CameraModel]) -> tuple[Observations, list[str]]:
    """Observations for darp's chain: measured flange poses (inverted for eye-to-hand); warnings."""
    warnings_out: list[str] = []
    P = folder.board.corners_m()
    flange = {a.arm: a for a in folder.arms}
    good = []
    for d in dets:
        if not d.ok:
            continue
        if d.capture_id not in flange[d.arm].T_base_flange:
            warnings_out.append(f"{flange[d.arm].pose_source}: no flange pose for capture {d.capture_id!r} "
                                f"({d.source}); capture skipped")
            continue
        good.append(d)
    for a in folder.arms:
        have = {d.capture_id for d in dets if d.arm == a.arm}
        extra = sorted(set(a.T_base_flange) - have)
        if extra:
            warnings_out.append(f"{a.pose_source}: {len(extra)} pose(s) without an image or board pose "
                                f"(e.g. {extra[0]!r}); check for missing frames")
    if not good:
        raise CalibrationError("no capture has a usable board detection and a flange pose", folder.root)
    arms = tuple(dict.fromkeys(d.arm for d in good))
    F = np.array([flange[d.arm].T_base_flange[d.capture_id] for d in good])
    if folder.eye_to_hand:
        F = invert_transform(F)
    counts = np.array([len(d.ids) for d in good])
    obs = Observations(
        arms=arms, capture_ids=[f"{d.arm}/{d.capture_id}" if len(arms) > 1 else d.capture_id for d in good],
        arm_index=np.array([arms.index(d.arm) for d in good]), q_rad=np.zeros((len(good), 6)),
        T_stream_depth=np.tile(np.eye(4), (len(good), 1, 1)), K=np.array([cameras[d.arm].K for d in good]),
        corner_capture=np.repeat(np.arange(len(good)), counts), corner_id=np.concatenate([d.ids for d in good]),
        P_board=np.concatenate([P[d.ids] for d in good]), uv=np.concatenate([d.corners_px for d in good]),
        T_depth_board_pnp=np.array([d.T_cam_board for d in good]), T_base_flange=F)
    return obs, warnings_out


# -- solving and held-out checks ----------------------------------------------------------------------

REFINE = RefineSettings(estimate_offsets=False)
REFINEMENT_TEXT = {
    "poses": "boards placed together in the base: centre (mm) and PnP-weighted rotation, flange sag "
             "(darp.calibration.anyarm_refine)",
    "pixels": "corner reprojection (px), darp's joint refinement without joint offsets",
    "board poses": "board poses: board centre (mm) and rotation (x 1000 mm/rad) in the base",
}


def darp_solver(obs: Observations, settings: RefineSettings = REFINE, metric: bool = False) -> ChainParams:
    """darp's calibration of measured-pose observations: best OpenCV start, then the joint refinement.

    ``metric``: the captures are board *poses* (no pixels were measured), so the refinement minimises
    the boards' disagreement in the reference frame (:func:`refine_metric`) instead of pixels.
    """
    est = {a: handeye.opencv_hand_eye(obs, a) for a in obs.arms}
    start = handeye.chain_from_estimates({a: handeye.best(est[a]) for a in obs.arms}, obs.arms)
    if metric:
        return refine_metric(start, obs)
    return refine(start, obs, None, settings).params


def metric_solver(obs: Observations) -> ChainParams:
    """:func:`darp_solver` for board-pose captures."""
    return darp_solver(obs, metric=True)


ROTATION_LEVER_MM = 1000.0  # board-pose refinement: mm of residual per radian of board rotation


def refine_metric(p0: ChainParams, obs: Observations, centre_board: np.ndarray | None = None,
                  lever_mm: float = ROTATION_LEVER_MM) -> ChainParams:
    """Hand-eyes, other bases and the board that best place every capture's board together (board poses).

    Per capture i (arm a) the board placed by that capture, ``T_i = T_ref_base_a F_i X_a T_cam_board_i``, is
    compared with the board ``W``: the distance of the board's centre (mm) and its rotation
    ``log(W^-1 T_i)`` (rad) times ``lever_mm``. The large default lever makes the rotation dominate (the
    hand-eye rotation is fitted first, as the two-step AX = XB methods do) and the centre fixes the
    translations; this is the held-out board consistency the report scores. Same parameterisation as
    the pixel refinement (:class:`darp.calibration.refine.Layout`, right perturbations, no joint offsets).
    """
    from scipy.optimize import least_squares

    from darp.calibration.geometry import log_delta
    from darp.calibration.refine import Layout

    if obs.T_base_flange is None:
        raise CalibrationError("board-pose refinement needs measured flange poses")
    layout = Layout(p0.arms, {a: np.zeros(6, bool) for a in p0.arms})
    c = np.append(np.unique(obs.P_board, axis=0).mean(axis=0) if centre_board is None else centre_board, 1.0)
    F, B = np.asarray(obs.T_base_flange), obs.T_depth_board_pnp

    def fun(x: np.ndarray) -> np.ndarray:
        p = layout.unpack(x, p0)
        T = np.empty_like(B)
        for a, arm in enumerate(obs.arms):
            sel = obs.arm_index == a
            T[sel] = p.T_ref_base[arm] @ F[sel] @ p.T_wrist_cam[arm] @ B[sel]
        d = 1e3 * ((T @ c)[:, :3] - (p.T_ref_board @ c)[:3])
        r = lever_mm * log_delta(invert_transform(p.T_ref_board) @ T)[:, :3]
        return np.concatenate([d.ravel(), r.ravel()])

    x = np.zeros(layout.size)
    if lever_mm > 0:
        x = least_squares(fun, x, method="lm").x
        return layout.unpack(x, p0)
    lever = 100.0  # whitened: the lever is the ratio of the residuals' own spreads, re-estimated (3 rounds)
    for _ in range(3):
        lever_mm = lever
        x = least_squares(fun, x, method="lm").x
        r = fun(x)
        n = len(r) // 2
        lever = float(np.sqrt(np.mean(r[:n] ** 2)) / max(np.sqrt(np.mean((r[n:] / lever_mm) ** 2)), 1e-9))
    return layout.unpack(x, p0)


def opencv_solver(method: str) -> Callable[[Observations], ChainParams]:
    """One OpenCV method alone (e.g. ``"calibrateHandEye/TSAI"``): its hand-eye, board averaged over captures."""
    def solve(obs: Observations) -> ChainParams:
        chosen = {}
        for a in obs.arms:
            pick = [e for e in handeye.opencv_hand_eye(obs, a) if e.method == method]
            if not pick or not pick[0].ok:
                raise CalibrationError(f"{method} failed on these captures")
            chosen[a] = pick[0]
        return handeye.chain_from_estimates(chosen, obs.arms)
    return solve


@dataclass
class HandEyeOutcome:
    """What :func:`solve_folder` found."""

    calibration: Calibration
    params: ChainParams
    observations: Observations
    detections: list[GenericDetection]
    cameras: dict[str, CameraModel]
    heldout: dict[str, Any]
    consistency: dict[str, Any]
    comparison: dict[str, dict[str, Any]]
    warnings: list[str]
    pairing_lines: list[str] = field(default_factory=list)  # how captures were paired, and the check's numbers


REFINEMENTS = ("poses", "poses-no-sag", "pixels")


def choose_solver(refinement: str, pose_only: bool, eye_to_hand: bool) -> Callable[[Observations], ChainParams]:
    """``poses``: :mod:`darp.calibration.anyarm_refine` (sag term for eye-in-hand); ``poses-no-sag``: the same
    without it; ``pixels``: darp's corner reprojection refinement (board poses without images: the unweighted
    board-pose refinement)."""
    if refinement == "pixels":
        return metric_solver if pose_only else darp_solver
    if refinement not in REFINEMENTS:
        raise CalibrationError(f"unknown refinement {refinement!r} ({', '.join(REFINEMENTS)})")
    return anyarm_solver_no_sag if eye_to_hand or refinement == "poses-no-sag" else anyarm_solver


MIN_ROTATION_DEG = 2.0  # the smallest flange rotation between captures, about each of two axes, hand-eye needs


def check_flange_motion(obs: Observations, arm: str, root: Path) -> None:
    """Hand-eye is determined only when the flange rotates about at least two different axes between captures
    (Tsai-Lenz); identical or one-axis poses are refused instead of "solved" to an arbitrary answer."""
    T = flange_poses(obs, obs.for_arm(arm), np.zeros(6))
    R0 = T[0, :3, :3]
    vecs = np.array([Rotation.from_matrix(R0.T @ Ti[:3, :3]).as_rotvec() for Ti in T[1:]]).reshape(-1, 3)
    spread = np.linalg.svd(vecs, compute_uv=False) if len(vecs) else np.zeros(1)
    second = float(np.degrees(spread[1] / np.sqrt(len(vecs)))) if spread.size > 1 else 0.0
    if second < MIN_ROTATION_DEG:
        most = float(np.degrees(np.max(np.linalg.norm(vecs, axis=1)))) if len(vecs) else 0.0
        raise CalibrationError(f"{arm}: the flange poses do not rotate about two different axes (largest rotation "
                               f"from the first capture {most:.2f} deg): hand-eye is undetermined; capture poses "
                               "that tilt the flange in different directions", root)


def solve_folder(root: str | Path, *, intrinsics: str | Path | None = None, eye_to_hand: bool | None = None,
                 folds: int = 5, seed: int = 0, compare: bool = True, folds_file: str | Path | None = None,
                 refinement: str = "poses", how: PairingOptions | None = None, force: bool = False
                 ) -> HandEyeOutcome:
    """The whole any-arm calibration of a captures folder."""
    from darp.calibration.diagnose import check_pose_conventions

    folder = load_capture_folder(root, intrinsics, eye_to_hand, how)
    dets, cameras, info = detect_folder(folder)
    obs, warns = build_generic_observations(folder, dets, cameras)
    pairing_checks = {}
    for arm in obs.arms:
        if int(np.sum(obs.for_arm(arm))) < 4:
            raise CalibrationError(f"{arm}: {int(np.sum(obs.for_arm(arm)))} usable captures; hand-eye needs at "
                                   "least 4", folder.root)
        check_pose_conventions(folder, obs, arm)
        check_flange_motion(obs, arm, folder.root)
        pairing_checks[arm], kept = check_capture_pairing(folder, obs, arm, force)
        if kept:
            warns.append(kept)
    pose_only = all(d.source.startswith(BOARD_POSES) for d in dets if d.ok)
    solver = choose_solver(refinement, pose_only, folder.eye_to_hand)
    params = solver(obs)
    centre = folder.board.corners_m().mean(axis=0)
    k = min(folds, min(int(np.sum(obs.for_arm(a))) for a in obs.arms)) if folds > 1 else 0
    split = fold_split(obs, k, seed, folds_file) if (k > 1 or folds_file is not None) else None
    held = heldout_corners(obs, solver, split) if split is not None else {}
    cons = heldout_consistency(obs, solver, centre, split) if split is not None else {}
    comparison: dict[str, dict[str, Any]] = {}
    if compare and split is not None:
        for m in OPENCV_METHODS:
            try:
                comparison[m] = heldout_consistency(obs, opencv_solver(m), centre, split)
            except CalibrationError as err:
                comparison[m] = {"error": str(err)}
    fit = reprojection_errors(params, corrected_observations(params, obs))
    fit_cons = board_consistency(params, obs, centre)
    warns += disagreeing_captures(obs, dets, fit_cons[0])
    report: dict[str, Any] = {
        "kind": "any-arm hand-eye",
        "mode": "eye_to_hand" if folder.eye_to_hand else "eye_in_hand",
        "refinement": REFINEMENT_TEXT[refinement if refinement.startswith("poses") else
                                      ("pixels" if not pose_only else "board poses")]
        + (" (no sag)" if refinement == "poses-no-sag" or (refinement == "poses" and folder.eye_to_hand) else ""),
        "sag": {a: v.tolist() for a, v in getattr(params, "sag", {}).items()},
        "pairing": {a.arm: {"rule": a.pairing.rule, "pairs": len(a.pairing.pairs),
                            "first": a.pairing.pairs[:3], "last": a.pairing.pairs[-3:],
                            "check_mm": pairing_checks.get(a.arm, {})} for a in folder.arms if a.pairing},
        "captures_folder": str(folder.root),
        "board": folder.board.describe(),
        "pose_conventions": {"unit": folder.conventions.unit, "quaternion": folder.conventions.quaternion},
        "intrinsics": {"K": {a: c.K for a, c in cameras.items()}, "dist": {a: c.dist for a, c in cameras.items()},
                       **info},
        "n_captures": {a: int(np.sum(obs.for_arm(a))) for a in obs.arms},
        "rejected": {f"{d.arm}/{d.capture_id}": d.reason for d in dets if not d.ok},
        "fit": {"reprojection_px": summarise(fit), "board_consistency_mm": summarise(fit_cons[0]),
                "board_corner_consistency_mm": summarise(fit_cons[1]),
                "board_consistency_deg": summarise(fit_cons[2])},
        "heldout": {"folds": int(len(np.unique(split))) if split is not None else 0,
                    "split": (f"folds file {folds_file}" if folds_file is not None else
                              f"seeded ({seed}), {k} folds: darp.calibration.anyarm_heldout.fold_split"),
                    "fold_of": dict(zip(obs.capture_ids, split.tolist(), strict=True)) if split is not None else {},
                    "corner_3d_mm": {a: summarise(v["corner_3d_mm"]) for a, v in held.items()},
                    "reprojection_px": {a: summarise(v["reprojection_px"]) for a, v in held.items()},
                    "board_consistency_mm": cons.get("mm"), "board_corner_consistency_mm": cons.get("corner_mm"),
                    "board_consistency_deg": cons.get("deg")},
        "opencv_heldout_board_consistency": {m: ({"mm": v["mm"], "corner_mm": v["corner_mm"], "deg": v["deg"]}
                                                 if "mm" in v else v) for m, v in comparison.items()},
        "warnings": warns,
    }
    if folder.eye_to_hand:
        a0 = obs.arms[0]
        report["T_base_cam"] = params.T_wrist_cam[a0]
        report["T_flange_board"] = params.T_ref_board
    if len(obs.arms) > 1:
        report["base_to_base"] = {f"{obs.arms[0]}->{a}": params.T_ref_base[a] for a in obs.arms[1:]}
    arms_out = {}
    for a in obs.arms:
        if folder.eye_to_hand:  # world = the fixed camera; the "wrist camera" is the board on the flange
            arms_out[a] = ArmCalibration("", invert_transform(params.T_wrist_cam[a]), params.T_ref_board.copy(),
                                         n_captures=int(np.sum(obs.for_arm(a))))
        else:
            arms_out[a] = ArmCalibration("", params.T_ref_base[a].copy(), params.T_wrist_cam[a].copy(),
                                         n_captures=int(np.sum(obs.for_arm(a))))
    world = ("eye-to-hand: world = the fixed camera's optical frame; T_wrist_cam holds the board on the flange "
             "(T_flange_board)" if folder.eye_to_hand else
             f"the base frame of {obs.arms[0]} (any-arm calibration, no joint offsets)")
    cal = Calibration(epoch=folder.root.name, date=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                      arms=arms_out, board=folder.board.spec(), world_frame=world, report=_jsonable(report))
    lines = []
    for ac in folder.arms:
        if ac.pairing is not None:
            lines.append(f"{ac.arm}: {describe_pairs(ac.pairing)}")
        c = pairing_checks.get(ac.arm)
        if c:
            lines.append(f"{ac.arm}: pairing check: boards agree to {c['as given']:.2f} mm median as paired, "
                         f"{c['shift+1']:.1f} / {c['shift-1']:.1f} mm with the poses shifted by +1 / -1")
    return HandEyeOutcome(cal, params, obs, dets, cameras, {"per_arm": held}, cons, comparison, warns, lines)


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.floating | np.integer):
        return v.item()
    return v


__all__ = ["OPENCV_METHODS", "REFINEMENTS", "GenericDetection", "HandEyeOutcome", "board_consistency",
           "board_in_reference", "build_generic_observations", "check_capture_pairing", "choose_solver", "darp_solver",
           "detect_folder", "fold_split", "heldout_consistency", "load_capture_folder", "marker_diagnosis",
           "metric_solver", "opencv_solver", "refine_metric", "solve_folder", "solve_intrinsics"]
