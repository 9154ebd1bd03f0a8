"""The calibration driver: captures -> detections -> OpenCV start -> identifiability -> refinement ->
held-out evaluation -> a :class:`~darp.formats.calibration.Calibration` (plus a report folder).

Everything in one call, :func:`solve_captures`; :func:`calibrate_observations` is the part that k-fold
evaluation repeats without the withheld captures. Besides darp's refined calibration, the same
captures are solved by OpenCV alone (``calibrateHandEye``, best of five methods, and
``calibrateRobotWorldHandEye``, best of SHAH and LI; bases from each arm's board estimate, no joint
offsets) and by darp's refinement without joint offsets, so the report can show what each step buys.
"""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from darp.calibration import handeye
from darp.calibration.captures import CaptureSet
from darp.calibration.depth_fit import DepthFitSettings, estimate_depth_corrections
from darp.calibration.detect import Detection, DetectionSettings, detect_captures
from darp.calibration.evaluate import kfold_heldout, summarise, truth_errors
from darp.calibration.kinematic_ident import KinIdentifiability, KinIdentSettings, analyse_kinematics
from darp.calibration.model import ChainParams, Observations, build_observations, reprojection_errors
from darp.calibration.refine import (
    Identifiability,
    RefineResult,
    RefineSettings,
    analyse_identifiability,
    refine,
)
from darp.calibration.world_frame import WORLD_FRAME_TEXT, world_from_reference
from darp.errors import CalibrationError
from darp.formats.calibration import ArmCalibration, Calibration
from darp.kinematics.kinematic_model import PARAM_NAMES as KIN_NAMES
from darp.kinematics.kinematic_model import KinematicParams
from darp.kinematics.transforms import invert_transform

METHODS = ("darp", "darp_no_offsets", "opencv_hand_eye", "opencv_robot_world")
METHOD_LABELS = {
    "darp": "darp: joint refinement (hand-eye, bases, board, joint offsets)",
    "darp_no_offsets": "darp refinement without joint offsets",
    "opencv_hand_eye": "OpenCV calibrateHandEye (best of 5 methods) + board-averaged bases",
    "opencv_robot_world": "OpenCV calibrateRobotWorldHandEye (best of SHAH, LI) + board-averaged bases",
    "darp_model": "darp with the richer arm model (--model: + joint origins, axis tilts[, compliance])",
}


