"""The measured surface of real depth: a fused signed distance kept only where enough frames measured it.

Each fuse frame's depth is cleaned first (:func:`clean_depth`): outside the survey's depth range (its own
distribution, :mod:`darp.reconstruction.depth_stats`; a far body behind an empty gap, such as a floor seen
through a glass table, is cut), pixels whose neighbours jump by more than one surface can at that depth
(noise growing with z^2 plus the step of a surface at the largest incidence) and ``edge_margin_px`` around
them (flying pixels and the fattened foreground at silhouettes), and pixels outside the crop region. The
cleaned depth is integrated into a truncated signed distance (Open3D's ``VoxelBlockGrid``; truncation three
noise sigmas at the far end of the range), where each voxel's weight counts the frames that measured it.

Marching cubes then extracts the zero level only where every corner voxel was measured by at least
``min_frames`` frames: the support. Nothing is closed that no frame saw (a TSDF fills no hole; it only joins
measurements), and a surface seen by one frame alone is not kept. ``min_frames`` comes from the survey's visit
counts (:func:`support_frames`).

Marching cubes places a vertex by interpolating the signed distance linearly between two voxel centres, so on
real depth its vertices sit up to a voxel's fraction off the depth the frames measured. The last pass
(:meth:`MeasuredSurface.snap`) moves every vertex along its normal to the weighted mean of the fuse frames'
measurements there: each frame that sees the vertex within the truncation, at an incidence below
``max_incidence_deg``, gives the offset along the normal of the point its cleaned depth measured at the vertex's
pixel, weighted by ``1 / sigma(z)^2`` of the survey's noise model (a near frame counts more than a far one). At
most ``2 * SNAP_FRAMES`` frames, spread over the survey, are kept for it (their cleaned depth).

:func:`open_share` reports how much of the envelope's top and side the mesh leaves open.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d

from darp.errors import ReconstructionError
from darp.reconstruction.backproject import PosedDepth, Region
from darp.reconstruction.depth_stats import DepthStats, invalid_depth

METHODS = ("auto", "paper", "measured")
COLOUR_EVERY = 8  # every 8th fuse frame is kept (subsampled) to colour the mesh
COLOUR_STEP_PX = 2  # ... at every 2nd pixel
COLOUR_VIEWS = 4  # at most this many of them, spread over the survey, colour the vertices (first come, first served)
SNAP_FRAMES = 8  # the vertex pass keeps between this and twice this many fuse frames, spread over the survey


@dataclass(frozen=True)
class SurfaceSettings:
    """``surface`` settings of ``darp process``: which surface, and overrides of what the data gives."""

    method: str = "auto"  # auto: measured for imported surveys, paper for DARP surveys; paper; measured
    voxel_size_m: float | None = None  # None: from the survey's depth (depth_stats)
    min_depth_m: float | None = None  # None: from the survey's depth distribution
    max_depth_m: float | None = None  # None: from the survey's depth distribution (cut at an empty gap)
    min_frames: int | None = None  # frames that must measure every corner of a cube; None: from the visit counts
    truncation_m: float | None = None  # None: from the depth noise (depth_stats)
    edge_margin_px: int = 0  # further pixels dropped around a discontinuity (its nearer pixel always goes)
    max_incidence_deg: float = 75.0  # steeper steps between neighbouring pixels are discontinuities
    block_resolution: int = 8  # voxels per block side of the hash grid
    heldout_stride_px: int = 3  # held-out frames are scored at every n-th pixel of each row and column
    snap: bool = True  # move the vertices along their normals to the frames' noise-weighted mean depth

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ReconstructionError(f"surface.method must be one of {', '.join(METHODS)}, got {self.method!r}")
        for name in ("voxel_size_m", "min_depth_m", "max_depth_m", "min_frames", "truncation_m"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ReconstructionError(f"surface.{name} must be > 0 (or absent: from the data), got {value}")
        if self.heldout_stride_px < 1:
            raise ReconstructionError(f"surface.heldout_stride_px must be >= 1, got {self.heldout_stride_px}")
        if self.edge_margin_px < 0 or not 0 < self.max_incidence_deg < 90 or self.block_resolution not in (8, 16):
            raise ReconstructionError("surface: edge_margin_px >= 0, max_incidence_deg in (0, 90), "
                                      "block_resolution 8 or 16")


def clean_depth(raw: np.ndarray, scale: float, focal_px: float, stats: DepthStats, lo: float, hi: float,
                margin_px: int) -> np.ndarray:
    """Float32 metric depth with 0 where there is no trustworthy measurement (module doc)."""
    z = raw.astype(np.float32) * np.float32(scale)
    z[invalid_depth(raw) | (z < lo) | (z > hi)] = 0.0
    valid = z > 0
    bound = np.float32(4.0 * math.sqrt(2.0) * stats.noise_a) * np.square(z) + z * np.float32(
        math.tan(math.radians(stats.max_incidence_deg)) / focal_px)
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a = z[:-1] if axis == 0 else z[:, :-1]
        b = z[1:] if axis == 0 else z[:, 1:]
        ba = bound[:-1] if axis == 0 else bound[:, :-1]
        bb = bound[1:] if axis == 0 else bound[:, 1:]
        va = valid[:-1] if axis == 0 else valid[:, :-1]
        vb = valid[1:] if axis == 0 else valid[:, 1:]
        jump = (np.abs(a - b) > np.minimum(ba, bb)) & va & vb
        # the farther pixel of a jump is background and stays; the nearer (and a pixel beside a hole) goes
        near_a = jump & (a < b)
        near_b = jump & (b < a)
        if axis == 0:
            edge[:-1] |= near_a | (va & ~vb)
            edge[1:] |= near_b | (vb & ~va)
        else:
            edge[:, :-1] |= near_a | (va & ~vb)
            edge[:, 1:] |= near_b | (vb & ~va)
    if margin_px > 0:
        import cv2

        edge = cv2.dilate(edge.view(np.uint8), np.ones((2 * margin_px + 1,) * 2, np.uint8)).astype(bool)
    z[edge] = 0.0
    return z


def support_frames(weights: np.ndarray) -> int:
    """Frames that must measure every corner of a cube for it to be meshed: two (a second frame confirms every
    surface), three in a dense survey whose median near-surface voxel was measured by 20 frames or more (there a
    surface two frames saw while its neighbours were seen twenty times is more likely an artefact)."""
    if weights.size == 0:
        return 2
    return 3 if float(np.median(weights)) >= 20 else 2


class MeasuredSurface:
    """Streaming TSDF of cleaned depth: :meth:`add` frames, then :meth:`mesh`."""

    def __init__(self, stats: DepthStats, settings: SurfaceSettings | None = None,
                 region: Region | None = None) -> None:
        self.settings = settings or SurfaceSettings()
        self.stats = stats
        self.region = region
        s = self.settings
        self.voxel_size_m = s.voxel_size_m or stats.voxel_size_m
        self.min_depth_m = s.min_depth_m or stats.min_depth_m
        self.max_depth_m = s.max_depth_m or stats.max_depth_m
        self.truncation_m = s.truncation_m or max(stats.truncation_m, 2.0 * self.voxel_size_m)
        self.frames = 0
        self.pixels_in = 0
        self.pixels_kept = 0
        self._grid: Any = None
        self._views: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]] = []
        self._snap_views: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (cleaned depth, K, extrinsic)
        self._snap_every = 1

    def _make_grid(self) -> Any:
        f32 = o3d.core.float32
        # open3d's stubs want SizeVectors for the channels; its binding takes plain ints (as its examples pass)
        return o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (f32, f32), (1, 1),  # type: ignore[arg-type]
                                             self.voxel_size_m, self.settings.block_resolution, 4096,
                                             o3d.core.Device("CPU:0"))

    def add(self, frame: PosedDepth) -> int:
        """Clean and integrate one frame; returns the pixels it kept. Colour is not fused (it doubles the cost
        of integration): every ``colour_every``-th frame is kept, subsampled, to colour the mesh's vertices."""
        it = frame.intrinsics
        focal = 0.5 * (it.fx + it.fy)
        z = clean_depth(frame.depth, frame.depth_scale, focal, self.stats, self.min_depth_m, self.max_depth_m,
                        self.settings.edge_margin_px)
        if self.region is not None:
            z = _crop(z, frame, self.region)
        kept = int(np.count_nonzero(z))
        self.frames += 1
        self.pixels_in += int(np.count_nonzero(frame.depth))
        self.pixels_kept += kept
        if kept == 0:
            return 0
        if self._grid is None:
            self._grid = self._make_grid()
        K = np.array([[it.fx, 0, it.ppx], [0, it.fy, it.ppy], [0, 0, 1]])
        extrinsic = np.linalg.inv(frame.T_world_cam)
        # open3d's stubs make Tensor's dtype and device required; they default to the array's and the CPU
        Kt = o3d.core.Tensor.from_numpy(np.ascontiguousarray(K, np.float64))
        Et = o3d.core.Tensor.from_numpy(np.ascontiguousarray(extrinsic, np.float64))
        depth = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(z)))
        mult = self.truncation_m / self.voxel_size_m
        blocks = self._grid.compute_unique_block_coordinates(depth, Kt, Et, 1.0, self.max_depth_m, mult)
        self._grid.integrate(blocks, depth, Kt, Et, 1.0, self.max_depth_m, mult)
        if frame.colour is not None and (self.frames - 1) % COLOUR_EVERY == 0:
            step = COLOUR_STEP_PX
            self._views.append((frame.colour[::step, ::step].copy(), z[::step, ::step].copy(), K, extrinsic, step))
        if self.settings.snap and (self.frames - 1) % self._snap_every == 0:
            self._snap_views.append((z, K, extrinsic))
            if len(self._snap_views) >= 2 * SNAP_FRAMES:  # keep every other one from now on: spread, bounded
                self._snap_views = self._snap_views[::2]
                self._snap_every *= 2
        return kept

    def snap(self, vertices: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, float]:
        """``vertices`` moved along their unit ``normals`` to the kept frames' noise-weighted mean measurement
        (module doc); returns them and the share (%) of vertices some frame measured."""
        V = np.asarray(vertices, np.float32)
        N = np.asarray(normals, np.float32)
        X, NX = np.ascontiguousarray(V.T), np.ascontiguousarray(N.T)  # (3, n): R @ X is ten times V @ R.T's speed
        num = np.zeros(len(V), np.float64)
        den = np.zeros(len(V), np.float64)
        cos_min = math.cos(math.radians(self.stats.max_incidence_deg))
        for z, K, extrinsic in self._snap_views:
            R, t = extrinsic[:3, :3].astype(np.float32), extrinsic[:3, 3].astype(np.float32)
            fx, fy, cx, cy = (np.float32(x) for x in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            P = R @ X + t[:, None]
            front = P[2] > 1e-6
            zc = np.where(front, P[2], np.float32(1))
            u = np.rint(fx * P[0] / zc + cx).astype(np.int32)
            v = np.rint(fy * P[1] / zc + cy).astype(np.int32)
            idx = np.flatnonzero(front & (u >= 0) & (v >= 0) & (u < z.shape[1]) & (v < z.shape[0]))
            zm = z[v[idx], u[idx]]
            seen = zm > 0
            idx, zm = idx[seen], zm[seen]
            u, v, Pi = u[idx], v[idx], P[:, idx]
            q = np.stack([(u - cx) / fx * zm, (v - cy) / fy * zm, zm])
            n_cam = R @ NX[:, idx]
            offset = np.einsum("ij,ij->j", q - Pi, n_cam)  # the measured point's offset along the normal
            cos = np.abs(np.einsum("ij,ij->j", Pi, n_cam)) / np.linalg.norm(Pi, axis=0)
            ok = (np.abs(offset) < self.truncation_m) & (cos > cos_min)
            w = 1.0 / np.square(self.stats.sigma(zm[ok]).astype(np.float64))
            num += np.bincount(idx[ok], w * offset[ok], len(V))
            den += np.bincount(idx[ok], w, len(V))
        has = den > 0
        shift = np.zeros(len(V), np.float32)
        shift[has] = num[has] / den[has]
        return V + N * shift[:, None], float(100.0 * has.mean()) if len(V) else 0.0

    def vertex_colours(self, vertices: np.ndarray) -> np.ndarray | None:
        """(V, 3) uint8 colours: each vertex takes the colour of the first kept frame that measured it (its
        depth there within the truncation); None when no frame had colour."""
        if not self._views:
            return None
        out = np.zeros((len(vertices), 3), np.uint8)
        todo = np.ones(len(vertices), bool)
        vertices = np.asarray(vertices, np.float32)
        pick = np.unique(np.linspace(0, len(self._views) - 1, min(COLOUR_VIEWS, len(self._views))).round().astype(int))
        for i in pick:
            rgb, z, K, extrinsic, step = self._views[i]
            idx = np.flatnonzero(todo)
            if idx.size == 0:
                break
            P = vertices[idx] @ extrinsic[:3, :3].T.astype(np.float32) + extrinsic[:3, 3].astype(np.float32)
            front = P[:, 2] > 1e-6
            u = np.rint((K[0, 0] * P[:, 0] / np.where(front, P[:, 2], 1) + K[0, 2]) / step).astype(np.int64)
            v = np.rint((K[1, 1] * P[:, 1] / np.where(front, P[:, 2], 1) + K[1, 2]) / step).astype(np.int64)
            ok = front & (u >= 0) & (v >= 0) & (u < z.shape[1]) & (v < z.shape[0])
            ok[ok] &= np.abs(z[v[ok], u[ok]] - P[ok, 2]) <= self.truncation_m
            out[idx[ok]] = rgb[v[ok], u[ok]]
            todo[idx[ok]] = False
        return out

    def surface_weights(self) -> np.ndarray:
        """Weights (frames) of a sample of the voxels within half the truncation of the surface."""
        if self._grid is None:
            return np.empty(0, np.float32)
        # every 7th voxel: the median and the share seen once are the same, for a seventh of the reading
        tsdf = self._grid.attribute("tsdf").numpy().reshape(-1)[::7]
        weight = self._grid.attribute("weight").numpy().reshape(-1)[::7]
        near = (weight > 0) & (np.abs(tsdf) < 0.5)
        return np.asarray(weight[near], np.float32)

    def mesh(self) -> tuple[o3d.geometry.TriangleMesh, dict[str, Any]]:
        """The supported zero level as a mesh, and what was done (counts, thresholds)."""
        if self._grid is None:
            raise ReconstructionError("nothing to mesh: no frame kept any depth pixel")
        weights = self.surface_weights()
        min_frames = self.settings.min_frames or support_frames(weights)
        # Open3D keeps a cube whose corners' weights all exceed the threshold
        mesh = self._grid.extract_triangle_mesh(weight_threshold=min_frames - 0.5).to_legacy()
        if len(mesh.triangles) == 0:
            raise ReconstructionError(f"no surface was measured by {min_frames} frames")
        snapped_pct = None
        if self._snap_views:
            mesh.compute_vertex_normals()
            moved, snapped_pct = self.snap(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals))
            mesh.vertices = o3d.utility.Vector3dVector(moved.astype(np.float64))
        colours = self.vertex_colours(np.asarray(mesh.vertices))
        if colours is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(colours.astype(np.float64) / 255.0)
        info = {"method": "measured", "voxel_size_m": self.voxel_size_m, "truncation_m": self.truncation_m,
                "depth_range_m": [self.min_depth_m, self.max_depth_m], "min_frames": int(min_frames),
                "visits": {"median": float(np.median(weights)) if weights.size else 0.0,
                           "seen_once_pct": float(100 * np.mean(weights < 1.5)) if weights.size else 0.0},
                "frames": self.frames, "pixels_kept_pct": 100.0 * self.pixels_kept / max(self.pixels_in, 1),
                "blocks": int(self._grid.hashmap().size())}
        if snapped_pct is not None:
            info["snap"] = {"frames": len(self._snap_views), "vertices_measured_pct": snapped_pct}
        return mesh, info


