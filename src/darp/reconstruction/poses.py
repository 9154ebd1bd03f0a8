"""Camera trajectories of a whole survey: eq. 1 at every frame of both cameras, and their outputs.

``recover_survey_poses`` reads the survey (joint log and each recording's frame index; no pixels) and
evaluates :func:`darp.kinematics.camera_poses.camera_poses` per arm. ``write_survey_poses`` writes,
per camera, a TUM trajectory (posed frames only) and an ``.npz`` with every frame, plus
``summary.json`` (and the figure, see :mod:`darp.reconstruction.rig_figures`). Every file is written
atomically; the survey folder is never written to.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError, SurveyError
from darp.formats.atomic import atomic_open
from darp.formats.calibration import ArmCalibration, Calibration
from darp.formats.envelope import Envelope
from darp.formats.realsense.recording import Recording
from darp.formats.schema import write_json_checked
from darp.formats.survey import Survey
from darp.formats.trajectories import TUM_HEADER, write_tum
from darp.kinematics.camera_poses import DEFAULT_MAX_GAP_S, STATUS_NAMES, CameraPoses, camera_poses
from darp.kinematics.kinematic_model import KinematicParams, fk_batch_params
from darp.reconstruction.keyframes import joint_speed_noise

_log = logging.getLogger(__name__)

HOST_TIME_DOMAINS = ("Global Time", "System Time")
SUMMARY_FILE = "summary.json"
TUM_COMMENTS = (f"# {TUM_HEADER}  (T_world_cam; seconds, metres)",)
FIGURE_FILE = "trajectories.png"


@dataclass(frozen=True)
class CameraTrajectory:
    """One camera's frames (of one stream) with their eq. 1 poses."""

    arm: str
    serial: str
    stream: str
    frame_numbers: np.ndarray  # (N,) device frame counters
    timestamps_ms: np.ndarray  # (N,) frame timestamps as recorded (camera clock)
    timestamp_domains: tuple[str, ...]  # distinct domains seen in the stream
    poses: CameraPoses
    log_span_s: tuple[float, float]  # first and last joint-log time of this arm (host clock)
    log_rows: int
    speed_noise_rad_s: float = 0.0  # the joint log's measured speed noise (keyframes.joint_speed_noise)

    @property
    def camera_span_s(self) -> tuple[float, float] | None:
        if self.timestamps_ms.size == 0:
            return None
        return float(self.timestamps_ms.min()) / 1000.0, float(self.timestamps_ms.max()) / 1000.0

    @property
    def file_stem(self) -> str:
        return f"cam{self.serial}_{self.arm}"

    def summary(self) -> dict[str, Any]:
        return {
            "serial": self.serial,
            "stream": self.stream,
            **self.poses.counts(),
            "log_rows": self.log_rows,
            "log_span_s": list(self.log_span_s),
            "speed_noise_rad_s": self.speed_noise_rad_s,
            "camera_span_s": None if self.camera_span_s is None else list(self.camera_span_s),
            "timestamp_domains": list(self.timestamp_domains),
        }


@dataclass
class SurveyPoses:
    """Trajectories of every camera of a survey and how they were made."""

    survey_path: Path
    calibration: Calibration
    calibration_path: Path | None  # None: the rig's nominal values
    stream: str
    max_gap_s: float
    clock_offset_s: float
    trajectories: dict[str, CameraTrajectory]
    envelope: Envelope | None = None
    warnings: list[str] = field(default_factory=list)
    # the richer kinematic model per arm when corrections.kinematics is on (None: off, the paper's eq. 1)
    kinematics: dict[str, Any] | None = None
    time_alignment: dict[str, Any] = field(default_factory=dict)  # what the time alignment did (issue 16)

    def summary(self) -> dict[str, Any]:
        extra = {} if self.kinematics is None else {"kinematics": self.kinematics}
        if self.time_alignment:
            extra["time_alignment"] = self.time_alignment
        return {
            "survey": str(self.survey_path),
            "calibration": {
                "path": None if self.calibration_path is None else str(self.calibration_path),
                "epoch": self.calibration.epoch,
                "nominal": self.calibration_path is None,
            },
            "stream": self.stream,
            "max_gap_s": self.max_gap_s,
            "clock_offset_s": self.clock_offset_s,
            "arms": {arm: traj.summary() for arm, traj in self.trajectories.items()},
            "warnings": list(self.warnings),
            **extra,
        }


