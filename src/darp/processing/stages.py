"""The stages of ``darp process``: each turns the job's inputs or an earlier stage's files into its own.

    poses -> keyframes -> fusion -> mesh -> evaluation

=========== =========================================================== ==================================
stage       what it does                                                 writes (under ``<out>/<survey>/``)
=========== =========================================================== ==================================
poses       eq. 1 at every depth frame of both cameras (or the twin's    ``poses/`` (TUM, npz, summary.json)
            true poses with ``truth_poses``)
keyframes   settled, view-diverse keyframes per arm, held-out split,     ``keyframes/`` (npz + keyframes.json)
            exported with aligned RGB, IR and the support mask
fusion      voxel-support fusion of the ``fuse`` keyframes, per arm      ``<arm>.ply`` per arm, ``fused.ply``
            and both arms
mesh        multi-scale ball pivoting of the fused cloud                 ``mesh.ply``
evaluation  held-out, cross-arm, truth metrics, figures                  ``results.json``, ``evaluation/``,
            (:mod:`darp.processing.evaluate`)                            ``figures/``
=========== =========================================================== ==================================

Each :class:`~darp.processing.runner.Stage` declares the files that say it is done (``summary.json`` and
``keyframes.json`` are written last in their folders; the clouds are renamed together; ``results.json``
is written last); :func:`darp.processing.runner.process_survey` runs :data:`PROCESS_STAGES`. **Memory**
stays flat in survey length: poses need only the frame index, keyframes are decoded one time window at a
time, and fusion and evaluation stream keyframes from disk.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError, ReconstructionError
from darp.formats.atomic import write_json_atomic
from darp.formats.schema import to_jsonable
from darp.processing.diagnostics import low_floor_hint, no_keyframe_error
from darp.processing.evaluate import EVALUATION_DIR, HELDOUT_DISTANCES, TRUTH_DISTANCES, evaluate_processed_survey
from darp.processing.job import FUSED_FILE, KEYFRAMES_DIR, MESH_FILE, POSES_DIR, SurveyJob
from darp.processing.results import RESULTS_FILE, survey_results
from darp.processing.runner import Stage, staged_outputs
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.fusion import VoxelFusion, write_voxel_cloud
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
from darp.reconstruction.poses import write_survey_poses


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
                                     {arm: job.recording(arm).stream("depth").intrinsics},
                                     envelope.park_q_rad)[arm]
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



def fusion_outputs(job: SurveyJob) -> tuple[str, ...]:
    """The fusion stage's clouds: one per arm of the survey and the fused one."""
    return (*(f"{arm}.ply" for arm in job.arms), FUSED_FILE)


def stage_evaluation(job: SurveyJob) -> dict[str, Any]:
    """Evaluate and write ``results.json`` (the last stage of :data:`PROCESS_STAGES`)."""
    evaluation = evaluate_processed_survey(job)
    results = survey_results(job, evaluation)
    write_json_atomic(job.out / RESULTS_FILE, to_jsonable(results))
    heldout = evaluation["heldout"]["aggregate"]
    return {"heldout_median_mm": heldout.get("median_mm"), "heldout_points": heldout.get("count"),
            "truth": evaluation["truth"] is not None}


def evaluation_outputs(job: SurveyJob) -> tuple[str, ...]:
    """The evaluation stage's raw distances (truth distances on a twin survey with its true mesh) and
    ``results.json``; figures depend on the data and are not required."""
    truth = job.survey.truth_path
    has_truth = truth is not None and (truth / "object.ply").is_file()
    return (f"{EVALUATION_DIR}/{HELDOUT_DISTANCES}", *((f"{EVALUATION_DIR}/{TRUTH_DISTANCES}",) if has_truth else ()),
            RESULTS_FILE)


RECONSTRUCTION_STAGES: tuple[Stage[SurveyJob], ...] = (
    Stage("poses", stage_poses, (f"{POSES_DIR}/summary.json",), ("corrections",)),
    Stage("keyframes", stage_keyframes, (f"{KEYFRAMES_DIR}/keyframes.json",),
          ("keyframes", "fusion", "corrections", "refinement")),
    Stage("fusion", stage_fusion, fusion_outputs, ("fusion",)),
    Stage("mesh", stage_mesh, (MESH_FILE,), ("mesh",)),
)
"""poses -> keyframes -> fusion -> mesh: the reconstruction without its evaluation."""

PROCESS_STAGES: tuple[Stage[SurveyJob], ...] = (
    *RECONSTRUCTION_STAGES,
    Stage("evaluation", stage_evaluation, evaluation_outputs, ("evaluation",)),
)
"""poses -> keyframes -> fusion -> mesh -> evaluation: what ``darp process`` runs."""


__all__ = [
    "PROCESS_STAGES",
    "RECONSTRUCTION_STAGES",
    "evaluation_outputs",
    "fusion_outputs",
    "refine_keyframes",
    "stage_evaluation",
    "stage_fusion",
    "stage_keyframes",
    "stage_mesh",
    "stage_poses",
]
