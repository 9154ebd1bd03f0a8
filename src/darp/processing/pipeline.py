"""The processing driver: a survey goes through a few named stages, each saving what it made.

    poses -> keyframes -> fusion -> mesh -> evaluation

=========== =========================================================== ==================================
stage       what it does                                                 writes (under ``<out>/<survey>/``)
=========== =========================================================== ==================================
poses       eq. 1 at every depth frame of both cameras (or the twin's    ``poses/`` (TUM, npz, summary.json)
            true poses with ``truth_poses``)
keyframes   settled, view-diverse keyframes per arm, held-out split,     ``keyframes/`` (npz + keyframes.json)
            exported with aligned RGB, IR and the support mask
fusion      voxel-support fusion of the ``fuse`` keyframes, per arm      ``arm110.ply``, ``arm111.ply``,
            and both arms                                                ``fused.ply``
mesh        multi-scale ball pivoting of the fused cloud                 ``mesh.ply``
evaluation  held-out, cross-arm, truth metrics, figures                  ``results.json``, ``figures/``
=========== =========================================================== ==================================

The evaluation stage lives in :mod:`darp.processing.results` (layers: evaluation uses reconstruction,
never the reverse); callers pass the full list, ``darp.processing.results.PROCESS_STAGES``.

**Resume.** After each stage ``stages.json`` records the stage's fingerprint (a hash chaining the
previous stage's fingerprint, the survey's files, the calibration and the settings that stage uses)
and its summary. With ``resume`` a stage whose fingerprint matches and whose outputs exist is skipped;
once a stage runs, every later stage runs too. **Memory** stays flat in survey length: poses need
only the frame index, keyframes are decoded one time window at a time, and fusion and evaluation
stream keyframes from disk.

**Nothing unfinished looks finished.** ``UNFINISHED.txt`` is written into the survey's output folder
before the first stage runs and removed only when the last stage has completed; it says which stage
was running or failed and why, so an interrupted or failed run (SIGKILL included) leaves a folder that
every reader (``darp report``, ``--resume``, the batch summary) treats as unfinished. A stage writes
its files under temporary names (``*.partial``) and renames them when all are written; a stage that
fails removes what it wrote. A failure is raised as :class:`StageFailure`: one line naming the survey,
the stage and the reason.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import DarpError, FormatError, ReconstructionError
from darp.formats.atomic import UNFINISHED_FILE, write_json_atomic, write_text_atomic
from darp.formats.calibration import Calibration, calibration_to_dict
from darp.formats.envelope import Envelope
from darp.formats.realsense.recording import Recording
from darp.formats.realsense.types import IMAGE_STREAMS
from darp.formats.survey import Survey
from darp.processing.settings import ProcessSettings
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.envelope_estimate import envelope_record, estimate_survey_envelope
from darp.reconstruction.fusion import VoxelFusion, calibration_uncertainty_m, write_voxel_cloud
from darp.reconstruction.keyframe_io import (
    FOR_FUSION,
    KeyframeIndex,
    export_arm_keyframes,
    iter_keyframes,
    read_keyframe_index,
    write_keyframe_index,
)
from darp.reconstruction.keyframes import FUSE, select_survey_keyframes
from darp.reconstruction.mesh import ball_pivoting_mesh, ball_pivoting_radii, mesh_area, write_mesh
from darp.reconstruction.poses import SurveyPoses, recover_survey_poses, write_survey_poses
from darp.reconstruction.time_align import TimeAlignSettings

STAGES_FILE = "stages.json"
TIME_ALIGN = TimeAlignSettings()
PARTIAL_SUFFIX = ".partial"
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


@dataclass(frozen=True)
class Stage:
    """A named step: ``run(job) -> summary``; ``outputs`` (relative paths) must exist once it is done."""

    name: str
    run: Callable[[SurveyJob], dict[str, Any]]
    outputs: tuple[str, ...]
    settings_groups: tuple[str, ...] = ()


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


# -- the reconstruction stages ---------------------------------------------------------------------------
def stage_poses(job: SurveyJob) -> dict[str, Any]:
    """Camera poses of every depth frame; writes ``poses/``."""
    job.report("poses", 0, 1)
    poses = job.poses()
    write_survey_poses(poses, job.out / POSES_DIR)
    job.report("poses", 1, 1)
    summary = poses.summary()
    summary["pose_source"] = "truth" if job.truth_poses else "calibration"
    return summary


def stage_keyframes(job: SurveyJob) -> dict[str, Any]:
    """Select and export keyframes of both arms; writes ``keyframes/``."""
    poses = job.poses()
    envelope = job.envelope()  # the survey's, or estimated from the survey when it has no geometry
    centre = np.asarray(envelope.center_m)
    crop = job.crop()
    folder = job.keyframes_dir
    _clear_keyframes(folder, poses.trajectories)
    selections = {
        arm: select_survey_keyframes({arm: traj}, centre, job.settings.keyframes,
                                     {arm: job.recording(arm).stream("depth").intrinsics})[arm]
        for arm, traj in poses.trajectories.items()}
    total = sum(len(s) for s in selections.values())
    done = 0

    def tick(step: int) -> None:
        nonlocal done
        done += step
        job.report("keyframes", done, total)

    entries = []
    depth_corr, depth_record = job.depth_corrections()
    for arm, selection in selections.items():
        entries += export_arm_keyframes(job.recording(arm), selection, poses.trajectories[arm], folder,
                                        crop=crop, progress=tick, depth_correction=depth_corr.get(arm))
    arms = {arm: {"serial": poses.trajectories[arm].serial, **sel.counts,
                  "still_threshold_rad_s": round(sel.still_threshold_rad_s, 6),
                  "speed_noise_rad_s": round(sel.speed_noise_rad_s, 6)} for arm, sel in selections.items()}
    if not entries:
        raise no_keyframe_error(job, selections)
    refine_record = None
    if job.settings.corrections.refine:  # issue 16 item 4; nothing at all happens in paper mode
        entries, refine_record = refine_keyframes(job, folder, entries, crop)
    index = KeyframeIndex(folder=folder, survey=job.survey.name,
                          object_name=envelope.object_name,
                          pose_source="truth" if job.truth_poses else "calibration",
                          settings=job.settings.to_dict()["keyframes"], arms=arms, keyframes=entries,
                          extra={"calibration_epoch": job.calibration.epoch,
                                 "support_mask": {"source": job.envelope_record()["source"],
                                                  "center_m": list(crop.center_m), "radius_m": crop.radius_m,
                                                  "height_m": crop.height_m, "table_z_m": crop.table_z_m,
                                                  "margin_m": crop.margin_m, "table_margin_m": crop.table_margin_m,
                                                  "calibration_uncertainty_m": job.calibration_uncertainty()},
                                 **({"depth_correction": depth_record} if depth_record else {})})
    if refine_record is not None:  # the poses in this folder are refined: say so, and how
        index.extra["refinement"] = refine_record
    write_keyframe_index(index)
    n_held = sum(1 for e in entries if e.split != FUSE)
    summary = {"arms": arms, "keyframes": len(entries), "fuse": len(entries) - n_held, "heldout": n_held,
               "envelope": job.envelope_record()}
    if depth_record:
        summary["depth_correction"] = depth_record
    if refine_record is not None:
        summary["refine"] = refine_record
    return summary


def refine_keyframes(job: SurveyJob, folder: Path, entries: list[Any],
                     crop: EnvelopeCrop) -> tuple[list[Any], dict[str, Any]]:
    """Survey-level refinement (:mod:`darp.reconstruction.refine`) of the exported keyframes: their
    ``.npz`` files are rewritten with the corrected poses; returns the new entries and the record.
    Only ``fuse`` keyframes are read to compute corrections; held-out ones get their arm's correction
    (and with ``refinement.heldout: register`` are then each aligned alone to the refined fuse keyframes)."""
    import dataclasses as dc

    from darp.reconstruction.keyframe_io import read_keyframe, write_keyframe
    from darp.reconstruction.refine import RefineView, refine_poses

    views = [RefineView(e.file, e.arm, e.frame_number, e.split, e.T_world_cam) for e in entries]
    register = job.settings.refinement.heldout == "register"  # held-out frames are read only then
    read: dict[str, Any] = {}  # each keyframe file is read once: for the refinement, then to rewrite its pose

    def frame(e: Any) -> Any:
        if e.split != FUSE and not register:
            return None
        read[e.file] = read_keyframe(folder / e.file)
        return read[e.file].posed_depth(colour=False)

    job.report("refine", 0, None)
    result = refine_poses(views, (frame(e) for e in entries), crop, job.calibration_uncertainty(),
                          job.settings.refinement, job.settings.fusion_used.depth)
    new_entries = []
    for entry in entries:
        T = result.poses[entry.file]
        if not np.array_equal(T, entry.T_world_cam):
            keyframe = read.pop(entry.file, None) or read_keyframe(folder / entry.file)
            write_keyframe(folder / entry.file, dc.replace(keyframe, T_world_cam=T))
        new_entries.append(dc.replace(entry, T_world_cam=T))
    job.report("refine", 1, 1)
    return new_entries, result.record


def no_keyframe_error(job: SurveyJob, selections: dict[str, Any]) -> ReconstructionError:
    """Why no keyframe was selected, blaming the input that explains it (joint log, envelope, ...)."""
    survey = job.survey
    log_file = survey.arm_poses_path or survey.path
    env_file = survey.envelope_path or survey.path
    parts = []
    blame: Path = survey.path
    for arm, sel in selections.items():
        c = sel.counts
        traj = job.poses().trajectories[arm]
        if c.get("posed", 0) == 0:
            span = traj.camera_span_s
            cam = "no frames" if span is None else f"camera frames {span[0]:.3f} .. {span[1]:.3f} s"
            parts.append(f"{arm}: none of {c.get('frames', 0)} frames lies inside the joint log (log "
                         f"{traj.log_span_s[0]:.3f} .. {traj.log_span_s[1]:.3f} s, {cam}; time_s must be host-clock "
                         "seconds, increasing)")
            blame = log_file
        elif outside_range(traj.poses.q_rad[traj.poses.posed]) > 0.5:
            q = traj.poses.q_rad[traj.poses.posed]
            parts.append(f"{arm}: the joint log's values (up to {float(np.nanmax(np.abs(q))):.3g} rad) are outside "
                         "the Z1's joint range in most frames (radians expected)")
            blame = log_file
        elif c.get("settled", 0) == 0:
            parts.append(f"{arm}: of {c['posed']} posed frames none is settled (stillness threshold "
                         f"{sel.still_threshold_rad_s:.3f} rad/s, measured joint-speed noise "
                         f"{sel.speed_noise_rad_s:.3f} rad/s)")
            blame = log_file
        elif c.get("in_view", 0) == 0:
            centre = job.envelope().center_m
            where = "unknown" if centre is None else "(" + ", ".join(f"{1000 * v:.0f}" for v in centre) + ") mm"
            parts.append(f"{arm}: {c['settled']} settled frames but none sees the envelope centre {where}")
            if blame == survey.path:
                blame = env_file if job.envelope_record().get("source") != "estimated" else survey.path
        else:
            parts.append(f"{arm}: {c.get('in_view', 0)} frames in view gave no keyframe")
    detail = "; ".join(parts) or "the survey has no arm"
    return ReconstructionError(f"no keyframe selected: {detail}", blame)


def outside_range(q_rad: np.ndarray, tol_rad: float = 0.2) -> float:
    """Share of the rows of ``q_rad`` (N, 6) outside the Z1's joint limits (by more than ``tol_rad``)."""
    from darp.kinematics.z1 import within_limits

    q = np.asarray(q_rad, np.float64).reshape(-1, 6)
    if q.size == 0:
        return 0.0
    inside = np.asarray(within_limits(np.nan_to_num(q, nan=0.0, posinf=1e9, neginf=-1e9), tol_rad=tol_rad))
    return float(1.0 - inside.mean())


