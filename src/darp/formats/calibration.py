"""The calibration file of one rig epoch (JSON): hand-eye, base-to-world and joint-zero offsets per arm.

This module is only the data container and its on-disk form; computing a calibration lives in
``darp.calibration``. Schema 1::

    schema_version  1
    epoch           label of the calibration epoch (a remount or a moved base starts a new one)
    date            ISO 8601 date or date-time of the calibration
    board           ChArUco board: squares_x, squares_y, square_length_m, marker_length_m, dictionary
                    (null when the calibration did not come from a board, e.g. a nominal one)
    world_frame     free text: how the world frame is defined
    arms            {arm: {serial, T_world_base, T_wrist_cam, joint_offsets_rad,
                           joint_offsets_std_rad?, identifiable?, residuals?, n_captures?,
                           depth_correction?, time_offset_s?, time_offset_std_s?}}
    report          free object (statistics, settings, notes)

``T_world_base`` and ``T_wrist_cam`` are 4x4 rigid transforms (``T_a_b`` maps points from b to a);
the wrist frame is the Z1 flange. ``joint_offsets_rad`` is the static joint-zero correction dq of
eq. 1: the model is evaluated at q + dq.

Optional per-arm corrections (issue 16; absent = nothing to apply): ``depth_correction`` is the camera's
depth correction estimated from the board captures (:class:`DepthCorrection`: corrected depth =
``scale * z + offset_m + quad_per_m * z^2`` for measured depth ``z`` in metres, with standard errors);
``time_offset_s`` (+ ``time_offset_std_s``) is how far the camera's frame stamps are behind the true
exposure instants relative to the joint log (the log is sampled at ``stamp - time_offset_s``).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.limits import HAND_EYE_MAX_M, JOINT_OFFSET_ABS_MAX_RAD, POSITION_ABS_MAX_M
from darp.formats.schema import (
    as_array,
    as_dict,
    as_float,
    as_int,
    as_rigid_transform,
    as_str,
    load_json_object,
    refuse_unknown_keys,
    to_jsonable,
    write_json_checked,
)

SCHEMA_VERSION = 1
N_JOINTS = 6
TOP_KEYS = ("schema_version", "epoch", "date", "board", "world_frame", "arms", "report")
ARM_KEYS = ("serial", "T_world_base", "T_wrist_cam", "joint_offsets_rad", "joint_offsets_std_rad", "identifiable",
            "residuals", "n_captures", "kinematics", "depth_correction", "time_offset_s", "time_offset_std_s")
DEPTH_CORRECTION_KEYS = ("model", "scale", "offset_m", "quad_per_m", "scale_std", "offset_std_m", "quad_std_per_m",
                         "quad_identifiable", "range_m", "n_captures", "n_pixels", "residual_mad_m", "notes")
DEPTH_CORRECTION_MODEL = "z_true = scale * z + offset_m + quad_per_m * z^2"


def _refuse_unknown(record: dict[str, Any], known: tuple[str, ...], where: str, path: Path | None) -> None:
    refuse_unknown_keys(record, known, where, path)


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board as printed: squares, their size, the marker size and the ArUco dictionary."""

    squares_x: int
    squares_y: int
    square_length_m: float
    marker_length_m: float
    dictionary: str  # OpenCV name, e.g. "DICT_5X5_100"


