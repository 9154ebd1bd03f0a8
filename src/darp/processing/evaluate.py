"""The evaluation stage's computations: held-out, cross-arm and truth metrics of one processed survey, and figures.

Inputs are the stage outputs in ``<out>/<survey>/`` (keyframes, clouds, mesh); the raw survey is read
only for the release-composition row and, for a twin survey, the ``truth/`` folder (true object mesh
and true camera poses). Raw distances are kept in ``evaluation/*.npz`` so that statistics can be
pooled over surveys (the paper pools 1,563,466 held-out points of ten objects).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp.evaluation.composition import survey_composition
from darp.evaluation.cross_arm import cross_arm_consistency
from darp.evaluation.heldout import evaluate_heldout
from darp.evaluation.point_to_mesh import MeshDistance, distance_stats
from darp.evaluation.truth_metrics import (
    SEEABLE_DEPTH_RANGE_M,
    SEEABLE_MAX_INCIDENCE_DEG,
    TRUTH_THRESHOLDS_M,
    missing_by_cause,
    sample_surface,
    seeable_from_poses,
    truth_metrics,
    visible_in_frames,
)
from darp.formats.atomic import atomic_path
from darp.formats.io_input import npz_input
from darp.processing.job import FIGURES_DIR, FUSED_FILE, MESH_FILE, SurveyJob
from darp.reconstruction.cloud_io import read_mesh_ply, read_ply
from darp.reconstruction.keyframe_io import DEPTH_ONLY, iter_keyframes, posed_frames, read_keyframe_index
from darp.reconstruction.keyframes import FUSE, HELDOUT

EVALUATION_DIR = "evaluation"
HELDOUT_DISTANCES = "heldout_distances.npz"
TRUTH_DISTANCES = "truth_distances.npz"
FIGURES = {"cross_arm": "cross_arm.png", "partial_fused": "partial_fused.png", "heldout": "heldout_histogram.png"}


def _save_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, allow_pickle=False, **arrays)  # numeric arrays; load_distances reads without pickle


def load_distances(path: str | Path) -> dict[str, np.ndarray]:
    """Arrays of an ``evaluation/*_distances.npz`` file ({} when absent)."""
    path = Path(path)
    if not path.is_file():
        return {}
    with npz_input(path, "a distances .npz") as data:
        return {name: data[name] for name in data.files}


def _cloud(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    ply = read_ply(path)
    return ply.points, ply.normals, ply.colours


def read_truth_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of the twin's ``truth/object.ply`` (it carries face colours, which
    :func:`darp.reconstruction.cloud_io.read_ply` does not read: trimesh does)."""
    import trimesh

    from darp.errors import FormatError

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except (OSError, ValueError) as err:
        raise FormatError(f"cannot read the true mesh: {err}", path) from err
    if not isinstance(mesh, trimesh.Trimesh):
        raise FormatError(f"the true mesh is not a triangle mesh (trimesh read a {type(mesh).__name__})", path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def keyframe_pose_pairs(job: SurveyJob) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per arm: the keyframes' poses and the twin's true poses of the same frames, (K, 4, 4) each."""
    from darp.formats.truth import read_camera_poses

    assert job.survey.truth_path is not None
    index = read_keyframe_index(job.keyframes_dir)
    out = {}
    for arm in sorted({k.arm for k in index.keyframes}):
        truth = read_camera_poses(job.survey.truth_path / f"camera_poses_{arm}.npz")
        lookup = {int(n): i for i, n in enumerate(truth["frame_number"])}
        pairs = [(k.T_world_cam, truth["T_world_cam"][lookup[k.frame_number]])
                 for k in index.select(arm=arm) if k.frame_number in lookup]
        if pairs:
            out[arm] = (np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]))
    return out


def pose_errors_vs_truth(pairs: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """Per arm: how far the keyframes' poses are from the true poses (translation mm, rotation deg)."""
    from darp.kinematics.transforms import pose_error

    out: dict[str, Any] = {}
    for arm, (estimated, true) in pairs.items():
        t_err, r_err = pose_error(estimated, true)
        t_mm, r_deg = np.asarray(t_err) * 1000.0, np.degrees(np.asarray(r_err))
        out[arm] = {"keyframes": len(t_mm), "translation_median_mm": round(float(np.median(t_mm)), 4),
                    "translation_max_mm": round(float(t_mm.max()), 4),
                    "rotation_median_deg": round(float(np.median(r_deg)), 5),
                    "rotation_max_deg": round(float(r_deg.max()), 5)}
    return out


def world_gauge(pairs: dict[str, tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The rigid ``T_truthworld_world`` that best maps the keyframes' camera centres (both arms) onto the
    true ones (Kabsch, least squares), or None with fewer than 3 keyframes.

    A calibration realises its own world frame (e.g. midway between the calibrated base origins); the
    twin keeps the nominal one. The two differ by a rigid 'gauge' that no held-out or cross-arm measure
    can see; accuracy after removing it isolates the reconstruction's own error.
    """
    if not pairs:
        return None
    a = np.concatenate([e[:, :3, 3] for e, _ in pairs.values()])
    b = np.concatenate([t[:, :3, 3] for _, t in pairs.values()])
    if len(a) < 3:
        return None
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cb - R @ ca
    return T


def _truth(job: SurveyJob, fused: np.ndarray,
           mesh: tuple[np.ndarray, np.ndarray]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    settings = job.settings.evaluation
    assert job.survey.truth_path is not None
    truth_v, truth_t = read_truth_mesh(job.survey.truth_path / "object.ply")
    rng = np.random.default_rng(settings.seed)
    samples, normals = sample_surface(truth_v, truth_t, rng, spacing_m=settings.truth_sample_spacing_m)
    total = len(read_keyframe_index(job.keyframes_dir).select(FUSE))

    def frames() -> Any:
        for k, frame in enumerate(posed_frames(iter_keyframes(job.keyframes_dir, FUSE, skip=DEPTH_ONLY), colour=False)):
            yield frame
            job.report("evaluation", k + 1, total)

    seen = visible_in_frames(samples, frames(), tolerance_m=settings.visibility_tolerance_m, normals=normals)
    metrics = truth_metrics(fused, truth_v, truth_t, samples, seen, mesh=mesh, rng=rng, thresholds_m=TRUTH_THRESHOLDS_M)
    truth_distance = MeshDistance(truth_v, truth_t)
    accuracy = truth_distance.distances(fused)
    seen_samples = samples[seen]
    from scipy.spatial import cKDTree

    completeness = cKDTree(fused).query(seen_samples, k=1)[0].astype(np.float32) if seen_samples.size else np.empty(0)
    pairs = keyframe_pose_pairs(job)
    summary = {**metrics.to_dict(), "pose_error": pose_errors_vs_truth(pairs)}
    seeable = seeable_completeness(job, fused, samples, normals, truth_v, truth_t, seen)
    if seeable is not None:
        summary["seeable"] = seeable
    gauge = world_gauge(pairs)
    if gauge is not None:
        aligned = fused @ gauge[:3, :3].T + gauge[:3, 3]
        angle = np.degrees(np.arccos(np.clip((np.trace(gauge[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        summary["world_gauge"] = {
            "translation_mm": round(float(np.linalg.norm(gauge[:3, 3] + gauge[:3, :3] @ fused.mean(axis=0)
                                                          - fused.mean(axis=0)) * 1000.0), 4),
            "rotation_deg": round(float(angle), 5),
            "T_truthworld_world": gauge.tolist(),
            "accuracy_aligned": distance_stats(truth_distance.distances(aligned), TRUTH_THRESHOLDS_M).to_dict()}
    return summary, {"accuracy": accuracy, "completeness": completeness}


def seeable_completeness(job: SurveyJob, fused: np.ndarray, samples: np.ndarray, normals: np.ndarray,
                         truth_v: np.ndarray, truth_t: np.ndarray, seen: np.ndarray) -> dict[str, Any] | None:
    """Completeness against the surface any feasible camera pose can see: the true samples that some feasible
    candidate pose of the survey's planner (``manip_envelope.json`` ``coverage.feasible_poses``) sees
    (:func:`~darp.evaluation.truth_metrics.seeable_from_poses`, with the keyframes' depth image size), and the
    share of them within each threshold of the fused cloud; also ``co_seeable_pct``, the share of that surface
    which feasible poses of both arms see within the same rules (what a plan can give both arms to compare at
    good incidence: a thin plate whose faces point at the arms has none). None when the survey recorded no
    feasible poses."""
    from scipy.spatial import cKDTree

    env = job.survey.envelope()
    record = (env.extra.get("coverage") or {}) if env is not None else {}
    by_arm = record.get("feasible_poses") if isinstance(record, dict) else None
    if not isinstance(by_arm, dict) or not by_arm:
        return None
    poses_by_arm = [[np.asarray(p, np.float64).reshape(3, 4) for p in arm_poses] for arm_poses in by_arm.values()]
    n_poses = sum(len(arm_poses) for arm_poses in poses_by_arm)
    first = next(iter_keyframes(job.keyframes_dir, FUSE, skip=DEPTH_ONLY), None)
    if first is None or not n_poses:
        return None
    intr = first.posed_depth().intrinsics
    per_arm = [seeable_from_poses(samples, normals, truth_v, truth_t, arm_poses, width=intr.width, height=intr.height,
                                  fx=intr.fx, fy=intr.fy, ppx=intr.ppx, ppy=intr.ppy,
                                  table_z_m=float(np.min(truth_v[:, 2])))
               for arm_poses in poses_by_arm]
    mask = np.logical_or.reduce(per_arm)
    # what a plan can give the arms to compare at good incidence: the seeable surface feasible poses of every arm see
    co_seeable = np.logical_and.reduce(per_arm) if len(per_arm) > 1 else np.zeros_like(mask)
    distance = cKDTree(fused).query(samples[mask], k=1)[0] if mask.any() else np.empty(0)
    causes = None
    if job.settings.evaluation.missing_by_cause and mask.any():
        threshold = job.settings.evaluation.missing_threshold_m
        missing = np.zeros(len(samples), bool)
        missing[np.flatnonzero(mask)[distance > threshold]] = True
        causes = missing_causes(job, samples, normals, truth_v, truth_t, missing, threshold)
    return {"poses": n_poses, "samples": int(mask.sum()), "of_mesh_pct": round(100.0 * float(mask.mean()), 4),
            "co_seeable_pct": round(100.0 * float(co_seeable.sum()) / max(1, int(mask.sum())), 4),
            "seen_by_keyframes_pct": round(100.0 * float(np.mean(seen[mask])), 4) if mask.any() else None,
            "completeness_pct": {f"{t * 1000:g}mm": (round(100.0 * float(np.mean(distance <= t)), 4)
                                                     if distance.size else None) for t in TRUTH_THRESHOLDS_M},
            **({"missing_by_cause": causes} if causes is not None else {})}


def missing_causes(job: SurveyJob, samples: np.ndarray, normals: np.ndarray, truth_v: np.ndarray,
                   truth_t: np.ndarray, missing: np.ndarray, threshold_m: float) -> dict[str, Any]:
    """:func:`~darp.evaluation.truth_metrics.missing_by_cause` for a processed twin survey: the fuse keyframes
    are fused again (same settings and crops) keeping each step's points, each is back-projected without any
    crop (what the camera measured), and the samples are tested against the keyframes' own poses for being
    in view (unoccluded in the image, any incidence and depth) and in view well (the seeable rules)."""
    from scipy.spatial import cKDTree

    from darp.reconstruction.backproject import DepthFilterSettings, backproject
    from darp.reconstruction.fusion import VoxelFusion

    idx = np.flatnonzero(missing)
    targets = samples[idx]
    measured_local = np.zeros(idx.size, bool)
    raw_local = np.zeros(idx.size, bool)
    unfiltered = DepthFilterSettings(min_depth_m=0.0, max_depth_m=1e3, discontinuity_abs_m=1e3, edge_margin_px=0,
                                     max_incidence_deg=90.0)
    target_tree = cKDTree(targets) if idx.size else None
    fusion = VoxelFusion(job.settings.fusion_used, job.crop())
    poses: list[np.ndarray] = []
    intr = None
    for keyframe in iter_keyframes(job.keyframes_dir, FUSE, skip=DEPTH_ONLY):
        frame = keyframe.posed_depth(colour=False)
        intr = frame.intrinsics
        poses.append(np.asarray(frame.T_world_cam, np.float64))
        if job.settings.corrections.table:
            fusion.add(frame, job.table_region(frame)[0])
        else:
            fusion.add(frame)
        if target_tree is not None:
            for settings, reached in ((job.settings.fusion_used.depth, measured_local), (unfiltered, raw_local)):
                raw = backproject(frame, settings, None).points
                if len(raw):
                    hits = target_tree.query_ball_point(np.asarray(raw, np.float64), r=threshold_m)
                    near = [j for group in hits for j in group]
                    reached[np.unique(np.asarray(near, np.int64))] = True
    result = fusion.result(keep_stages=True)
    assert result.stages is not None
    view: dict[str, np.ndarray] = {}
    for name, incidence, depth_range in (("in_view", 89.9, (0.0, np.inf)),
                                         ("in_view_well", SEEABLE_MAX_INCIDENCE_DEG, SEEABLE_DEPTH_RANGE_M)):
        local = np.zeros(idx.size, bool)
        if intr is not None and idx.size:
            local = seeable_from_poses(targets, normals[idx], truth_v, truth_t, poses, width=intr.width,
                                       height=intr.height, fx=intr.fx, fy=intr.fy, ppx=intr.ppx, ppy=intr.ppy,
                                       table_z_m=float(np.min(truth_v[:, 2])), max_incidence_deg=incidence,
                                       depth_range_m=depth_range)
        full = np.zeros(len(samples), bool)
        full[idx] = local
        view[name] = full
    measured, measured_raw = np.zeros(len(samples), bool), np.zeros(len(samples), bool)
    measured[idx], measured_raw[idx] = measured_local, raw_local
    return missing_by_cause(samples, missing, in_view=view["in_view"], in_view_well=view["in_view_well"],
                            measured=measured, measured_raw=measured_raw, stages=result.stages,
                            threshold_m=threshold_m)


def evaluate_processed_survey(job: SurveyJob) -> dict[str, Any]:
    """The evaluation stage: every number of the survey's ``results.json`` that needs computing."""
    out, settings = job.out, job.settings
    folder = out / EVALUATION_DIR
    folder.mkdir(exist_ok=True)
    index = read_keyframe_index(job.keyframes_dir)
    crop = job.crop()
    v, t = read_mesh_ply(out / MESH_FILE)
    job.report("evaluation", 0, None)

    heldout_frames = posed_frames(iter_keyframes(job.keyframes_dir, HELDOUT, skip=DEPTH_ONLY), colour=False)
    heldout = evaluate_heldout(heldout_frames, MeshDistance(v, t), object_name=index.object_name or job.survey.name,
                               settings=settings.fusion_used, region=crop,
                               region_of=(lambda f: job.table_region(f)[0]) if settings.corrections.table else None)
    _save_arrays(folder / HELDOUT_DISTANCES, heldout.distances)

    arms = [a for a in job.arms if (out / f"{a}.ply").is_file()]
    clouds = {arm: _cloud(out / f"{arm}.ply") for arm in arms}
    fused, _, fused_colours = _cloud(out / FUSED_FILE)
    cross = None
    if len(arms) == 2 and all(len(clouds[a][0]) for a in arms):
        (pa, na, _), (pb, nb, _) = clouds[arms[0]], clouds[arms[1]]
        cross = cross_arm_consistency(pa, pb, normals_a=na, normals_b=nb, names=(arms[0], arms[1])).to_dict()

    truth = None
    if job.survey.truth_path is not None and (job.survey.truth_path / "object.ply").is_file():
        truth, distances = _truth(job, fused, (v, t))
        _save_arrays(folder / TRUTH_DISTANCES, distances)

    figures: dict[str, str] = {}
    if settings.evaluation.figures:
        figures = draw_figures(out, {a: clouds[a][0] for a in arms}, fused, fused_colours, heldout.distances,
                               title=index.object_name or job.survey.name)
    composition = survey_composition(job.survey)
    job.report("evaluation", 1, 1)
    return {"heldout": heldout.to_dict(), "cross_arm": cross, "truth": truth, "figures": figures,
            "composition": {**composition.__dict__, "notes": list(composition.notes)}}


def draw_figures(out: Path, arm_clouds: dict[str, np.ndarray], fused: np.ndarray, fused_colours: np.ndarray | None,
                 heldout: dict[str, np.ndarray], title: str) -> dict[str, str]:
    """The survey's figures in ``figures/``; returns their paths relative to ``out`` by kind."""
    from darp.evaluation.figures import cross_arm_figure, heldout_histogram, partial_fused_figure

    folder = out / FIGURES_DIR
    folder.mkdir(exist_ok=True)
    made: dict[str, str] = {}
    non_empty = {a: p for a, p in arm_clouds.items() if len(p)}
    if non_empty:
        cross_arm_figure(non_empty, folder / FIGURES["cross_arm"], title=f"{title}: cross-arm alignment")
        made["cross_arm"] = f"{FIGURES_DIR}/{FIGURES['cross_arm']}"
    if len(arm_clouds) == 2 and len(fused):
        (a, pa), (b, pb) = arm_clouds.items()
        partial_fused_figure(pa, pb, fused, folder / FIGURES["partial_fused"], names=(a, b),
                             fused_colours=fused_colours, title=f"{title}: partial and fused clouds")
        made["partial_fused"] = f"{FIGURES_DIR}/{FIGURES['partial_fused']}"
    if any(len(d) for d in heldout.values()):
        heldout_histogram(heldout, folder / FIGURES["heldout"], title=f"{title}: held-out point-to-mesh distances")
        made["heldout"] = f"{FIGURES_DIR}/{FIGURES['heldout']}"
    return made


__all__ = ["EVALUATION_DIR", "FIGURES", "HELDOUT_DISTANCES", "TRUTH_DISTANCES", "draw_figures",
           "evaluate_processed_survey", "keyframe_pose_pairs", "load_distances", "pose_errors_vs_truth",
           "read_truth_mesh", "world_gauge"]
