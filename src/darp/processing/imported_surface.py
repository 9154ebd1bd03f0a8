"""The measured surface of an imported (real) survey: depth statistics, cleaned TSDF, support-trimmed mesh.

``surface.method`` chooses the surface of a survey: ``paper`` (voxel-support fusion and ball pivoting,
:mod:`darp.reconstruction.fusion`), ``measured`` (:mod:`darp.reconstruction.tsdf_surface`), or ``auto``:
measured for imported surveys, paper for DARP and twin surveys (whose outputs stay as they were: on the
twin's ``paper`` profile the paper surface was closer to the truth, docs/processing.md).

Held-out frames are cleaned with the same per-frame rules as the fused ones (depth range, discontinuities,
crop) and scored against the mesh, as the paper surface's held-out frames are with fusion's filters.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d

from darp.evaluation.heldout import HeldoutResult
from darp.evaluation.point_to_mesh import MeshDistance
from darp.reconstruction.backproject import PosedDepth, Region
from darp.reconstruction.cloud_io import write_cloud_ply
from darp.reconstruction.depth_stats import DepthStats, survey_depth_stats
from darp.reconstruction.tsdf_surface import MeasuredSurface, SurfaceSettings, _crop, clean_depth, open_share

DEPTH_ONLY = ("ir_left", "ir_right", "support_mask", "rgb")


def resolve_method(settings: SurfaceSettings, imported: bool) -> str:
    """``paper`` or ``measured`` for a survey (``auto``: measured when imported)."""
    if settings.method == "auto":
        return "measured" if imported else "paper"
    return settings.method


def depth_stats_of(frames: Iterable[PosedDepth], settings: SurfaceSettings) -> DepthStats:
    """The survey's depth statistics from its fuse frames."""
    return survey_depth_stats(((f.depth, f.depth_scale, 0.5 * (f.intrinsics.fx + f.intrinsics.fy)) for f in frames),
                              max_incidence_deg=settings.max_incidence_deg)


def build_measured_surface(stats: DepthStats, frames: Iterable[PosedDepth], settings: SurfaceSettings,
                           region: Region | None = None) -> tuple[o3d.geometry.TriangleMesh, dict[str, Any]]:
    """Integrate ``frames`` (streamed) and extract the supported mesh; returns it and its record."""
    surface = MeasuredSurface(stats, settings, region)
    t0 = time.process_time()
    for frame in frames:
        surface.add(frame)
    t1 = time.process_time()
    mesh, info = surface.mesh()
    info["cpu_s"] = {"integrate": t1 - t0, "extract": time.process_time() - t1}
    info["depth_stats"] = stats.to_dict()
    mesh.compute_vertex_normals()
    return mesh, info


def heldout_points_measured(frame: PosedDepth, stats: DepthStats, surface: dict[str, Any],
                            settings: SurfaceSettings, region: Region | None) -> np.ndarray:
    """World points (N, 3) of a held-out frame after the measured surface's per-frame cleaning."""
    it = frame.intrinsics
    lo, hi = surface["depth_range_m"]
    z = clean_depth(frame.depth, frame.depth_scale, 0.5 * (it.fx + it.fy), stats, lo, hi, settings.edge_margin_px)
    if region is not None:
        z = _crop(z, frame, region)
    step = settings.heldout_stride_px
    v, u = np.nonzero(z[::step, ::step])
    v, u = v * step, u * step
    zz = z[v, u]
    P = np.stack([(u - it.ppx) / it.fx * zz, (v - it.ppy) / it.fy * zz, zz], 1)
    return np.asarray(P @ frame.T_world_cam[:3, :3].T + frame.T_world_cam[:3, 3], np.float32)


def evaluate_heldout_measured(frames: Iterable[PosedDepth], mesh: MeshDistance, stats: DepthStats,
                              surface: dict[str, Any], settings: SurfaceSettings, region: Region | None,
                              object_name: str, keep: Callable[[PosedDepth, np.ndarray], None] | None = None
                              ) -> HeldoutResult:
    """Held-out distances of the cleaned held-out frames to the measured mesh (streamed)."""
    parts: dict[str, list[np.ndarray]] = {}
    counts: dict[str, int] = {}
    for frame in frames:
        points = heldout_points_measured(frame, stats, surface, settings, region)
        if keep is not None:
            keep(frame, points)
        counts[frame.arm] = counts.get(frame.arm, 0) + 1
        parts.setdefault(frame.arm, []).append(mesh.distances(points) if len(points) else np.empty(0, np.float32))
    return HeldoutResult(object_name, {a: np.concatenate(p).astype(np.float32) for a, p in parts.items()}, counts)