def recover_survey_poses(
    survey: Survey,
    calibration: Calibration,
    *,
    calibration_path: Path | None = None,
    stream: str = "depth",
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    clock_offset_s: float = 0.0,
    wrist_frame: str = "flange",
    on_arm: Callable[[str], None] | None = None,
    open_recording: Callable[[str], AbstractContextManager[Recording]] | None = None,
    kinematics: bool = False,
    time_offsets_s: Mapping[str, float] | None = None,
) -> SurveyPoses:
    """Eq. 1 at every ``stream`` frame of every camera of ``survey``.

    ``on_arm(arm)`` is called before each arm is processed (for progress display). A camera whose
    serial differs from the calibration's for its arm is refused: its poses would belong to another arm.
    ``open_recording(arm)``: a context manager giving ``arm``'s recording (default: ``survey.open_recording``,
    which opens and closes it; a caller that holds the recordings open passes its own).
    ``kinematics``: use the calibration's richer kinematic model (``kinematics`` per arm: joint origins, axis
    tilts, compliance; :mod:`darp.kinematics.kinematic_model`) in eq. 1; an arm without one is posed with the
    paper's model and a warning naming the calibration file.
    ``time_offsets_s``: per arm, the camera's frame-stamp latency (issue 16's time alignment): the log is
    sampled at ``stamp - clock_offset_s - offset``; absent arms get none.
    """
    opener = open_recording if open_recording is not None else survey.open_recording
    log = survey.arm_poses()
    result = SurveyPoses(
        survey_path=survey.path,
        calibration=calibration,
        calibration_path=calibration_path,
        stream=stream,
        max_gap_s=max_gap_s,
        clock_offset_s=clock_offset_s,
        trajectories={},
        envelope=survey.envelope(),
    )
    if kinematics:
        result.kinematics = {}
    for arm in survey.arms:
        if on_arm is not None:
            on_arm(arm)
        try:
            cal = calibration.arms[arm]
        except KeyError:
            raise SurveyError(
                f"the calibration (epoch {calibration.epoch!r}) has no arm {arm!r} "
                f"(arms: {', '.join(calibration.arms)})", survey.path) from None
        serial = survey.serials[arm]
        if cal.serial != serial:
            raise SurveyError(
                f"{arm}'s camera is {serial} but the calibration (epoch {calibration.epoch!r}) "
                f"calibrated camera {cal.serial} on {arm}", survey.path)
        with opener(arm) as recording:
            infos = recording.frame_infos(recording.stream(stream).key)
        frame_numbers = np.array([i.frame_number for i in infos], dtype=np.int64)
        timestamps_ms = np.array([i.timestamp_ms for i in infos], dtype=np.float64)
        domains = tuple(sorted({i.timestamp_domain for i in infos}))
        foreign = [d for d in domains if d not in HOST_TIME_DOMAINS]
        if foreign:
            result.warnings.append(
                f"{arm}: {stream} timestamps are in the {', '.join(foreign)} domain, not host time; "
                "poses assume camera time = host time + clock offset")
        log_t, log_q = log.times(arm), log.joints(arm)
        T_world_base, T_wrist_cam, joint_offsets, fk, info = eq1_model(
            cal, arm, calibration_path=calibration_path, kinematics=result.kinematics is not None,
            wrist_frame=wrist_frame, warnings=result.warnings)
        log_q = with_backlash(log_q, info)
        if result.kinematics is not None:
            result.kinematics[arm] = info
        poses = camera_poses(
            log_t, log_q, timestamps_ms / 1000.0,
            T_world_base=T_world_base, T_wrist_cam=T_wrist_cam,
            joint_offsets_rad=joint_offsets, max_gap_s=max_gap_s,
            clock_offset_s=clock_offset_s + float((time_offsets_s or {}).get(arm, 0.0)), wrist_frame=wrist_frame,
            fk_batch=fk,
        )
        counts = poses.counts()
        if counts["frames"] and counts["posed"] == 0:
            result.warnings.append(
                f"{arm}: none of {counts['frames']} frames lies inside the joint log "
                f"({log_t[0]:.3f} .. {log_t[-1]:.3f} s); check the clock offset")
        result.trajectories[arm] = CameraTrajectory(
            arm=arm, serial=serial, stream=stream, frame_numbers=frame_numbers,
            timestamps_ms=timestamps_ms, timestamp_domains=domains, poses=poses,
            log_span_s=(float(log_t[0]), float(log_t[-1])), log_rows=int(log_t.size),
            speed_noise_rad_s=joint_speed_noise(log_t, log_q),
        )
    return result