def _clear_keyframes(folder: Path, arms: Any) -> None:
    """Remove what an earlier export wrote (never anything else: the folder may be the user's)."""
    from darp.reconstruction.keyframe_io import INDEX_FILE, OBSERVATIONS_DIR

    for name in [*arms, OBSERVATIONS_DIR]:
        sub = folder / name
        if sub.is_dir():
            for npz in sub.glob("*.npz"):
                npz.unlink()
            if not any(sub.iterdir()):
                sub.rmdir()
    (folder / INDEX_FILE).unlink(missing_ok=True)
    folder.mkdir(parents=True, exist_ok=True)


def low_floor_hint(crop: EnvelopeCrop) -> str:
    """When the crop's floor (its table margin, which grows with the calibration's stated error) cuts at least
    half of the object's height, the reason an empty fusion gives (one clause, '' otherwise)."""
    if crop.table_margin_m < 0.5 * crop.height_m:
        return ""
    return (f"; the crop keeps only points {crop.table_margin_m * 1000:.0f} mm above the table (it grows with the "
            f"calibration's held-out error), {100 * crop.table_margin_m / crop.height_m:.0f} % of the object's "
            f"{crop.height_m * 1000:.0f} mm height: a better calibration, or --corrections table, is needed for "
            "an object this low")


