"""Measured-surface meshes: multi-scale ball pivoting over the fused cloud, then clean-up.

Ball pivoting (Bernardini et al. 1999, Open3D's ``create_from_point_cloud_ball_pivoting``) rolls a
ball of radius r over the points and makes a triangle wherever it rests on three of them without
containing any other; passes with growing radii fill the gaps the smaller balls fell through. It only
connects measured points, so regions no camera saw stay open: there is no Poisson solve and no hole
filling. Radii are multiples (default 2, 4, 8) of the cloud's point spacing, the median distance to
the nearest neighbour; the means of two neighbouring voxels often sit close to their shared face, so
that spacing is about half a voxel and the default radii are about 1, 2 and 4 voxels. Normals are
required and must face the cameras (fusion provides them): the ball pivots on the side the normals
point to, so the triangles face outward.

Clean-up removes degenerate, duplicated and non-manifold triangles, unreferenced vertices and
(optionally) tiny connected components.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from darp.errors import ReconstructionError
from darp.reconstruction.cloud_io import write_mesh_ply


@dataclass(frozen=True)
class MeshSettings:
    """Ball-pivoting parameters (docs/processing.md)."""

    radius_factors: tuple[float, ...] = (2.0, 4.0, 8.0)  # ball radii / spacing (about 1, 2, 4 voxels)
    spacing_m: float | None = None  # None: the cloud's median nearest-neighbour distance
    min_component_triangles: int = 10  # smaller connected pieces are dropped (0 keeps all)
    split_sides: bool = False  # pivot the points facing away from / toward the cloud's vertical axis apart

    def __post_init__(self) -> None:
        if not self.radius_factors or any(not f > 0 for f in self.radius_factors):
            raise ReconstructionError("radius_factors must be positive and not empty")
        if self.spacing_m is not None and not self.spacing_m > 0:
            raise ReconstructionError("spacing_m must be positive")
        if self.min_component_triangles < 0:
            raise ReconstructionError("min_component_triangles must be >= 0")


def point_spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point."""
    if points.shape[0] < 2:
        raise ReconstructionError("a cloud of fewer than two points has no spacing")
    dist, _ = cKDTree(points).query(points, k=2, workers=-1)
    spacing = float(np.median(dist[:, 1]))
    if not spacing > 0:
        raise ReconstructionError("the cloud's points coincide (zero spacing)")
    return spacing


def ball_pivoting_radii(points: np.ndarray, settings: MeshSettings | None = None) -> list[float]:
    """The ball radii (metres) for ``points``."""
    settings = settings or MeshSettings()
    spacing = settings.spacing_m if settings.spacing_m is not None else point_spacing(points)
    return sorted(spacing * f for f in settings.radius_factors)


def ball_pivoting_mesh(points: np.ndarray, normals: np.ndarray, colours: np.ndarray | None = None,
                       settings: MeshSettings | None = None) -> o3d.geometry.TriangleMesh:
    """Mesh the measured surface: multi-scale ball pivoting, then :func:`clean_mesh`.

    ``points`` and ``normals`` are (N, 3) (normals unit and oriented toward the cameras), ``colours``
    (N, 3) uint8 RGB or None.
    """
    settings = settings or MeshSettings()
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ReconstructionError(f"points {points.shape} and normals {normals.shape} must both be (N, 3)")
    if points.shape[0] < 3:
        raise ReconstructionError(f"cannot mesh {points.shape[0]} points")
    lengths = np.linalg.norm(normals, axis=1)
    if not np.all(np.abs(lengths - 1.0) < 1e-3):
        raise ReconstructionError("ball pivoting needs unit normals for every point")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    if colours is not None:
        cloud.colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64) / 255.0)
    radii = ball_pivoting_radii(points, settings)
    if not settings.split_sides:
        mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
            cloud, o3d.utility.DoubleVector(radii))
        return clean_mesh(mesh, settings.min_component_triangles)
    mesh = o3d.geometry.TriangleMesh()
    for part in normal_sides(points, normals):
        if part.sum() >= 3:
            mesh += o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
                cloud.select_by_index(np.flatnonzero(part).tolist()), o3d.utility.DoubleVector(radii))
    return clean_mesh(mesh, settings.min_component_triangles)


def normal_sides(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(outward, inward) boolean masks: whether a point's normal has a horizontal component away from the
    vertical axis through the cloud's centroid (``MeshSettings.split_sides``).

    Fused normals point toward the cameras that saw a voxel; where a surface is seen from both sides (a thin
    part, an inside wall over a rim) neighbouring points carry opposite normals. A ball touching two of them
    makes a triangle whose vertex normals disagree, so ball pivoting stops there and leaves a hole in a
    surface the fused cloud has (docs/accuracy.md, the seed-3 mug). Pivoting each side on its own avoids
    that; no point is added or moved.
    """
    radial = np.asarray(points, np.float64)[:, :2] - np.asarray(points, np.float64)[:, :2].mean(axis=0)
    outward: np.ndarray = np.einsum("ij,ij->i", np.asarray(normals, np.float64)[:, :2], radial) >= 0.0
    return outward, ~outward


def clean_mesh(mesh: o3d.geometry.TriangleMesh, min_component_triangles: int = 0) -> o3d.geometry.TriangleMesh:
    """Drop degenerate/duplicated/non-manifold triangles, small components, unreferenced vertices."""
    mesh.remove_duplicated_vertices()
    mesh.remove_duplicated_triangles()
    mesh.remove_degenerate_triangles()
    mesh.remove_non_manifold_edges()
    if min_component_triangles > 0 and len(mesh.triangles):
        ids, sizes, _ = mesh.cluster_connected_triangles()
        small = np.asarray(sizes)[np.asarray(ids)] < min_component_triangles
        if small.any():
            mesh.remove_triangles_by_mask(small)
    mesh.remove_unreferenced_vertices()
    if len(mesh.triangles):
        mesh.compute_triangle_normals()
    return mesh


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """(E, 2) vertex pairs of the edges that belong to exactly one triangle (the mesh's open rims)."""
    tri = np.asarray(triangles, np.int64)
    if tri.size == 0:
        return np.empty((0, 2), np.int64)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    rims: np.ndarray = uniq[counts == 1]
    return rims


def mesh_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (T, 3) int64) of an Open3D mesh."""
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def mesh_area(mesh: o3d.geometry.TriangleMesh) -> float:
    """Total triangle area (m^2)."""
    v, t = mesh_arrays(mesh)
    if t.size == 0:
        return 0.0
    return float(0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum())


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> Path:
    """Write ``mesh`` as binary PLY (vertices, normals, colours, faces), atomically."""
    v, t = mesh_arrays(mesh)
    normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
    colours = (np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
               if mesh.has_vertex_colors() else None)
    return write_mesh_ply(path, v, t, normals=normals, colours=colours)


__all__ = [
    "MeshSettings",
    "ball_pivoting_mesh",
    "ball_pivoting_radii",
    "boundary_edges",
    "clean_mesh",
    "normal_sides",
    "mesh_area",
    "mesh_arrays",
    "point_spacing",
    "write_mesh",
]
