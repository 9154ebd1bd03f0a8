"""Exact point-to-mesh distances (Open3D RaycastingScene, Embree closest-point queries) and their statistics.

The distance of a point to a triangle mesh is the distance to the nearest point on any triangle
(unsigned; open meshes are fine). :class:`MeshDistance` builds the acceleration structure once and
answers any number of queries in chunks, so memory stays bounded for millions of points.
:func:`distance_stats` gives the paper's held-out table: median, RMSE, 90th percentile and the share of
points within 5 and 10 mm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from darp.errors import EvaluationError

DEFAULT_THRESHOLDS_M = (0.005, 0.010)
_CHUNK = 1 << 20


class MeshDistance:
    """Distances from points to one triangle mesh (world frame, metres)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        vertices = np.asarray(vertices, np.float32)
        triangles = np.asarray(triangles, np.uint32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
            raise EvaluationError(f"mesh arrays must be (V, 3) and (T, 3), got {vertices.shape} {triangles.shape}")
        if triangles.shape[0] == 0:
            raise EvaluationError("the mesh has no triangles: nothing to measure distances to")
        if triangles.max() >= vertices.shape[0]:
            raise EvaluationError("triangle indices point past the vertex array")
        self.n_triangles = int(triangles.shape[0])
        self._scene = o3d.t.geometry.RaycastingScene()
        # open3d's stubs make Tensor's dtype and device required; they default to the array's and the CPU
        self._scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))  # type: ignore[call-overload]

    @classmethod
    def from_open3d(cls, mesh: o3d.geometry.TriangleMesh) -> MeshDistance:
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.triangles))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N,) float32 unsigned distance of each point to the mesh."""
        pts = _as_points(points)
        out = np.empty(pts.shape[0], np.float32)
        for start in range(0, pts.shape[0], _CHUNK):
            chunk = o3d.core.Tensor(pts[start:start + _CHUNK])  # type: ignore[call-overload]  # (see __init__)
            out[start:start + _CHUNK] = self._scene.compute_distance(chunk).numpy()
        return out

    def closest_points(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) float32 nearest surface points, (N,) int64 triangle index)."""
        pts = _as_points(points)
        closest = np.empty_like(pts)
        tri = np.empty(pts.shape[0], np.int64)
        for start in range(0, pts.shape[0], _CHUNK):
            chunk = o3d.core.Tensor(pts[start:start + _CHUNK])  # type: ignore[call-overload]  # (see __init__)
            answer = self._scene.compute_closest_points(chunk)
            closest[start:start + _CHUNK] = answer["points"].numpy()
            tri[start:start + _CHUNK] = answer["primitive_ids"].numpy()
        return closest, tri


def _as_points(points: np.ndarray) -> np.ndarray:
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise EvaluationError(f"query points must be (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise EvaluationError("query points contain NaN or infinity")
    return pts


@dataclass(frozen=True)
class DistanceStats:
    """Summary of unsigned distances (metres); ``within_pct`` maps a threshold (m) to a percentage."""

    count: int
    median_m: float
    mean_m: float
    rmse_m: float
    p90_m: float
    max_m: float
    within_pct: dict[float, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Millimetres and percentages, for reports and JSON."""
        out: dict[str, Any] = {"count": self.count}
        for name in ("median", "mean", "rmse", "p90", "max"):
            value = getattr(self, f"{name}_m")
            out[f"{name}_mm"] = None if np.isnan(value) else round(value * 1000.0, 4)
        for threshold, pct in sorted(self.within_pct.items()):
            out[f"within_{threshold * 1000.0:g}mm_pct"] = None if np.isnan(pct) else round(pct, 4)
        return out


def distance_stats(distances: np.ndarray, thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M) -> DistanceStats:
    """Median, mean, RMSE, 90th percentile (linear interpolation), max and % within each threshold.

    An empty input gives count 0 and NaN statistics (a region nobody saw is not an error).
    """
    d = np.asarray(distances, np.float64).reshape(-1)
    if d.size and (not np.all(np.isfinite(d)) or d.min() < 0):
        raise EvaluationError("distances must be finite and non-negative")
    if d.size == 0:
        nan = float("nan")
        return DistanceStats(0, nan, nan, nan, nan, nan, {float(t): nan for t in thresholds_m})
    return DistanceStats(
        count=int(d.size),
        median_m=float(np.median(d)),
        mean_m=float(d.mean()),
        rmse_m=float(np.sqrt(np.mean(d * d))),
        p90_m=float(np.percentile(d, 90)),
        max_m=float(d.max()),
        within_pct={float(t): float(100.0 * np.count_nonzero(d <= t) / d.size) for t in thresholds_m},
    )


def point_to_mesh_distances(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """One-shot convenience: distances of ``points`` to the mesh ``(vertices, triangles)``."""
    return MeshDistance(vertices, triangles).distances(points)


__all__ = ["DEFAULT_THRESHOLDS_M", "DistanceStats", "MeshDistance", "distance_stats", "point_to_mesh_distances"]