def stage_fusion(job: SurveyJob) -> dict[str, Any]:
    """Fuse the ``fuse`` keyframes (streamed from disk); writes the per-arm and fused clouds."""
    index = read_keyframe_index(job.keyframes_dir)
    total = len(index.select(FUSE))
    fusion = VoxelFusion(job.settings.fusion_used, job.crop())
    table_records: list[dict[str, Any]] = []
    for k, keyframe in enumerate(iter_keyframes(job.keyframes_dir, FUSE, skip=FOR_FUSION)):
        frame = keyframe.posed_depth()
        if job.settings.corrections.table:  # issue 16: each keyframe above its own fitted table plane
            region, record = job.table_region(frame)
            table_records.append(record)
            fusion.add(frame, region)
        else:
            fusion.add(frame)
        job.report("fusion", k + 1, total + 1)
    try:
        result = fusion.result()
    except ReconstructionError as err:
        raise ReconstructionError(err.message + low_floor_hint(job.crop()), err.path) from None
    if len(result.fused) == 0:
        points_in = result.stats.get("fused", {}).get("points_in", 0)
        raise ReconstructionError(
            f"fusion kept no point: {total} fuse keyframes left {points_in} points inside the envelope and no voxel "
            f"had the support asked (min_frames {job.settings.fusion_used.min_frames}, min_view_bins "
            f"{job.settings.fusion_used.min_view_bins})" + low_floor_hint(job.crop()), job.keyframes_dir)
    clouds = {**{f"{arm}.ply": cloud for arm, cloud in result.per_arm.items()}, FUSED_FILE: result.fused}
    with staged_outputs(job.out, list(clouds)) as paths:
        for name, cloud in clouds.items():
            write_voxel_cloud(paths[name], cloud)
    job.report("fusion", total + 1, total + 1)
    out: dict[str, Any] = {"points": {**{arm: len(c) for arm, c in result.per_arm.items()},
                                      "fused": len(result.fused)}, "stats": result.stats}
    if job.settings.corrections.table:
        from darp.reconstruction.table_plane import summarise

        out["table"] = summarise(table_records)
    return out


