"""The survey job: one survey being processed, its inputs, settings and output folder.

:class:`SurveyJob` holds what every stage needs (:mod:`darp.processing.stages`) and computes once per run
what they share: the open recordings, the camera poses (eq. 1, the twin's true poses with
``truth_poses``, shifted by the time alignment with ``corrections.time``), the envelope (estimated from
the survey when ``manip_envelope.json`` has no geometry) and the support crop. It offers the runner
(:mod:`darp.processing.runner`) its name, identity and settings fingerprints. :func:`open_job` is the
one way to open a survey folder as a job; the output folder's layout names are here too.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError, ReconstructionError
from darp.formats.calibration import Calibration, calibration_to_dict, read_calibration
from darp.formats.envelope import Envelope
from darp.formats.realsense.recording import Recording
from darp.formats.realsense.types import IMAGE_STREAMS
from darp.formats.survey import Survey, open_survey
from darp.processing.settings import ProcessSettings
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.envelope_estimate import envelope_record, estimate_survey_envelope
from darp.reconstruction.fusion import calibration_uncertainty_m
from darp.reconstruction.poses import SurveyPoses, recover_survey_poses
from darp.reconstruction.time_align import TimeAlignSettings

TIME_ALIGN = TimeAlignSettings()
POSES_DIR, KEYFRAMES_DIR, FIGURES_DIR = "poses", "keyframes", "figures"
FUSED_FILE, MESH_FILE = "fused.ply", "mesh.ply"

ProgressFn = Callable[[str, float, float | None], None]
"""``progress(stage, done, total)``; ``total`` None while a stage cannot tell how long it takes."""


@dataclass
class SurveyJob:
    """One survey being processed: inputs, settings, output folder and what stages hand on."""

    survey: Survey
    out: Path  # <out>/<survey name>
    calibration: Calibration
    calibration_path: Path | None
    settings: ProcessSettings = field(default_factory=ProcessSettings)
    truth_poses: bool = False
    progress: ProgressFn | None = None
    keyframes_folder: Path | None = None  # default: <out>/keyframes
    # what the stages share, computed once per run
    _envelope: Envelope | None = field(default=None, init=False, repr=False)
    _envelope_record: dict[str, Any] = field(default_factory=dict, init=False, repr=False)
    _recordings: dict[str, Recording] = field(default_factory=dict, init=False, repr=False)
    _poses: SurveyPoses | None = field(default=None, init=False, repr=False)
    _time_record: dict[str, Any] = field(default_factory=dict, init=False, repr=False)

    def depth_corrections(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """Per arm the depth correction to apply (``corrections.depth`` on and the calibration has one), and
        the record for results.json (``{}`` when the switch is off: paper mode)."""
        if not self.settings.corrections.depth:
            return {}, {}
        where = self.calibration_path or "the calibration"
        apply: dict[str, Any] = {}
        record: dict[str, Any] = {"applied_at": "keyframe export (stored keyframe depth is corrected)", "arms": {}}
        for arm in self.arms:
            corr = self.calibration.arms[arm].depth_correction if arm in self.calibration.arms else None
            if corr is None:
                record["arms"][arm] = {"applied": False,
                                       "reason": f"{where} has no depth_correction for {arm}: paper mode for it"}
                continue
            apply[arm] = corr
            record["arms"][arm] = {"applied": True, **corr.to_dict()}
        missing = [a for a in self.arms if a not in apply]
        if missing:
            record["warning"] = (f"corrections.depth is on but {where} has no depth_correction for "
                                 f"{', '.join(missing)} (captures without depth?): not applied there")
        return apply, record

    def report(self, stage: str, done: float, total: float | None) -> None:
        if self.progress is not None:
            self.progress(stage, done, total)

    @property
    def name(self) -> str:
        """The survey's name (the runner's ``stages.json`` and failures name it)."""
        return self.survey.name

    def identity(self) -> dict[str, Any]:
        """What the first stage's fingerprint hashes: the survey's files (names, sizes, modification times),
        the calibration and ``truth_poses``."""
        s = self.survey
        files = [*s.recording_paths.values(), s.arm_poses_path, s.envelope_path]
        return {"survey": s.name, "files": sorted((f.name, f.stat().st_size, f.stat().st_mtime_ns)
                                                  for f in files if f is not None),
                "calibration": calibration_to_dict(self.calibration), "truth_poses": self.truth_poses}

    def settings_fingerprint(self, groups: Sequence[str]) -> str:
        """A hash of the settings ``groups`` (a stage's fingerprint includes those it uses)."""
        return self.settings.fingerprint(*groups)

    @property
    def keyframes_dir(self) -> Path:
        return self.keyframes_folder if self.keyframes_folder is not None else self.out / KEYFRAMES_DIR

    @property
    def arms(self) -> tuple[str, ...]:
        return self.survey.arms

    def crop(self) -> EnvelopeCrop:
        """The object-support region: the envelope cylinder with fusion's margins (grown with the
        calibration's stated held-out error, :func:`darp.reconstruction.fusion.calibration_uncertainty_m`)."""
        return self.settings.fusion_used.crop(self.envelope(), calibration_uncertainty_m=self.calibration_uncertainty())

    def calibration_uncertainty(self) -> float | None:
        """The calibration's stated uncertainty (metres), or None when it states none."""
        return calibration_uncertainty_m(self.calibration.arms[a].residuals for a in self.arms
                                         if a in self.calibration.arms)

    def envelope(self) -> Envelope:
        """The survey's envelope; without centre/radius/height, one estimated from the survey's own
        poses and depth (:mod:`darp.reconstruction.envelope_estimate`), once per run."""
        if self._envelope is None:
            envelope = self.survey.envelope()
            if envelope is None or not envelope.has_geometry:
                estimate = estimate_survey_envelope(
                    self.poses(), self.recording, [self.calibration.arms[a].T_world_base[:2, 3] for a in self.arms],
                    keyframe_settings=self.settings.keyframes, depth_settings=self.settings.fusion_used.depth,
                    path=self.survey.path)
                self._envelope_record = estimate.to_dict()
                envelope = estimate.envelope(envelope)
            else:
                self._envelope_record = envelope_record(envelope)
            self._envelope = envelope
        return self._envelope

    def table_region(self, frame: PosedDepth) -> tuple[Any, dict[str, Any]]:
        """``corrections.table``: the region of one keyframe (the crop above its own fitted table plane, or the
        crop when none is found) and its record (:mod:`darp.reconstruction.table_plane`)."""
        from darp.reconstruction.table_plane import table_region

        return table_region(frame, self.crop(), None, self.settings.fusion_used.depth, self.calibration_uncertainty())

    def envelope_record(self) -> dict[str, Any]:
        """Where the envelope came from: ``{"source": "manip_envelope.json" | "estimated", "center_m", ...}``."""
        self.envelope()
        return self._envelope_record

    def recording(self, arm: str) -> Recording:
        """``arm``'s recording, opened once per run (reading a bag's frame index decodes every chunk)."""
        recordings = self._recordings
        if arm not in recordings:
            recording = self.survey.open_recording(arm)
            # An empty time window makes the reader index every image stream in ONE pass over the file;
            # asked stream by stream (depth for the poses, then infrared, then colour for the frame
            # sets) a .bag is decompressed once per stream, and its resident size grows with each pass.
            images = [key for key in IMAGE_STREAMS if key in recording.streams]
            for _ in recording.iter_frames(images, start_ms=math.inf, stop_ms=math.inf):
                pass
            recordings[arm] = recording
        return recordings[arm]

    def close(self) -> None:
        """Close the recordings this run opened."""
        recordings, self._recordings = self._recordings, {}
        for recording in recordings.values():
            recording.close()

    def poses(self) -> SurveyPoses:
        """Eq. 1 (or true) poses of every depth frame, computed once per run."""
        if self._poses is None:
            poses = self._recover_poses()
            if self.truth_poses:
                poses = with_truth_poses(poses, self.survey)
            self._poses = poses
            if self.settings.corrections.time and not self.truth_poses:
                offsets, self._time_record = self._time_offsets(poses)
                if offsets:
                    self._poses = self._recover_poses(offsets)
                self._poses.time_alignment = self._time_record
        return self._poses

    def _recover_poses(self, time_offsets_s: dict[str, float] | None = None) -> SurveyPoses:
        """Eq. 1 with this run's open recordings and corrections (the kinematic model, the time offsets)."""
        return recover_survey_poses(
            self.survey, self.calibration, calibration_path=self.calibration_path,
            open_recording=lambda arm: contextlib.nullcontext(self.recording(arm)),
            kinematics=self.settings.corrections.kinematics, time_offsets_s=time_offsets_s)

    def _time_offsets(self, poses: SurveyPoses) -> tuple[dict[str, float], dict[str, Any]]:
        """Per arm the camera's time offset: the calibration's ``time_offset_s`` when it has one, else
        estimated from this survey's moving frames (:mod:`darp.reconstruction.time_align`)."""
        from darp.reconstruction.time_align import accept, estimate_arm_offset, pooled_offset, reference_surface

        offsets: dict[str, float] = {}
        record: dict[str, Any] = {"arms": {}}
        to_estimate = []
        for arm in self.arms:
            cal = self.calibration.arms[arm]
            if cal.time_offset_s is not None:
                offsets[arm] = float(cal.time_offset_s)
                record["arms"][arm] = {"source": "calibration", "offset_s": cal.time_offset_s,
                                       "std_s": cal.time_offset_std_s}
            else:
                to_estimate.append(arm)
        if to_estimate:
            region = self.crop()
            depth = self.settings.fusion_used.depth
            estimates = {}
            for arm in to_estimate:
                # the arm's own settled frames: the other arm's carry the base-to-base error, which a moving
                # frame of this arm would also be pulled toward
                frames = self._arm_frames(arm, poses)
                reference = reference_surface([frames], region, TIME_ALIGN, depth)
                if reference is None:
                    record["arms"][arm] = {"source": "survey", "offset_s": None,
                                           "reason": "no settled frame sees the support region"}
                    continue
                estimates[arm] = estimate_arm_offset(frames, reference, region, TIME_ALIGN, depth)
            pooled = pooled_offset(list(estimates.values()), TIME_ALIGN) if len(estimates) > 1 else None
            if pooled is not None:
                record["pooled"] = {k: v for k, v in pooled.to_dict().items() if k not in ("grid_s", "cost_mm2")}
            for arm, est in estimates.items():
                entry = {"source": "survey", **est.to_dict()}
                if accept(est, TIME_ALIGN):
                    offsets[arm] = float(est.offset_s)  # type: ignore[arg-type]
                elif pooled is not None and accept(pooled, TIME_ALIGN):
                    offsets[arm] = float(pooled.offset_s)  # type: ignore[arg-type]
                    entry["applied"] = f"pooled estimate (this camera's std above {TIME_ALIGN.max_std_s:g} s)"
                else:
                    entry["not_applied"] = (f"std above {TIME_ALIGN.max_std_s:g} s"
                                            if est.offset_s is not None else est.reason)
                record["arms"][arm] = entry
        not_applied = [a for a in self.arms if a not in offsets]
        if not_applied:
            record["warning"] = (f"corrections.time is on but no time offset for {', '.join(not_applied)}: "
                                 "paper mode (frame stamps as recorded) there")
        record["applied_s"] = offsets
        return offsets, record

    def _arm_frames(self, arm: str, poses: SurveyPoses) -> Any:
        """The time-offset estimator's view of one arm (joint log, eq. 1 inputs, depth decoder)."""
        from darp.reconstruction.keyframe_io import frameset_at
        from darp.reconstruction.keyframes import settled_mask
        from darp.reconstruction.poses import eq1_model, with_backlash
        from darp.reconstruction.time_align import ArmFrames

        traj = poses.trajectories[arm]
        log = self.survey.arm_poses()
        cal = self.calibration.arms[arm]
        # the same eq. 1 as the poses (the richer model's transforms, kinematics and backlash when that switch is on)
        T_world_base, T_wrist_cam, joint_offsets, fk, info = eq1_model(
            cal, arm, calibration_path=self.calibration_path, kinematics=self.settings.corrections.kinematics)
        recording = self.recording(arm)
        threshold = self.settings.keyframes.still_threshold(traj.speed_noise_rad_s)
        speed = traj.poses.joint_speed_rad_s

        def read_depth(index: int) -> np.ndarray:
            frameset = frameset_at(recording, index)
            assert frameset.depth is not None
            return np.asarray(frameset.depth.data, np.uint16)

        intr = recording.stream("depth").intrinsics
        assert intr is not None
        return ArmFrames(arm=arm, log_t_s=log.times(arm), log_q_rad=with_backlash(log.joints(arm), info),
                         frame_t_s=traj.poses.t_s,
                         T_world_cam=traj.poses.T_world_cam, joint_speed_rad_s=speed,
                         still=settled_mask(traj.poses.t_s, speed, self.settings.keyframes, threshold),
                         T_world_base=T_world_base, T_wrist_cam=T_wrist_cam,
                         joint_offsets_rad=joint_offsets, intrinsics=intr,
                         depth_scale=float(recording.depth_scale), read_depth=read_depth, fk_batch=fk)

    def time_alignment_record(self) -> dict[str, Any]:
        """What the time alignment did ({} when ``corrections.time`` is off)."""
        self.poses()
        return self._time_record


# -- truth poses (the accuracy floor) -----------------------------------------------------------------
def with_truth_poses(poses: SurveyPoses, survey: Survey) -> SurveyPoses:
    """The same frames with the twin's TRUE camera poses (``truth/camera_poses_<arm>.npz``), by frame number.

    Joint velocities (for keyframe selection) stay those of the joint log. Frames the truth lacks
    lose their pose.
    """
    from darp.formats.truth import read_camera_poses
    from darp.kinematics.camera_poses import CameraPoses

    if survey.truth_path is None:
        raise ReconstructionError("--truth-poses needs a twin survey with a truth/ folder", survey.path)
    trajectories = {}
    for arm, traj in poses.trajectories.items():
        truth = read_camera_poses(survey.truth_path / f"camera_poses_{arm}.npz")
        lookup = {int(n): i for i, n in enumerate(truth["frame_number"])}
        T = np.full_like(traj.poses.T_world_cam, np.nan)
        status = traj.poses.status.copy()
        for i, n in enumerate(traj.frame_numbers.tolist()):
            if n in lookup:
                T[i] = truth["T_world_cam"][lookup[n]]
            else:
                status[i] = max(int(status[i]), 1)
        true_poses = CameraPoses(traj.poses.t_s, T, status, traj.poses.q_rad, traj.poses.joint_velocity_rad_s)
        trajectories[arm] = dataclasses.replace(traj, poses=true_poses)
    return dataclasses.replace(poses, trajectories=trajectories,
                               warnings=[*poses.warnings, "poses are the twin's TRUE camera poses (--truth-poses)"])



# -- opening a survey folder as a job -------------------------------------------------------------------------
def survey_calibration(survey_path: str | Path, calibration_path: str | Path | None) -> Calibration:
    """The calibration a survey is processed with: ``calibration_path``, or the twin's true one
    (``<survey>/truth/calibration.json``) when it is None."""
    if calibration_path is not None:
        return read_calibration(calibration_path)
    truth = Path(survey_path) / "truth" / "calibration.json"
    if not truth.is_file():
        raise FormatError("no truth/calibration.json (only twin surveys have one): give a calibration",
                          Path(survey_path))
    return read_calibration(truth)


def open_job(survey_path: str | Path, out: str | Path, calibration: Calibration, *,
             calibration_path: Path | None = None, settings: ProcessSettings | None = None,
             truth_poses: bool = False, progress: ProgressFn | None = None,
             keyframes_folder: Path | None = None) -> SurveyJob:
    """The processing job of one survey folder (its serials mapped with the calibration's); ``out`` is the
    survey's own output folder. The survey's notes (no manip_envelope.json, a partial survey ...) are in
    ``job.survey.notes``."""
    survey = open_survey(survey_path, serial_to_arm={arm.serial: name for name, arm in calibration.arms.items()},
                         mapping_source=calibration_path)
    return SurveyJob(survey=survey, out=Path(out), calibration=calibration, calibration_path=calibration_path,
                     settings=settings or ProcessSettings(), truth_poses=truth_poses, progress=progress,
                     keyframes_folder=keyframes_folder)


__all__ = [
    "FIGURES_DIR",
    "FUSED_FILE",
    "KEYFRAMES_DIR",
    "MESH_FILE",
    "POSES_DIR",
    "TIME_ALIGN",
    "ProgressFn",
    "SurveyJob",
    "open_job",
    "survey_calibration",
    "with_truth_poses",
]