def eq1_model(cal: ArmCalibration, arm: str, *, calibration_path: Path | None = None, kinematics: bool = False,
              wrist_frame: str = "flange", warnings: list[str] | None = None,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray] | None, dict[str, Any]]:
    """Eq. 1's inputs for one arm: ``T_world_base``, ``T_wrist_cam``, joint zeros, forward kinematics (None:
    the nominal Z1's) and what was applied. With ``kinematics`` and a calibration that has the richer model,
    its own transforms and forward kinematics; else the paper model's (a warning appended when asked for)."""
    if not kinematics:
        return cal.T_world_base, cal.T_wrist_cam, cal.joint_offsets_rad, None, {}
    fk, info = _kinematic_fk(cal, arm, calibration_path, wrist_frame, [] if warnings is None else warnings)
    if fk is None or cal.kinematics is None:
        return cal.T_world_base, cal.T_wrist_cam, cal.joint_offsets_rad, None, info
    T_world_base, T_wrist_cam, joint_offsets = _kinematic_transforms(cal.kinematics, arm, calibration_path, cal)
    return T_world_base, T_wrist_cam, joint_offsets, fk, info


def _kinematic_fk(cal: ArmCalibration, arm: str, calibration_path: Path | None, wrist_frame: str,
                  warnings: list[str]) -> tuple[Callable[[np.ndarray], np.ndarray] | None, dict[str, Any]]:
    """The richer model's forward kinematics of one arm and what was applied (None: paper model, warned)."""
    where = calibration_path if calibration_path is not None else "the calibration"
    if cal.kinematics is None:
        message = (f"{arm}: {where} has no kinematics (solve it with darp calib solve --model kinematic...); "
                   "posed with the paper's model")
        warnings.append(message)
        _log.warning(message)
        return None, {"applied": False, "reason": "calibration has no kinematics"}
    try:
        params = KinematicParams.from_dict(cal.kinematics, f"arms.{arm}.kinematics")
    except FormatError as err:
        raise FormatError(err.message, calibration_path) from None
    info: dict[str, Any] = {"applied": True, "model": cal.kinematics.get("model"),
                            "estimated": list(cal.kinematics.get("estimated", [])),
                            "compliance_rad_per_nm": params.compliance_rad_per_nm.tolist()}
    if params.has_backlash:  # applied to the joint log by the caller (it needs the log's history)
        info["backlash_rad"] = params.backlash_rad.tolist()
        params = replace(params, backlash_rad=np.zeros(6))
    return (lambda Q: fk_batch_params(Q, params, wrist_frame)), info