def stage_mesh(job: SurveyJob) -> dict[str, Any]:
    """Multi-scale ball pivoting of ``fused.ply``; writes ``mesh.ply``."""
    from darp.reconstruction.cloud_io import read_ply

    job.report("mesh", 0, None)
    cloud = read_ply(job.out / FUSED_FILE)
    if cloud.normals is None:
        raise FormatError("the fused cloud has no normals", job.out / FUSED_FILE)
    normals = cloud.normals / np.linalg.norm(cloud.normals, axis=1, keepdims=True)
    mesh = ball_pivoting_mesh(cloud.points, normals, cloud.colours, job.settings.mesh_used)
    if len(mesh.triangles) == 0:
        raise ReconstructionError(f"ball pivoting made no triangle from the fused cloud's {len(cloud.points)} points "
                                  "(too few or too sparse: more views per arm are needed)", job.out / FUSED_FILE)
    with staged_outputs(job.out, [MESH_FILE]) as paths:
        write_mesh(paths[MESH_FILE], mesh)
    job.report("mesh", 1, 1)
    return {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "area_m2": mesh_area(mesh),
            "radii_m": ball_pivoting_radii(cloud.points, job.settings.mesh_used)}


@contextlib.contextmanager
def staged_outputs(folder: Path, names: Sequence[str]) -> Any:
    """Write a stage's files under temporary names (``<name>.partial``), renamed to their final names
    only when every one is written; on an error the temporary files go and no final name is touched."""
    temporary = {name: folder / (name + PARTIAL_SUFFIX) for name in names}
    try:
        yield temporary
    except BaseException:
        for path in temporary.values():
            path.unlink(missing_ok=True)
        raise
    for name, path in temporary.items():
        path.replace(folder / name)