@dataclass(frozen=True)
class SolveSettings:
    """What the driver does besides the defaults of each step."""

    detection: DetectionSettings = field(default_factory=DetectionSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    folds: int = 5  # 0 or 1: no held-out evaluation
    seed: int = 0
    min_captures_per_arm: int = 6
    arms: tuple[str, ...] | None = None  # order: first = reference; default sorted arm ids
    compare: bool = True  # also solve with OpenCV alone and without joint offsets
    epoch: str | None = None
    model: str = "paper"  # paper | kinematic | kinematic+compliance (darp.calibration.kinematic_ident)
    kin_ident: KinIdentSettings = field(default_factory=KinIdentSettings)
    depth: DepthFitSettings = field(default_factory=DepthFitSettings)  # captures with depth: per-camera fit


@dataclass
class CoreResult:
    """One calibration of a set of observations (reference frame = first arm's base)."""

    params: ChainParams
    refined: RefineResult
    identifiability: Identifiability | None  # None when the free offsets were given
    opencv: dict[str, list[handeye.HandEyeEstimate]]
    start: ChainParams
    kin_ident: KinIdentifiability | None = None  # the richer model's identifiability (None: paper model)
    paper: RefineResult | None = None  # the paper model's refinement, when a richer model was solved


def opencv_chain(estimates: dict[str, list[handeye.HandEyeEstimate]], arms: tuple[str, ...],
                 family: str | None) -> ChainParams:
    """A calibration from OpenCV estimates alone (best of ``family``; None: best of all)."""
    return handeye.chain_from_estimates({a: handeye.best(estimates[a], family) for a in arms}, arms)


def calibrate_observations(obs: Observations, settings: RefineSettings | None = None,
                           free_joints: dict[str, np.ndarray] | None = None, *, model: str = "paper",
                           free_kin: dict[str, np.ndarray] | None = None,
                           kin_settings: KinIdentSettings | None = None) -> CoreResult:
    """OpenCV start, identifiability (unless ``free_joints`` is given), joint refinement; with a richer
    ``model``, then the kinematic identifiability (unless ``free_kin`` is given) and a second refinement
    of everything from the paper model's solution."""
    s = settings or RefineSettings()
    estimates = {a: handeye.opencv_hand_eye(obs, a, s.wrist_frame) for a in obs.arms}
    start = opencv_chain(estimates, obs.arms, None)
    ident = analyse_identifiability(start, obs, s) if free_joints is None else None
    free = ident.identifiable if ident is not None else free_joints
    assert free is not None
    refined = refine(start, obs, free, s)
    if model == "paper":
        return CoreResult(refined.params, refined, ident, estimates, start)
    kin_ident = None
    if free_kin is None:
        kin_ident = analyse_kinematics(refined.params, obs, free, model, refined.sigma_px, kin_settings)
        free_kin = kin_ident.free
    rich = refine(refined.params, obs, free, s, free_kin)
    for a in rich.params.arms:  # an arm with nothing estimated still carries the model (all zero)
        rich.params.kin.setdefault(a, KinematicParams())
    return CoreResult(rich.params, rich, ident, estimates, start, kin_ident, refined)


@dataclass
class SolveOutcome:
    """Everything :func:`solve_captures` found, for the file, the report and the tests."""

    calibration: Calibration
    core: CoreResult
    observations: Observations
    detections: list[Detection]
    T_ref_world: np.ndarray
    methods: dict[str, ChainParams]
    heldout: dict[str, dict[str, Any]]
    truth: dict[str, Any] | None
    timings_s: dict[str, float]


def to_calibration(params: ChainParams, T_ref_world: np.ndarray, serials: dict[str, str], *, epoch: str,
                   date: str, board: Any) -> Calibration:
    """A calibration file object for ``params`` in the world ``T_ref_world``."""
    T_world_ref = invert_transform(T_ref_world)
    arms = {a: ArmCalibration(serial=serials[a], T_world_base=T_world_ref @ params.T_ref_base[a],
                              T_wrist_cam=params.T_wrist_cam[a].copy(), joint_offsets_rad=params.dq[a].copy())
            for a in params.arms}
    return Calibration(epoch=epoch, date=date, arms=arms, board=board, world_frame=WORLD_FRAME_TEXT)


def _stats_by_arm(values: np.ndarray, obs: Observations) -> dict[str, dict[str, float]]:
    arm_of_corner = obs.arm_index[obs.corner_capture]
    return {arm: summarise(values[arm_of_corner == a]) for a, arm in enumerate(obs.arms)}


def solve_captures(captures: CaptureSet, settings: SolveSettings | None = None, *,
                   truth: Calibration | None = None,
                   progress: Callable[[str, int, int], None] | None = None) -> SolveOutcome:
    """Calibrate the rig from a capture folder (``truth``: compare with a true calibration, e.g. the twin's)."""
    s = settings or SolveSettings()
    timings: dict[str, float] = {}
    tick = time.perf_counter()
    done = [0]

    def advance(stage: str, total: int) -> Callable[[], None]:
        done[0] = 0

        def step() -> None:
            done[0] += 1
            if progress is not None:
                progress(stage, done[0], total)
        return step

    detections = detect_captures(captures, s.detection, advance("detect", len(captures.captures)))
    timings["detect"] = time.perf_counter() - tick
    arms = s.arms or tuple(sorted(captures.arms))
    if len(arms) != 2:
        raise CalibrationError(f"captures of two arms are needed, found {', '.join(arms) or 'none'}",
                               captures.folder)
    for arm in arms:
        n_ok = sum(d.ok for d in detections if d.arm == arm)
        if n_ok < s.min_captures_per_arm:
            reasons = sorted({d.reason for d in detections if d.arm == arm and not d.ok})
            raise CalibrationError(f"{arm}: only {n_ok} usable captures (need {s.min_captures_per_arm}); "
                                   f"rejections: {'; '.join(reasons) or 'none'}", captures.folder)
    obs = build_observations(detections, captures.board, arms)

    tick = time.perf_counter()
    core = calibrate_observations(obs, s.refine, model=s.model, kin_settings=s.kin_ident)
    timings["solve"] = time.perf_counter() - tick
    main = core.paper if core.paper is not None else core.refined  # the calibration's own fields: paper model
    T_ref_world = world_from_reference(main.params.T_ref_base, main.params.T_ref_board, arms)
    assert core.identifiability is not None
    free = core.identifiability.identifiable
    methods: dict[str, ChainParams] = {"darp": main.params}
    free_kin = core.kin_ident.free if core.kin_ident is not None else None
    solvers: dict[str, Callable[[Observations], ChainParams]] = {
        "darp": lambda o: calibrate_observations(o, s.refine, free).params}
    if core.paper is not None:  # a richer model, beside the paper's, always
        methods["darp_model"] = core.params
        solvers["darp_model"] = lambda o: calibrate_observations(o, s.refine, free, model=s.model,
                                                                  free_kin=free_kin).params
    if s.compare:
        methods["darp_no_offsets"] = refine(core.start, obs, None, s.refine).params
        methods["opencv_hand_eye"] = opencv_chain(core.opencv, arms, "calibrateHandEye")
        methods["opencv_robot_world"] = opencv_chain(core.opencv, arms, "calibrateRobotWorldHandEye")
        solvers["darp_no_offsets"] = lambda o: refine(
            opencv_chain({a: handeye.opencv_hand_eye(o, a) for a in arms}, arms, None), o, None, s.refine).params
        solvers["opencv_hand_eye"] = lambda o: opencv_chain(
            {a: handeye.opencv_hand_eye(o, a) for a in arms}, arms, "calibrateHandEye")
        solvers["opencv_robot_world"] = lambda o: opencv_chain(
            {a: handeye.opencv_hand_eye(o, a) for a in arms}, arms, "calibrateRobotWorldHandEye")

    tick = time.perf_counter()
    heldout: dict[str, dict[str, Any]] = {}
    if s.folds >= 2:
        for name, solver in solvers.items():
            heldout[name] = kfold_heldout(obs, solver, s.folds, s.seed, s.refine.wrist_frame,
                                          advance(f"held-out {name}", s.folds))
    timings["evaluate"] = time.perf_counter() - tick

    serials = {a: next(d.record.camera_serial for d in detections if d.arm == a) for a in arms}
    date = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    epoch = s.epoch or f"calib-{date[:10]}"
    cal = to_calibration(main.params, T_ref_world, serials, epoch=epoch, date=date, board=captures.board)
    fit_px = reprojection_errors(main.params, obs, s.refine.wrist_frame)
    fit_stats = _stats_by_arm(fit_px, obs)
    res = main
    for a in arms:
        entry = cal.arms[a]
        entry.joint_offsets_std_rad = res.joint_offset_std(a)
        entry.identifiable = tuple(bool(v) for v in free[a])
        entry.n_captures = int(np.count_nonzero(obs.for_arm(a)))
        he_std = res.std(f"handeye:{a}")
        entry.residuals = {
            "fit_reprojection_px": fit_stats[a],
            "hand_eye_std": {"rotation_deg": np.degrees(he_std[:3]).tolist(),
                             "translation_mm": (1e3 * he_std[3:]).tolist()},
            "n_rejected": sum(1 for d in detections if d.arm == a and not d.ok),
        }
        if f"base:{a}" in res.layout.slices:
            b_std = res.std(f"base:{a}")
            entry.residuals["base_std"] = {"rotation_deg": np.degrees(b_std[:3]).tolist(),
                                           "translation_mm": (1e3 * b_std[3:]).tolist()}
        if "darp" in heldout:
            entry.residuals["heldout"] = {k: summarise(v) for k, v in heldout["darp"]["per_arm"][a].items()}
        if core.kin_ident is not None:  # in the world the richer model itself realises (its bases and board)
            T_ref_world_model = world_from_reference(core.params.T_ref_base, core.params.T_ref_board, arms)
            entry.kinematics = _kinematics_entry(core, a, obs, T_ref_world_model, heldout.get("darp_model"))
    tick = time.perf_counter()
    depth_corr, depth_skipped = estimate_depth_corrections(captures, detections, s.depth)
    for a, corr in depth_corr.items():
        if a in cal.arms:
            cal.arms[a].depth_correction = corr
    if depth_corr or depth_skipped:
        timings["depth_correction"] = time.perf_counter() - tick
    truth_cmp = None
    if truth is not None:
        q_by_arm = {a: obs.q_rad[obs.for_arm(a)] for a in arms}
        truth_cmp = {}
        for name, params in methods.items():
            other = to_calibration(params, world_from_reference(params.T_ref_base, params.T_ref_board, arms),
                                   serials, epoch=name, date=date, board=captures.board)
            ident = free if name in ("darp", "darp_model") else {a: np.zeros(6, bool) for a in arms}
            truth_cmp[name] = truth_errors(other, truth, arms, ident, q_by_arm, s.refine.wrist_frame)
    cal.report = _report(s, captures, detections, obs, core, T_ref_world, heldout, truth_cmp, timings, arms)
    cal.report["depth_correction"] = {
        "captures_with_depth": sum(1 for c in captures.captures if c.has_depth),
        "estimated": sorted(depth_corr), "skipped": depth_skipped}
    return SolveOutcome(cal, core, obs, detections, T_ref_world, methods, heldout, truth_cmp, timings)


def _kinematics_entry(core: CoreResult, arm: str, obs: Observations, T_ref_world: np.ndarray,
                      heldout: dict[str, Any] | None) -> dict[str, Any]:
    """calibration.json's ``kinematics`` of one arm: the richer model's own eq. 1 transforms and joint zeros
    (the file's main fields stay the paper model's, so paper mode is unchanged), its parameters and their
    std, the identifiability table and its fit and held-out errors."""
    assert core.kin_ident is not None
    res = core.refined
    p = core.params
    kin = p.kin[arm]
    fit = reprojection_errors(p, obs)[obs.arm_index[obs.corner_capture] == obs.arms.index(arm)]
    std = np.zeros(len(KIN_NAMES))
    if f"kin:{arm}" in res.layout.slices:
        std[core.kin_ident.free[arm]] = res.std(f"kin:{arm}")
    return {"model": core.kin_ident.model,
            "T_world_base": (invert_transform(T_ref_world) @ p.T_ref_base[arm]).tolist(),
            "T_wrist_cam": p.T_wrist_cam[arm].tolist(), "joint_offsets_rad": p.dq[arm].tolist(),
            **kin.to_dict(),
            "fit_reprojection_px": summarise(fit),
            "heldout": None if heldout is None else {k: summarise(v) for k, v in heldout["per_arm"][arm].items()},
            "estimated": [KIN_NAMES[k] for k in np.flatnonzero(core.kin_ident.free[arm])],
            "std": {KIN_NAMES[k]: float(std[k]) for k in np.flatnonzero(core.kin_ident.free[arm])},
            "identifiability": core.kin_ident.table[arm],
            "mass_model": "darp.kinematics.kinematic_model.LINK_MASSES (nominal lumped Z1 links) + payload_kg "
                          "3 cm past the flange; base level, z up"}


def _fit_rms(params: ChainParams, obs: Observations, wrist_frame: str) -> dict[str, float]:
    err = reprojection_errors(params, obs, wrist_frame)
    arm_of = obs.arm_index[obs.corner_capture]
    return {arm: float(np.sqrt(np.mean(err[arm_of == a] ** 2))) for a, arm in enumerate(obs.arms)}


def _report(s: SolveSettings, captures: CaptureSet, detections: list[Detection], obs: Observations,
            core: CoreResult, T_ref_world: np.ndarray, heldout: dict[str, Any], truth_cmp: dict[str, Any] | None,
            timings: dict[str, float], arms: tuple[str, ...]) -> dict[str, Any]:
    res = core.paper if core.paper is not None else core.refined
    return {
        "source": str(captures.folder),
        "n_captures": len(captures.captures),
        "n_used": obs.n_captures,
        "rejected": {d.capture_id: d.reason for d in detections if not d.ok},
        "reference_arm": arms[0],
        "T_world_board": (invert_transform(T_ref_world) @ res.params.T_ref_board).tolist(),
        "sigma_px": res.sigma_px,
        "refine": {"cost": res.cost, "n_residuals": res.n_residuals, "nfev": res.nfev, "success": res.success,
                   "message": res.message, "parameters": res.layout.names,
                   "std": np.sqrt(np.clip(np.diag(res.covariance), 0, None)).tolist()},
        "identifiability": core.identifiability.to_dict() if core.identifiability else None,
        **({} if core.kin_ident is None else {"model": s.model, "kinematics": {
            **core.kin_ident.to_dict(),
            "fit_rms_px": {"paper": _fit_rms(core.paper.params, obs, s.refine.wrist_frame) if core.paper else None,
                           s.model: _fit_rms(core.params, obs, s.refine.wrist_frame)}}}),
        "opencv": {a: [{"method": e.method, "median_px": e.median_px if np.isfinite(e.median_px) else None,
                        "ok": e.ok} for e in est] for a, est in core.opencv.items()},
        "heldout": {name: {arm: {k: summarise(v) for k, v in d.items()} for arm, d in h["per_arm"].items()}
                    for name, h in heldout.items()},
        "heldout_per_capture": heldout.get("darp", {}).get("per_capture", {}),
        "folds": s.folds,
        "truth": truth_cmp,
        "methods": METHOD_LABELS,
        "timings_s": timings,
        "settings": {"detection": asdict(s.detection), "refine": asdict(s.refine), "seed": s.seed},
    }


__all__ = ["METHODS", "METHOD_LABELS", "CoreResult", "SolveOutcome", "SolveSettings", "calibrate_observations",
           "opencv_chain", "solve_captures", "to_calibration"]