def _kinematic_transforms(kin: dict[str, Any], arm: str, calibration_path: Path | None,
                          cal: ArmCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``T_world_base``, ``T_wrist_cam`` and joint zeros solved with the richer model (the arm's own when absent)."""
    out = []
    for key, shape, default in (("T_world_base", (4, 4), cal.T_world_base), ("T_wrist_cam", (4, 4), cal.T_wrist_cam),
                                ("joint_offsets_rad", (6,), cal.joint_offsets_rad)):
        value = np.asarray(kin.get(key, default), dtype=float)
        if value.shape != shape or not np.all(np.isfinite(value)):
            raise FormatError(f"arms.{arm}.kinematics.{key}: expected finite {shape} values", calibration_path)
        out.append(value)
    return out[0], out[1], out[2]


def with_backlash(log_q: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """The joint log as link angles under the richer model's backlash (``info`` from :func:`eq1_model`):
    each joint ``b`` behind its last move; the log unchanged when the model has no backlash. Records the
    number of direction changes in ``info``."""
    if info.get("backlash_rad") is None:
        return log_q
    direction = motion_directions(log_q)
    info["backlash_direction_changes"] = int(np.count_nonzero(np.diff(direction, axis=0)))
    out: np.ndarray = log_q - np.asarray(info["backlash_rad"], dtype=float) * direction
    return out


def motion_directions(log_q: np.ndarray, min_rows: int = 3, k_sigma: float = 4.0) -> np.ndarray:
    """Each joint's last motion direction (-1 / 0 / +1) at every row of a joint log (N, 6).

    The log is cut into settled runs (at least ``min_rows`` rows between which no joint steps by more
    than ``k_sigma`` x the encoder noise, measured from the log's second differences) and the moves
    between them. A joint's direction at a move and the run after it is the sign of the change of its
    mean from the previous run to this one, when that change exceeds ``k_sigma`` x its standard error
    (a smaller one keeps the previous direction); 0 before the first detected move. Small moves count:
    the link takes up its backlash on the side of any commanded move, however small. The richer
    model's backlash (:func:`darp.kinematics.kinematic_model.link_angles`) puts the link ``b`` behind:
    ``q_link = q - b * direction``.
    """
    Q = np.asarray(log_q, dtype=float)
    n = Q.shape[0]
    out = np.zeros(Q.shape)
    if n < 2 * min_rows:
        return out
    d2 = Q[2:] - 2.0 * Q[1:-1] + Q[:-2]
    noise = np.maximum(1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0), 1e-7)
    moving = np.any(np.abs(np.diff(Q, axis=0)) > k_sigma * np.sqrt(2.0) * noise, axis=1)  # (n - 1,) steps
    still = np.ones(n, bool)
    still[:-1] &= ~moving
    still[1:] &= ~moving
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0]))
    runs = [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= min_rows]
    direction = np.zeros(Q.shape[1])
    prev: tuple[int, int] | None = None
    for a, b in runs:
        if prev is not None:
            delta = Q[a:b].mean(axis=0) - Q[prev[0]:prev[1]].mean(axis=0)
            limit = k_sigma * noise * np.sqrt(1.0 / (prev[1] - prev[0]) + 1.0 / (b - a))
            direction = np.where(np.abs(delta) > limit, np.sign(delta), direction)
            out[prev[1]:a] = direction  # the move itself
        out[a:b] = direction
        prev = (a, b)
    if prev is not None:
        out[prev[1]:] = direction
    return out


# -- writing ---------------------------------------------------------------------------------------
def write_survey_poses(result: SurveyPoses, out_dir: str | Path) -> dict[str, Path]:
    """Write TUM + npz per camera and ``summary.json`` into ``out_dir``; returns the paths by name."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise SurveyError("output path exists and is not a folder", out)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    summary = result.summary()
    for arm, traj in result.trajectories.items():
        posed = traj.poses.posed
        tum = out / f"{traj.file_stem}.tum"
        write_tum(tum, [f"{t:.6f}" for t in traj.timestamps_ms[posed] / 1000.0], traj.poses.T_world_cam[posed],
                  TUM_COMMENTS, "{:.9f}".format)
        npz = out / f"{traj.file_stem}.npz"
        with atomic_open(npz, "wb") as handle:
            np.savez(
                handle,
                frame_numbers=traj.frame_numbers,
                timestamps_ms=traj.timestamps_ms,
                T_world_cam=traj.poses.T_world_cam,
                status=traj.poses.status,
                status_names=np.array(STATUS_NAMES),
                joint_velocity=traj.poses.joint_velocity_rad_s,
                q_rad=traj.poses.q_rad,
            )
        written[f"{arm}.tum"], written[f"{arm}.npz"] = tum, npz
        summary["arms"][arm].update({"tum": tum.name, "npz": npz.name})
    summary_path = out / SUMMARY_FILE
    write_json_checked(summary_path, summary)
    written["summary"] = summary_path
    return written


__all__ = [
    "FIGURE_FILE",
    "SUMMARY_FILE",
    "CameraTrajectory",
    "SurveyPoses",
    "motion_directions",
    "with_backlash",
    "recover_survey_poses",
    "write_survey_poses",
]