RECONSTRUCTION_STAGES: tuple[Stage, ...] = (
    Stage("poses", stage_poses, (f"{POSES_DIR}/summary.json",), ("corrections",)),
    Stage("keyframes", stage_keyframes, (f"{KEYFRAMES_DIR}/keyframes.json",),
          ("keyframes", "fusion", "corrections", "refinement")),
    Stage("fusion", stage_fusion, (FUSED_FILE,), ("fusion",)),
    Stage("mesh", stage_mesh, (MESH_FILE,), ("mesh",)),
)


def _fail(job: SurveyJob, stages: Sequence[Stage], stage: Stage, stages_state: dict[str, Any], reason: str,
          path: Path | None) -> None:
    """Record the failure (stages.json, UNFINISHED.txt), remove the failed stage's outputs, raise StageFailure."""
    for later in stages[stages.index(stage):]:
        stages_state.pop(later.name, None)
        for output in later.outputs:
            target = job.out / output
            if target.is_file():
                target.unlink()
    if stage.name == "fusion":
        for arm in job.arms:
            (job.out / f"{arm}.ply").unlink(missing_ok=True)
    line = f"failed: {stage.name}: {reason}"
    write_json_atomic(job.out / STAGES_FILE, {"survey": job.survey.name, "stages": stages_state,
                                              "failed": {"stage": stage.name, "reason": reason}})
    _mark_unfinished(job.out, line)
    raise StageFailure(job.survey.name, stage.name, reason, path)


# -- the driver ---------------------------------------------------------------------------------------------
def _survey_identity(job: SurveyJob) -> dict[str, Any]:
    s = job.survey
    files = [*s.recording_paths.values(), s.arm_poses_path, s.envelope_path]
    return {"survey": s.name, "files": sorted((f.name, f.stat().st_size, f.stat().st_mtime_ns)
                                              for f in files if f is not None),
            "calibration": calibration_to_dict(job.calibration), "truth_poses": job.truth_poses}


def stage_fingerprints(job: SurveyJob, stages: Sequence[Stage]) -> dict[str, str]:
    """Each stage's fingerprint: a hash of the previous one, its name and the settings it uses."""
    previous = hashlib.sha256(json.dumps(_survey_identity(job), sort_keys=True, default=str).encode()).hexdigest()
    out = {}
    for stage in stages:
        groups = job.settings.fingerprint(*stage.settings_groups) if stage.settings_groups else ""
        previous = hashlib.sha256(f"{previous}|{stage.name}|{groups}".encode()).hexdigest()[:16]
        out[stage.name] = previous
    return out