@dataclass(frozen=True)
class DepthCorrection:
    """One camera's depth correction: ``z_true = scale * z + offset_m + quad_per_m * z**2`` (metres).

    Estimated from board captures (``darp.calibration.depth_fit``); the ``*_std`` fields are standard
    errors; ``quad_identifiable`` says whether the distance-dependent term was estimated (False: fixed at 0);
    ``range_m`` is the span of measured depths the fit saw (outside it the model is extrapolated).
    """

    scale: float = 1.0
    offset_m: float = 0.0
    quad_per_m: float = 0.0
    scale_std: float | None = None
    offset_std_m: float | None = None
    quad_std_per_m: float | None = None
    quad_identifiable: bool = False
    range_m: tuple[float, float] | None = None
    n_captures: int = 0
    n_pixels: int = 0
    residual_mad_m: float | None = None
    notes: str = ""

    def apply(self, depth_m: np.ndarray) -> np.ndarray:
        """Corrected depth (float64 metres); 0 (no depth) stays 0, a correction below 0 becomes 0."""
        z = np.asarray(depth_m, dtype=np.float64)
        out = self.scale * z + self.offset_m + self.quad_per_m * z * z
        return np.where(z > 0, np.maximum(out, 0.0), 0.0)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"model": DEPTH_CORRECTION_MODEL, "scale": self.scale, "offset_m": self.offset_m,
                               "quad_per_m": self.quad_per_m}
        for key in ("scale_std", "offset_std_m", "quad_std_per_m"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        out["quad_identifiable"] = bool(self.quad_identifiable)
        if self.range_m is not None:
            out["range_m"] = [float(v) for v in self.range_m]
        out.update({"n_captures": int(self.n_captures), "n_pixels": int(self.n_pixels)})
        if self.residual_mad_m is not None:
            out["residual_mad_m"] = self.residual_mad_m
        if self.notes:
            out["notes"] = self.notes
        return out


def depth_correction_from_dict(value: Any, where: str, path: Path | None) -> DepthCorrection:
    """Parse and check a ``depth_correction`` record (scale within 0.8..1.2, offset within +-0.1 m)."""
    data = as_dict(value, where, path)
    _refuse_unknown(data, DEPTH_CORRECTION_KEYS, where, path)
    missing = [k for k in ("scale", "offset_m") if k not in data]
    if missing:
        raise FormatError(f"{where}: missing {', '.join(missing)}", path)
    if "model" in data and data["model"] != DEPTH_CORRECTION_MODEL:
        raise FormatError(f"{where}.model: expected {DEPTH_CORRECTION_MODEL!r}, got {data['model']!r}", path)

    def opt(key: str) -> float | None:
        return None if data.get(key) is None else as_float(data[key], f"{where}.{key}", path)

    rng = data.get("range_m")
    corr = DepthCorrection(
        scale=as_float(data["scale"], f"{where}.scale", path, positive=True),
        offset_m=as_float(data["offset_m"], f"{where}.offset_m", path),
        quad_per_m=as_float(data.get("quad_per_m", 0.0), f"{where}.quad_per_m", path),
        scale_std=opt("scale_std"), offset_std_m=opt("offset_std_m"), quad_std_per_m=opt("quad_std_per_m"),
        quad_identifiable=bool(data.get("quad_identifiable", False)),
        range_m=None if rng is None else tuple(float(v) for v in as_array(rng, f"{where}.range_m", path, (2,))),  # type: ignore[arg-type]
        n_captures=as_int(data.get("n_captures", 0), f"{where}.n_captures", path, minimum=0),
        n_pixels=as_int(data.get("n_pixels", 0), f"{where}.n_pixels", path, minimum=0),
        residual_mad_m=opt("residual_mad_m"),
        notes=as_str(data.get("notes", ""), f"{where}.notes", path),
    )
    if not (0.8 <= corr.scale <= 1.2 and abs(corr.offset_m) <= 0.1 and abs(corr.quad_per_m) <= 0.2):
        raise FormatError(f"{where}: scale {corr.scale:.4g}, offset {corr.offset_m:.4g} m, quad "
                          f"{corr.quad_per_m:.4g} /m is not a plausible depth correction", path)
    return corr


@dataclass
class ArmCalibration:
    """The static transforms and joint-zero correction of one arm."""

    serial: str  # camera serial on this arm's wrist
    T_world_base: np.ndarray  # frame naming convention: T_to_from
    T_wrist_cam: np.ndarray
    joint_offsets_rad: np.ndarray = field(default_factory=lambda: np.zeros(N_JOINTS))
    joint_offsets_std_rad: np.ndarray | None = None
    identifiable: tuple[bool, ...] | None = None  # per joint: could its offset be estimated?
    residuals: dict[str, Any] = field(default_factory=dict)
    n_captures: int | None = None
    # the richer kinematic model (issue 16 item 1; darp.kinematics.kinematic_model.KinematicParams.to_dict
    # plus "model" and "identifiability"); None: the paper's model (joint zeros only)
    kinematics: dict[str, Any] | None = None
    depth_correction: DepthCorrection | None = None  # issue 16 item 3 (absent: nothing to apply)
    time_offset_s: float | None = None  # issue 16 item 2: log sampled at frame stamp - offset
    time_offset_std_s: float | None = None


@dataclass
class Calibration:
    """One epoch's calibration of the whole rig."""

    epoch: str
    date: str  # ISO 8601
    arms: dict[str, ArmCalibration]
    board: CharucoBoardSpec | None = None
    world_frame: str = ""
    report: dict[str, Any] = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION

    def arm(self, name: str) -> ArmCalibration:
        """The calibration of arm ``name``, or an error listing the arms there are."""
        try:
            return self.arms[name]
        except KeyError:
            raise FormatError(
                f"no calibration for arm {name!r} (arms: {', '.join(self.arms) or 'none'})"
            ) from None

    def arm_for_serial(self, serial: str) -> str:
        """The arm whose wrist carries camera ``serial``."""
        for name, arm in self.arms.items():
            if arm.serial == serial:
                return name
        raise FormatError(f"no arm carries camera {serial!r} in calibration epoch {self.epoch!r}")


def board_from_dict(value: Any, path: Path | None = None) -> CharucoBoardSpec:
    """Parse and validate a ChArUco board spec (the ``board`` record of calibration and capture files)."""
    board = as_dict(value, "board", path)
    missing = [k for k in ("squares_x", "squares_y", "square_length_m", "marker_length_m", "dictionary")
               if k not in board]
    if missing:
        raise FormatError(f"board: missing {', '.join(missing)}", path)
    spec = CharucoBoardSpec(
        squares_x=as_int(board["squares_x"], "board.squares_x", path, minimum=2),
        squares_y=as_int(board["squares_y"], "board.squares_y", path, minimum=2),
        square_length_m=as_float(board["square_length_m"], "board.square_length_m", path, positive=True),
        marker_length_m=as_float(board["marker_length_m"], "board.marker_length_m", path, positive=True),
        dictionary=as_str(board["dictionary"], "board.dictionary", path),
    )
    if spec.marker_length_m >= spec.square_length_m:
        raise FormatError("board: marker_length_m must be smaller than square_length_m", path)
    return spec


def _arm_from(name: str, value: Any, path: Path | None) -> ArmCalibration:
    where = f"arms.{name}"
    arm = as_dict(value, where, path)
    missing = [k for k in ("serial", "T_world_base", "T_wrist_cam", "joint_offsets_rad") if k not in arm]
    if missing:
        raise FormatError(f"{where}: missing {', '.join(missing)}", path)
    _refuse_unknown(arm, ARM_KEYS, where, path)
    std = arm.get("joint_offsets_std_rad")
    flags = arm.get("identifiable")
    if flags is not None and (
        not isinstance(flags, list) or len(flags) != N_JOINTS or not all(isinstance(f, bool) for f in flags)
    ):
        raise FormatError(f"{where}.identifiable: expected a list of {N_JOINTS} booleans", path)
    n_captures = arm.get("n_captures")
    result = ArmCalibration(
        serial=as_str(arm["serial"], f"{where}.serial", path),
        T_world_base=as_rigid_transform(arm["T_world_base"], f"{where}.T_world_base", path),
        T_wrist_cam=as_rigid_transform(arm["T_wrist_cam"], f"{where}.T_wrist_cam", path),
        joint_offsets_rad=as_array(arm["joint_offsets_rad"], f"{where}.joint_offsets_rad", path, (N_JOINTS,)),
        joint_offsets_std_rad=None if std is None
        else as_array(std, f"{where}.joint_offsets_std_rad", path, (N_JOINTS,)),
        identifiable=None if flags is None else tuple(flags),
        residuals=as_dict(arm.get("residuals", {}), f"{where}.residuals", path),
        n_captures=None if n_captures is None else as_int(n_captures, f"{where}.n_captures", path, minimum=0),
        kinematics=None if arm.get("kinematics") is None else as_dict(arm["kinematics"], f"{where}.kinematics", path),
        depth_correction=None if arm.get("depth_correction") is None
        else depth_correction_from_dict(arm["depth_correction"], f"{where}.depth_correction", path),
        time_offset_s=None if arm.get("time_offset_s") is None
        else as_float(arm["time_offset_s"], f"{where}.time_offset_s", path),
        time_offset_std_s=None if arm.get("time_offset_std_s") is None
        else as_float(arm["time_offset_std_s"], f"{where}.time_offset_std_s", path),
    )
    if result.time_offset_s is not None and abs(result.time_offset_s) > 1.0:
        raise FormatError(f"{where}.time_offset_s: {result.time_offset_s!r} s is not a plausible camera latency "
                          "(more than 1 s)", path)
    _check_ranges(result, where, path)
    return result


def _check_ranges(arm: ArmCalibration, where: str, path: Path | None) -> None:
    """Refuse transforms and offsets outside the plausible ranges (docs/reliability.md)."""
    base = np.asarray(arm.T_world_base)[:3, 3]
    if float(np.max(np.abs(base))) > POSITION_ABS_MAX_M:
        shown = ", ".join(f"{v:.3g}" for v in base)
        raise FormatError(f"{where}.T_world_base: translation [{shown}] m is more than {POSITION_ABS_MAX_M:g} m "
                          "from the world origin", path)
    cam = float(np.linalg.norm(np.asarray(arm.T_wrist_cam)[:3, 3]))
    if cam > HAND_EYE_MAX_M:
        raise FormatError(f"{where}.T_wrist_cam: the camera is {cam:.3g} m from the flange (more than "
                          f"{HAND_EYE_MAX_M:g} m)", path)
    dq = np.abs(np.asarray(arm.joint_offsets_rad))
    if float(dq.max()) > JOINT_OFFSET_ABS_MAX_RAD:
        j = int(dq.argmax())
        raise FormatError(f"{where}.joint_offsets_rad: joint{j + 1} offset {float(arm.joint_offsets_rad[j])!r} rad is "
                          f"beyond +-{JOINT_OFFSET_ABS_MAX_RAD:g} rad", path)


def calibration_from_dict(payload: dict[str, Any], path: str | Path | None = None) -> Calibration:
    """Validate a parsed JSON object and build the :class:`Calibration`."""
    path = Path(path) if path is not None else None
    if "schema_version" not in payload:
        raise FormatError("missing schema_version", path)
    version = as_int(payload["schema_version"], "schema_version", path, minimum=1)
    if version > SCHEMA_VERSION:
        raise FormatError(
            f"schema_version {version} is newer than this darp understands ({SCHEMA_VERSION})", path
        )
    missing = [k for k in ("epoch", "date", "arms") if k not in payload]
    if missing:
        raise FormatError(f"missing {', '.join(missing)}", path)
    _refuse_unknown(payload, TOP_KEYS, "", path)
    date = as_str(payload["date"], "date", path)
    try:
        dt.datetime.fromisoformat(date)
    except ValueError:
        raise FormatError(f"date: not an ISO 8601 date: {date!r}", path) from None
    arms = as_dict(payload["arms"], "arms", path)
    if not arms:
        raise FormatError("arms: no arm calibrated", path)
    board = payload.get("board")
    parsed = {name: _arm_from(name, value, path) for name, value in arms.items()}
    serials: dict[str, str] = {}
    for name, arm in parsed.items():
        if arm.serial and arm.serial in serials:  # any-arm calibrations may have no camera serial
            raise FormatError(f"arms.{name}.serial: camera {arm.serial} is also on arms.{serials[arm.serial]}", path)
        serials[arm.serial] = name
    return Calibration(
        epoch=as_str(payload["epoch"], "epoch", path),
        date=date,
        arms=parsed,
        board=None if board is None else board_from_dict(board, path),
        world_frame=as_str(payload.get("world_frame", ""), "world_frame", path),
        report=as_dict(payload.get("report", {}), "report", path),
        schema_version=version,
    )


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    """The JSON object for ``cal`` (schema 1)."""
    arms: dict[str, Any] = {}
    for name, arm in cal.arms.items():
        entry: dict[str, Any] = {
            "serial": arm.serial,
            "T_world_base": np.asarray(arm.T_world_base, dtype=float).tolist(),
            "T_wrist_cam": np.asarray(arm.T_wrist_cam, dtype=float).tolist(),
            "joint_offsets_rad": np.asarray(arm.joint_offsets_rad, dtype=float).tolist(),
        }
        if arm.joint_offsets_std_rad is not None:
            entry["joint_offsets_std_rad"] = np.asarray(arm.joint_offsets_std_rad, dtype=float).tolist()
        if arm.identifiable is not None:
            entry["identifiable"] = [bool(f) for f in arm.identifiable]
        entry["residuals"] = arm.residuals
        if arm.n_captures is not None:
            entry["n_captures"] = int(arm.n_captures)
        if arm.kinematics is not None:
            entry["kinematics"] = arm.kinematics
        if arm.depth_correction is not None:
            entry["depth_correction"] = arm.depth_correction.to_dict()
        if arm.time_offset_s is not None:
            entry["time_offset_s"] = float(arm.time_offset_s)
        if arm.time_offset_std_s is not None:
            entry["time_offset_std_s"] = float(arm.time_offset_std_s)
        arms[name] = entry
    board = None if cal.board is None else {
        "squares_x": cal.board.squares_x,
        "squares_y": cal.board.squares_y,
        "square_length_m": cal.board.square_length_m,
        "marker_length_m": cal.board.marker_length_m,
        "dictionary": cal.board.dictionary,
    }
    return {
        "schema_version": SCHEMA_VERSION,
        "epoch": cal.epoch,
        "date": cal.date,
        "board": board,
        "world_frame": cal.world_frame,
        "arms": arms,
        "report": cal.report,
    }


def read_calibration(path: str | Path) -> Calibration:
    """Read and validate a calibration file."""
    return calibration_from_dict(load_json_object(path), Path(path))


def write_calibration(path: str | Path, cal: Calibration) -> None:
    """Validate ``cal`` with the reader's rules and write it atomically."""
    payload = to_jsonable(calibration_to_dict(cal))
    calibration_from_dict(payload, path)  # refuse to write what the reader would refuse
    write_json_checked(path, payload)