def write_mesh_cloud(path: Path, mesh: o3d.geometry.TriangleMesh, arm: str) -> Path:
    """The mesh's vertices as the survey's fused cloud (``fused.ply``: positions, normals, colours)."""
    colours = (np.clip(np.rint(np.asarray(mesh.vertex_colors) * 255), 0, 255).astype(np.uint8)
               if mesh.has_vertex_colors() else None)
    return write_cloud_ply(path, np.asarray(mesh.vertices, np.float32),
                           normals=np.asarray(mesh.vertex_normals, np.float32) if mesh.has_vertex_normals() else None,
                           colours=colours, comments=[f"arms {arm}", "measured surface: mesh vertices"])


def mesh_raster_figure(mesh: o3d.geometry.TriangleMesh, held_points: list[np.ndarray], path: Path, title: str,
                       median_mm: float, cells: int = 500) -> None:
    """The mesh from above (x, y) and the side (x, z) as rasters: every triangle's centre binned into ``cells``
    columns, shaded by its normal's light (the nearest triangle to the viewer wins), with a held-out frame's
    points in red. A raster shows a mesh of millions of triangles whole, at a fixed cost."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from darp.formats.atomic import atomic_path

    V = np.asarray(mesh.vertices, np.float32)
    F = np.asarray(mesh.triangles)
    F = F[::max(len(F) // (2 * cells * cells), 1)]  # about two triangles per cell are enough to fill it
    centres = V[F].mean(axis=1) if len(F) else np.empty((0, 3), np.float32)
    normals = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]) if len(F) else np.empty((0, 3))
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    fig = Figure(figsize=(12, 5))
    for n, (a, b, depth_axis, name) in enumerate(((0, 1, 2, "top (x, y)"), (0, 2, 1, "side (x, z)"))):
        ax = fig.add_subplot(1, 2, n + 1)
        if len(centres):
            lo, hi = centres.min(axis=0), centres.max(axis=0)
            size = max(float(hi[a] - lo[a]), float(hi[b] - lo[b]), 1e-6) / cells
            ia = ((centres[:, a] - lo[a]) / size).astype(np.int64)
            ib = ((centres[:, b] - lo[b]) / size).astype(np.int64)
            shape = (int(ib.max()) + 1, int(ia.max()) + 1)
            # nearest to the viewer: highest z from above, lowest y from the side (the viewer at -y)
            key = centres[:, depth_axis] if depth_axis == 2 else -centres[:, depth_axis]
            order = np.argsort(key, kind="stable")  # later (nearer) triangles overwrite earlier ones
            shade = np.full(shape, np.nan, np.float32)
            shade[ib[order], ia[order]] = np.abs(normals[order, depth_axis])
            ax.imshow(shade, origin="lower", cmap="gray", vmin=0, vmax=1, interpolation="nearest",
                      extent=(lo[a], lo[a] + shape[1] * size, lo[b], lo[b] + shape[0] * size))
        for P in held_points[:1]:
            if len(P):
                ax.scatter(P[:, a], P[:, b], s=0.2, c="red", alpha=0.3)
        ax.set_aspect("equal")
        ax.set_title(f"{title}: mesh {name}" + (f"; held-out median {median_mm:.2f} mm" if n == 0 else ""))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def envelope_open_pct(mesh: o3d.geometry.TriangleMesh, envelope: dict[str, Any], voxel_m: float) -> float | None:
    """Share of the envelope's side and top left open by the mesh (None without an envelope cylinder)."""
    centre, radius, height = envelope.get("center_m"), envelope.get("radius_m"), envelope.get("height_m")
    if centre is None or radius is None or height is None:
        return None
    return open_share(np.asarray(mesh.vertices), np.asarray(centre, float), float(radius), float(height),
                      max(2.0 * voxel_m, 0.002))


__all__ = ["DEPTH_ONLY", "build_measured_surface", "depth_stats_of", "envelope_open_pct", "mesh_raster_figure",
           "evaluate_heldout_measured", "heldout_points_measured", "resolve_method", "write_mesh_cloud"]