def read_stage_state(out: Path) -> dict[str, Any]:
    """``stages.json`` of a survey output folder ({} when absent or unreadable: then nothing is skipped)."""
    try:
        state = json.loads((out / STAGES_FILE).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return state if isinstance(state, dict) else {}


class StageFailure(ReconstructionError):
    """A survey failed in one stage: ``survey``, ``stage`` and ``reason`` (the original one-line error)."""

    def __init__(self, survey: str, stage: str, reason: str, path: str | Path | None = None) -> None:
        self.survey, self.stage, self.reason = survey, stage, reason
        super().__init__(f"survey {survey}: {stage} failed: {reason}")
        self.file = Path(path) if path is not None else None


def unfinished_reason(out: str | Path) -> str | None:
    """The first line of ``UNFINISHED.txt`` in a survey output folder, or None when the run completed."""
    marker = Path(out) / UNFINISHED_FILE
    if not marker.is_file():
        return None
    try:
        text = marker.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return "unfinished (UNFINISHED.txt unreadable)"
    return text.splitlines()[0] if text else "unfinished"


def _mark_unfinished(out: Path, line: str) -> None:
    write_text_atomic(out / UNFINISHED_FILE, f"{line}\nThis folder's processing did not complete: its outputs "
                      "are not results. Run darp process again (--resume keeps the completed stages).\n")


def process_survey(job: SurveyJob, stages: Sequence[Stage] = RECONSTRUCTION_STAGES, *,
                   resume: bool = False) -> dict[str, Any]:
    """Run ``stages`` in order on one survey; returns ``{stage: {"skipped", "seconds", "summary"}}``.

    ``UNFINISHED.txt`` marks the output folder until the last stage completes. A stage that fails
    raises :class:`StageFailure` (survey, stage, reason on one line), leaves ``stages.json`` and the
    marker saying so, and removes the failed stage's outputs.
    """
    job.out.mkdir(parents=True, exist_ok=True)
    fingerprints = stage_fingerprints(job, stages)
    state = read_stage_state(job.out) if resume else {}
    stages_state: dict[str, Any] = dict(state.get("stages", {}))
    report: dict[str, Any] = {}
    _mark_unfinished(job.out, f"running: {', '.join(s.name for s in stages)}")
    try:
        _run_stages(job, stages, resume, fingerprints, stages_state, report)
    finally:
        job.close()
    (job.out / UNFINISHED_FILE).unlink(missing_ok=True)
    return report


def _run_stages(job: SurveyJob, stages: Sequence[Stage], resume: bool, fingerprints: dict[str, str],
                stages_state: dict[str, Any], report: dict[str, Any]) -> None:
    rerun = False
    for stage in stages:
        before = stages_state.get(stage.name, {})
        complete = all((job.out / o).exists() for o in stage.outputs)
        if resume and not rerun and before.get("fingerprint") == fingerprints[stage.name] and complete:
            report[stage.name] = {"skipped": True, "seconds": before.get("seconds"), "summary": before.get("summary")}
            job.report(stage.name, 1, 1)
            continue
        rerun = True
        start = time.perf_counter()
        _mark_unfinished(job.out, f"running: {stage.name}")
        try:
            summary = stage.run(job)
        except DarpError as err:
            _fail(job, stages, stage, stages_state, str(err), err.path)
        except (ValueError, RuntimeError, ArithmeticError, IndexError, KeyError, MemoryError) as err:
            # a library failing inside a stage (Open3D, numpy, ...): still this survey's, named and contained
            _fail(job, stages, stage, stages_state, f"{type(err).__name__}: {err}".splitlines()[0], None)
        seconds = round(time.perf_counter() - start, 3)
        stages_state[stage.name] = {"fingerprint": fingerprints[stage.name], "seconds": seconds, "summary": summary}
        for later in stages[stages.index(stage) + 1:]:
            stages_state.pop(later.name, None)  # stale once this stage changed
        write_json_atomic(job.out / STAGES_FILE, {"survey": job.survey.name, "stages": stages_state})
        report[stage.name] = {"skipped": False, "seconds": seconds, "summary": summary}


__all__ = [
    "FIGURES_DIR",
    "FUSED_FILE",
    "KEYFRAMES_DIR",
    "MESH_FILE",
    "POSES_DIR",
    "RECONSTRUCTION_STAGES",
    "STAGES_FILE",
    "UNFINISHED_FILE",
    "ProgressFn",
    "Stage",
    "StageFailure",
    "SurveyJob",
    "process_survey",
    "read_stage_state",
    "stage_fingerprints",
    "stage_fusion",
    "stage_keyframes",
    "stage_mesh",
    "stage_poses",
    "staged_outputs",
    "unfinished_reason",
    "with_truth_poses",
]