def _crop(z: np.ndarray, frame: PosedDepth, region: Region) -> np.ndarray:
    v, u = np.nonzero(z)
    zz = z[v, u]
    it = frame.intrinsics
    P = np.stack([(u - it.ppx) / it.fx * zz, (v - it.ppy) / it.fy * zz, zz], 1)
    W = P @ frame.T_world_cam[:3, :3].T + frame.T_world_cam[:3, 3]
    out = ~region.contains(W)
    z = z.copy()
    z[v[out], u[out]] = 0.0
    return z


def open_share(vertices: np.ndarray, centre: np.ndarray, radius: float, height: float, bin_m: float) -> float:
    """Percentage of the envelope cylinder's side and top (cells ``bin_m`` a side) holding no mesh vertex."""
    rel = vertices - np.asarray(centre, float)
    ang = np.arctan2(rel[:, 1], rel[:, 0])
    n_ang = max(int(round(2 * math.pi * radius / bin_m)), 8)
    n_z = max(int(round(height / bin_m)), 1)
    inside = (np.abs(rel[:, 2]) <= height / 2) & (np.hypot(rel[:, 0], rel[:, 1]) <= radius)
    ai = np.clip(((ang + math.pi) / (2 * math.pi) * n_ang).astype(int), 0, n_ang - 1)
    zi = np.clip(((rel[:, 2] + height / 2) / height * n_z).astype(int), 0, n_z - 1)
    side = np.zeros((n_ang, n_z), bool)
    side[ai[inside], zi[inside]] = True
    n_top = max(int(round(2 * radius / bin_m)), 1)
    xi = np.clip(((rel[:, 0] + radius) / (2 * radius) * n_top).astype(int), 0, n_top - 1)
    yi = np.clip(((rel[:, 1] + radius) / (2 * radius) * n_top).astype(int), 0, n_top - 1)
    top = np.zeros((n_top, n_top), bool)
    top[xi[inside], yi[inside]] = True
    gx, gy = np.meshgrid((np.arange(n_top) + 0.5) / n_top * 2 - 1, (np.arange(n_top) + 0.5) / n_top * 2 - 1,
                         indexing="ij")
    disc = gx**2 + gy**2 <= 1
    side_area, top_area = 2 * math.pi * radius * height, math.pi * radius**2
    open_side = 1.0 - side.mean()  # cells (azimuth, height) with no surface along their ray
    open_top = 1.0 - (top & disc).sum() / max(int(disc.sum()), 1)
    return float(100.0 * (open_side * side_area + open_top * top_area) / (side_area + top_area))


__all__ = ["METHODS", "MeasuredSurface", "SurfaceSettings", "clean_depth", "open_share", "support_frames"]
