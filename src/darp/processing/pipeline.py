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

from darp.errors import FormatError, ReconstructionError
from darp.formats.atomic import write_json_atomic
from darp.formats.calibration import Calibration, calibration_to_dict
from darp.formats.envelope import Envelope
from darp.formats.realsense.recording import Recording
from darp.formats.realsense.types import IMAGE_STREAMS
from darp.formats.survey import Survey
from darp.processing.settings import ProcessSettings
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.envelope_estimate import envelope_record, estimate_survey_envelope
from darp.reconstruction.fusion import VoxelFusion, write_voxel_cloud
from darp.reconstruction.keyframe_io import (
    KeyframeIndex,
    export_arm_keyframes,
    iter_keyframes,
    read_keyframe_index,
    write_keyframe_index,
)
from darp.reconstruction.keyframes import FUSE, select_survey_keyframes
from darp.reconstruction.mesh import ball_pivoting_mesh, ball_pivoting_radii, mesh_area, write_mesh
from darp.reconstruction.poses import SurveyPoses, recover_survey_poses, write_survey_poses

STAGES_FILE = "stages.json"
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
        """The object-support region: the envelope cylinder with fusion's margins."""
        return self.settings.fusion.crop(self.envelope())

    def envelope(self) -> Envelope:
        """The survey's envelope; without centre/radius/height, one estimated from the survey's own
        poses and depth (:mod:`darp.reconstruction.envelope_estimate`), once per run."""
        if self._envelope is None:
            envelope = self.survey.envelope()
            if envelope is None or not envelope.has_geometry:
                estimate = estimate_survey_envelope(
                    self.poses(), self.recording, [self.calibration.arms[a].T_world_base[:2, 3] for a in self.arms],
                    keyframe_settings=self.settings.keyframes, depth_settings=self.settings.fusion.depth,
                    path=self.survey.path)
                self._envelope_record = estimate.to_dict()
                envelope = estimate.envelope(envelope)
            else:
                self._envelope_record = envelope_record(envelope)
            self._envelope = envelope
        return self._envelope

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
            poses = recover_survey_poses(  # with this run's open recordings
                self.survey, self.calibration, calibration_path=self.calibration_path,
                open_recording=lambda arm: contextlib.nullcontext(self.recording(arm)))
            if self.truth_poses:
                poses = with_truth_poses(poses, self.survey)
            self._poses = poses
        return self._poses


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
    for arm, selection in selections.items():
        entries += export_arm_keyframes(job.recording(arm), selection, poses.trajectories[arm], folder,
                                        crop=crop, progress=tick)
    arms = {arm: {"serial": poses.trajectories[arm].serial, **sel.counts} for arm, sel in selections.items()}
    if not entries:
        raise ReconstructionError("no keyframe selected: no settled frame sees the object "
                                  "(check the envelope, the calibration and the keyframe settings)", job.survey.path)
    index = KeyframeIndex(folder=folder, survey=job.survey.name,
                          object_name=envelope.object_name,
                          pose_source="truth" if job.truth_poses else "calibration",
                          settings=job.settings.keyframes.to_dict(), arms=arms, keyframes=entries,
                          extra={"calibration_epoch": job.calibration.epoch,
                                 "support_mask": {"source": job.envelope_record()["source"],
                                                  "center_m": list(crop.center_m), "radius_m": crop.radius_m,
                                                  "height_m": crop.height_m, "table_z_m": crop.table_z_m,
                                                  "margin_m": crop.margin_m, "table_margin_m": crop.table_margin_m}})
    write_keyframe_index(index)
    n_held = sum(1 for e in entries if e.split != FUSE)
    return {"arms": arms, "keyframes": len(entries), "fuse": len(entries) - n_held, "heldout": n_held,
            "envelope": job.envelope_record()}


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


def stage_fusion(job: SurveyJob) -> dict[str, Any]:
    """Fuse the ``fuse`` keyframes (streamed from disk); writes the per-arm and fused clouds."""
    index = read_keyframe_index(job.keyframes_dir)
    total = len(index.select(FUSE))
    fusion = VoxelFusion(job.settings.fusion, job.crop())
    for k, keyframe in enumerate(iter_keyframes(job.keyframes_dir, FUSE)):
        fusion.add(keyframe.posed_depth())
        job.report("fusion", k + 1, total + 1)
    result = fusion.result()
    for arm, cloud in result.per_arm.items():
        write_voxel_cloud(job.out / f"{arm}.ply", cloud)
    write_voxel_cloud(job.out / FUSED_FILE, result.fused)
    job.report("fusion", total + 1, total + 1)
    return {"points": {**{arm: len(c) for arm, c in result.per_arm.items()}, "fused": len(result.fused)},
            "stats": result.stats}


def stage_mesh(job: SurveyJob) -> dict[str, Any]:
    """Multi-scale ball pivoting of ``fused.ply``; writes ``mesh.ply``."""
    from darp.reconstruction.cloud_io import read_ply

    job.report("mesh", 0, None)
    cloud = read_ply(job.out / FUSED_FILE)
    if cloud.normals is None:
        raise FormatError("the fused cloud has no normals", job.out / FUSED_FILE)
    normals = cloud.normals / np.linalg.norm(cloud.normals, axis=1, keepdims=True)
    mesh = ball_pivoting_mesh(cloud.points, normals, cloud.colours, job.settings.mesh)
    write_mesh(job.out / MESH_FILE, mesh)
    job.report("mesh", 1, 1)
    return {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "area_m2": mesh_area(mesh),
            "radii_m": ball_pivoting_radii(cloud.points, job.settings.mesh)}


RECONSTRUCTION_STAGES: tuple[Stage, ...] = (
    Stage("poses", stage_poses, (f"{POSES_DIR}/summary.json",)),
    Stage("keyframes", stage_keyframes, (f"{KEYFRAMES_DIR}/keyframes.json",), ("keyframes", "fusion")),
    Stage("fusion", stage_fusion, (FUSED_FILE,), ("fusion",)),
    Stage("mesh", stage_mesh, (MESH_FILE,), ("mesh",)),
)


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


def process_survey(job: SurveyJob, stages: Sequence[Stage] = RECONSTRUCTION_STAGES, *,
                   resume: bool = False) -> dict[str, Any]:
    """Run ``stages`` in order on one survey; returns ``{stage: {"skipped", "seconds", "summary"}}``."""
    job.out.mkdir(parents=True, exist_ok=True)
    fingerprints = stage_fingerprints(job, stages)
    state = read_stage_state(job.out) if resume else {}
    stages_state: dict[str, Any] = dict(state.get("stages", {}))
    report: dict[str, Any] = {}
    try:
        _run_stages(job, stages, resume, fingerprints, stages_state, report)
    finally:
        job.close()
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
        summary = stage.run(job)
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
    "ProgressFn",
    "Stage",
    "SurveyJob",
    "process_survey",
    "read_stage_state",
    "stage_fingerprints",
    "stage_fusion",
    "stage_keyframes",
    "stage_mesh",
    "stage_poses",
    "with_truth_poses",
]
