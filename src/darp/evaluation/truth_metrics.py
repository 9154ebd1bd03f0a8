"""Metrics against ground truth (the digital twin's true object mesh): accuracy, completeness, F-score.

- **Accuracy**: distance of every reconstructed point to the true mesh (median, RMSE, p90...). Its
  share within a threshold is the **precision** at that threshold.
- **Completeness**: the share of the *seen* true surface that the reconstruction reaches: true-surface
  samples (area-uniform) that some keyframe saw, within a threshold of the nearest reconstructed point.
  Only seen samples count, because the pipeline never invents unseen geometry (the underside on the
  table is not a miss).
- **F-score** at a threshold: harmonic mean of precision and completeness.
- The mesh is judged the same way: its area-uniform samples against the true mesh (accuracy) and the
  seen true samples against the mesh (completeness).

Evaluation does not import the twin: the caller passes the true mesh as arrays. Visibility can be given
or computed here by projecting the samples into keyframes' depth images with a z-test.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from darp.errors import EvaluationError
from darp.evaluation.point_to_mesh import DistanceStats, MeshDistance, distance_stats
from darp.reconstruction.backproject import PosedDepth, check_pose, depth_to_metres

TRUTH_THRESHOLDS_M = (0.002, 0.005, 0.010)


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, rng: np.random.Generator, *,
                   spacing_m: float | None = None, count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random samples of a triangle mesh: ``(points (N, 3), unit normals (N, 3))``.

    Give ``count`` or ``spacing_m`` (then N = area / spacing^2). Normals follow the triangles' winding.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    if t.size == 0:
        raise EvaluationError("cannot sample a mesh without triangles")
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    double_area = np.linalg.norm(cross, axis=1)
    total = 0.5 * double_area.sum()
    if count is None:
        if spacing_m is None or not spacing_m > 0:
            raise EvaluationError("sample_surface needs count or a positive spacing_m")
        count = max(1, math.ceil(round(total / spacing_m**2, 6)))
    if total <= 0:
        raise EvaluationError("the mesh has zero area")
    tri = rng.choice(t.shape[0], size=count, p=double_area / double_area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1.0
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    a, b, c = v[t[tri, 0]], v[t[tri, 1]], v[t[tri, 2]]
    points = a + r1[:, None] * (b - a) + r2[:, None] * (c - a)
    normals = cross[tri] / np.where(double_area[tri] > 0, double_area[tri], 1.0)[:, None]
    return points, normals


def visible_in_frames(samples: np.ndarray, frames: Iterable[PosedDepth], *, tolerance_m: float = 0.005,
                      normals: np.ndarray | None = None) -> np.ndarray:
    """Boolean (N,): samples that at least one frame saw.

    A frame sees a sample when it projects inside the image onto a pixel with depth within
    ``tolerance_m`` of the sample's own depth and (with ``normals``) the sample faces the camera.
    """
    pts = np.asarray(samples, np.float64)
    seen = np.zeros(pts.shape[0], bool)
    for frame in frames:
        intr = frame.intrinsics
        if intr.model.lower() != "none" and any(abs(c) > 0 for c in intr.coeffs):
            raise EvaluationError("visibility needs undistorted depth intrinsics")
        T = check_pose(frame.T_world_cam)
        depth_m = depth_to_metres(frame.depth, frame.depth_scale)
        R, t = T[:3, :3], T[:3, 3]
        cam = (pts - t) @ R  # R^T (p - t)
        z = cam[:, 2]
        front = z > 1e-6
        u = np.rint(intr.fx * cam[:, 0] / np.where(front, z, 1.0) + intr.ppx).astype(np.int64)
        v = np.rint(intr.fy * cam[:, 1] / np.where(front, z, 1.0) + intr.ppy).astype(np.int64)
        inside = front & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        idx = np.flatnonzero(inside & ~seen)
        if normals is not None and idx.size:
            facing = np.einsum("ij,ij->i", np.asarray(normals, np.float64)[idx], t - pts[idx]) > 0
            idx = idx[facing]
        d = depth_m[v[idx], u[idx]]
        seen[idx[(d > 0) & (np.abs(d - z[idx]) <= tolerance_m)]] = True
    return seen


SEEABLE_MAX_INCIDENCE_DEG = 60.0  # beyond this a D4 depth pixel is too noisy to count as seen
SEEABLE_DEPTH_RANGE_M = (0.17, 1.2)  # the D435's usable depth range at the survey standoffs


def seeable_from_poses(samples: np.ndarray, normals: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                       poses: Iterable[np.ndarray], *, width: int = 640, height: int = 480, fx: float = 383.0,
                       fy: float = 383.0, ppx: float | None = None, ppy: float | None = None,
                       table_z_m: float | None = 0.0,
                       max_incidence_deg: float = SEEABLE_MAX_INCIDENCE_DEG,
                       depth_range_m: tuple[float, float] = SEEABLE_DEPTH_RANGE_M,
                       tolerance_m: float = 0.002) -> np.ndarray:
    """Boolean (N,): true-surface samples that at least one camera pose (``T_world_cam``, 4x4 or its top
    3x4 rows, optical axis +z) can see: the sample is the first surface its ray meets (Open3D ray casting
    against the true mesh and, with ``table_z_m``, the table plane; within ``tolerance_m``), it faces the
    camera within
    ``max_incidence_deg``, projects inside the ``width`` x ``height`` image (pinhole ``fx``, ``fy``, centred
    principal point unless given) and its depth is within ``depth_range_m``. With the feasible camera poses of a
    survey's planner this is "the surface any feasible camera pose can see"."""
    import open3d as o3d

    pts = np.asarray(samples, np.float64)
    nrm = np.asarray(normals, np.float64)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),  # type: ignore[call-overload]
                        o3d.core.Tensor(np.asarray(triangles, np.uint32)))  # type: ignore[call-overload]
    if table_z_m is not None:
        c = pts.mean(axis=0) if len(pts) else np.zeros(3)
        quad = np.array([[c[0] - 2, c[1] - 2, table_z_m], [c[0] + 2, c[1] - 2, table_z_m],
                         [c[0] + 2, c[1] + 2, table_z_m], [c[0] - 2, c[1] + 2, table_z_m]], np.float32)
        quad_t = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
        scene.add_triangles(o3d.core.Tensor(quad), o3d.core.Tensor(quad_t))  # type: ignore[call-overload]
    cos_max = math.cos(math.radians(max_incidence_deg))
    seen = np.zeros(len(pts), bool)
    for pose in poses:
        T = np.eye(4)
        T[:3] = np.asarray(pose, np.float64).reshape(-1, 4)[:3]
        T = check_pose(T)
        c = T[:3, 3]
        d = pts - c
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-12)[:, None]
        pc = d @ T[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            px = fx * pc[:, 0] / z + (width / 2 if ppx is None else ppx)
            py = fy * pc[:, 1] / z + (height / 2 if ppy is None else ppy)
        ok = ((-np.einsum("ij,ij->i", u, nrm) >= cos_max) & (z >= depth_range_m[0]) & (z <= depth_range_m[1])
              & (px >= 0) & (px < width) & (py >= 0) & (py < height) & ~seen)
        idx = np.flatnonzero(ok)
        if idx.size:
            rays = np.hstack([np.tile(c, (idx.size, 1)), u[idx]]).astype(np.float32)
            hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # type: ignore[call-overload]
            seen[idx[np.abs(hit - dist[idx]) < tolerance_m]] = True
    return seen


MISSING_CAUSES = ("not_in_view", "grazing_or_range", "no_depth", "depth_filter", "crop", "support",
                  "outlier_removal", "surface_fit")
"""Where a seeable true-surface sample missing from the fused cloud was lost, in pipeline order (see
:func:`missing_by_cause`)."""


def missing_by_cause(samples: np.ndarray, missing: np.ndarray, *, in_view: np.ndarray, in_view_well: np.ndarray,
                     measured: np.ndarray, stages: dict[str, np.ndarray], threshold_m: float,
                     measured_raw: np.ndarray | None = None) -> dict[str, Any]:
    """Why each ``missing`` sample (a seeable true-surface sample farther than ``threshold_m`` from the fused
    cloud) is missing: the last step of the pipeline that still had a point within ``threshold_m`` of it.

    - ``not_in_view``: no fused keyframe had it in its image unoccluded (``in_view`` False): planning;
    - ``grazing_or_range``: in view, but only beyond the seeable incidence or depth range (``in_view_well``
      False): planning;
    - ``no_depth``: in view well, but no frame's depth has a point near it, even unfiltered (``measured_raw``
      False: depth holes, or poses that put the measurement elsewhere);
    - ``depth_filter``: the unfiltered depth had a point near it, the per-frame depth filters (edges,
      incidence, range) left none (``measured`` False);
    - ``crop``: measured, but no voxel inside the envelope/table crop near it (``stages['in_envelope']``);
    - ``support``: a voxel near it, none supported (``stages['supported']``);
    - ``outlier_removal``: supported, removed by statistical outlier removal (``stages['after_sor']``);
    - ``surface_fit``: kept after outlier removal, moved or merged away by the surface fit.

    ``in_view``, ``in_view_well``, ``measured`` and ``measured_raw`` (default: ``measured``) are boolean per
    sample. Returns counts and shares (of the
    missing samples) per cause."""
    pts = np.asarray(samples, np.float64)
    todo = np.flatnonzero(np.asarray(missing, bool))
    cause = np.full(todo.size, -1, np.int64)

    def near(points: np.ndarray | None, idx: np.ndarray) -> np.ndarray:
        if points is None or len(points) == 0 or idx.size == 0:
            return np.zeros(idx.size, bool)
        d = cKDTree(np.asarray(points, np.float64)).query(pts[idx], k=1, distance_upper_bound=threshold_m)[0]
        found: np.ndarray = d <= threshold_m
        return found

    # from the end of the pipeline backwards: the first stage that still had the sample is the one that lost it
    for code, stage in ((7, "after_sor"), (6, "supported"), (5, "in_envelope")):
        open_ = np.flatnonzero(cause < 0)
        cause[open_[near(stages.get(stage), todo[open_])]] = code
    raw = measured if measured_raw is None else np.asarray(measured_raw, bool) | np.asarray(measured, bool)
    for code, mask in ((4, measured), (3, raw), (2, in_view_well), (1, in_view)):
        open_ = np.flatnonzero(cause < 0)
        cause[open_[np.asarray(mask, bool)[todo[open_]]]] = code
    cause[cause < 0] = 0
    counts = np.bincount(cause, minlength=len(MISSING_CAUSES))
    total = max(int(todo.size), 1)
    return {"missing": int(todo.size), "threshold_mm": round(threshold_m * 1000.0, 3),
            "count": {name: int(counts[i]) for i, name in enumerate(MISSING_CAUSES)},
            "share_pct": {name: round(100.0 * float(counts[i]) / total, 2) for i, name in enumerate(MISSING_CAUSES)}}


@dataclass(frozen=True)
class SurfaceScores:
    """Accuracy (reconstruction -> truth), completeness (seen truth -> reconstruction) and F-score."""

    accuracy: DistanceStats  # within_pct = precision at each threshold
    completeness: DistanceStats  # distances of the seen true samples; within_pct = completeness
    thresholds_m: tuple[float, ...]

    def precision_pct(self, threshold_m: float) -> float:
        return self.accuracy.within_pct[threshold_m]

    def completeness_pct(self, threshold_m: float) -> float:
        return self.completeness.within_pct[threshold_m]

    def fscore_pct(self, threshold_m: float) -> float:
        p, r = self.precision_pct(threshold_m), self.completeness_pct(threshold_m)
        return 0.0 if p + r == 0 else 2.0 * p * r / (p + r)

    def to_dict(self) -> dict[str, Any]:
        return {
            "accuracy": self.accuracy.to_dict(),
            "completeness": self.completeness.to_dict(),
            "fscore_pct": {f"{t * 1000:g}mm": round(self.fscore_pct(t), 4) for t in self.thresholds_m},
        }


@dataclass(frozen=True)
class TruthMetrics:
    """Cloud and (optionally) mesh scored against the true surface."""

    cloud: SurfaceScores
    mesh: SurfaceScores | None
    n_samples: int
    n_seen: int

    def to_dict(self) -> dict[str, Any]:
        return {"samples": self.n_samples, "seen": self.n_seen, "cloud": self.cloud.to_dict(),
                "mesh": None if self.mesh is None else self.mesh.to_dict()}


def truth_metrics(points: np.ndarray, truth_vertices: np.ndarray, truth_triangles: np.ndarray,
                  truth_samples: np.ndarray, seen: np.ndarray | None = None, *,
                  mesh: tuple[np.ndarray, np.ndarray] | None = None, rng: np.random.Generator | None = None,
                  mesh_sample_spacing_m: float = 0.001,
                  thresholds_m: Sequence[float] = TRUTH_THRESHOLDS_M) -> TruthMetrics:
    """Score a reconstructed cloud (and mesh ``(vertices, triangles)``) against the true mesh.

    ``truth_samples`` are area-uniform samples of the true surface, ``seen`` marks those some keyframe
    saw (all, when None). Mesh samples are drawn with ``rng`` (seed 0 by default) at ``mesh_sample_spacing_m``.
    """
    thresholds = tuple(float(t) for t in thresholds_m)
    samples = np.asarray(truth_samples, np.float64)
    seen_mask = np.ones(samples.shape[0], bool) if seen is None else np.asarray(seen, bool)
    if seen_mask.shape != (samples.shape[0],):
        raise EvaluationError("the seen mask must have one entry per true-surface sample")
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise EvaluationError("the reconstruction has no points to score")
    truth = MeshDistance(truth_vertices, truth_triangles)
    target = samples[seen_mask]

    to_cloud = cKDTree(pts).query(target, k=1, workers=-1)[0] if target.size else np.empty(0)
    cloud = SurfaceScores(distance_stats(truth.distances(pts), thresholds),
                          distance_stats(to_cloud, thresholds), thresholds)
    mesh_scores = None
    if mesh is not None:
        rng = rng if rng is not None else np.random.default_rng(0)
        mesh_points, _ = sample_surface(mesh[0], mesh[1], rng, spacing_m=mesh_sample_spacing_m)
        to_mesh = MeshDistance(*mesh).distances(target) if target.size else np.empty(0)
        mesh_scores = SurfaceScores(distance_stats(truth.distances(mesh_points), thresholds),
                                    distance_stats(to_mesh, thresholds), thresholds)
    return TruthMetrics(cloud=cloud, mesh=mesh_scores, n_samples=int(samples.shape[0]),
                        n_seen=int(seen_mask.sum()))


__all__ = ["MISSING_CAUSES", "SEEABLE_DEPTH_RANGE_M", "SEEABLE_MAX_INCIDENCE_DEG", "TRUTH_THRESHOLDS_M",
           "SurfaceScores", "TruthMetrics", "missing_by_cause", "sample_surface", "seeable_from_poses",
           "truth_metrics", "visible_in_frames"]
