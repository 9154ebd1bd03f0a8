"""Voxel support of the fused cloud: which voxels enough frames and viewing directions saw (docs/processing.md
section 3, step 1), with the in-view test behind the adaptive support and the borrowed (neighbourhood, cell)
support. Split out of :mod:`darp.reconstruction.fusion`, which re-exports these names."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.voxel_stats import VoxelStats, cell_keys, pack_keys, popcount64, unpack_keys

if TYPE_CHECKING:
    from darp.reconstruction.fusion import FusionSettings


@dataclass(frozen=True, eq=False)
class FrameView:
    """What the in-view test keeps of a fused frame: its pose and a subsampled metric depth image."""

    arm_bit: int
    R_cam_world: np.ndarray  # (3, 3)
    t_cam_world: np.ndarray  # (3,)
    centre: np.ndarray  # (3,) camera centre, world
    fx: float
    fy: float
    ppx: float
    ppy: float  # of the subsampled image
    depth_m: np.ndarray  # (h, w) float32, 0 = no depth
    stride: int = 1  # the subsampling: full-resolution focal length = fx * stride

    @classmethod
    def of(cls, frame: PosedDepth, arm_bit: int, stride: int) -> FrameView:
        from darp.reconstruction.backproject import depth_to_metres

        T = np.asarray(frame.T_world_cam, np.float64)
        R = T[:3, :3].T
        k = frame.intrinsics
        return cls(arm_bit, R, -R @ T[:3, 3], T[:3, 3].copy(), k.fx / stride, k.fy / stride,
                   (k.ppx + 0.5) / stride - 0.5, (k.ppy + 0.5) / stride - 0.5,
                   np.ascontiguousarray(depth_to_metres(frame.depth, frame.depth_scale)[::stride, ::stride]), stride)


def in_view(points: np.ndarray, views: Iterable[FrameView], tolerance_m: float, arm_bits: int = 0xFF,
            normals: np.ndarray | None = None, voxel_size_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each point (N, 3): how many of ``views`` (of the arms in ``arm_bits``) had it in view, and the
    viewing-direction bins (uint64 mask) of those views (see the module docstring).

    With ``voxel_size_m`` a frame counts by the chance that one of its pixels lands in the voxel: the
    voxel's footprint in pixels, ``(voxel_size_m * fx / z)^2``, foreshortened by the angle between the
    voxel's ``normals`` and the direction to the camera (at least 0.2), at most 1. A low-resolution
    frame whose pixels are about the voxel's size does not hit every voxel it sees.
    """
    from darp.reconstruction.voxel_stats import view_bins

    p = np.asarray(points, np.float64)
    count = np.zeros(len(p), np.float64)
    bins = np.zeros(len(p), np.uint64)
    for view in views:
        if not (arm_bits >> view.arm_bit) & 1:
            continue
        cam = p @ view.R_cam_world.T + view.t_cam_world
        z = cam[:, 2]
        h, w = view.depth_m.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(view.fx * cam[:, 0] / z + view.ppx)
            v = np.rint(view.fy * cam[:, 1] / z + view.ppy)
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx = np.flatnonzero(inside)
        d = view.depth_m[v[idx].astype(np.int64), u[idx].astype(np.int64)]
        seen = idx[(d > 0) & (z[idx] <= d + tolerance_m)]
        if voxel_size_m is None:
            count[seen] += 1.0
        elif seen.size:
            footprint = (voxel_size_m * view.fx * view.stride / z[seen]) ** 2
            if normals is not None:
                to_camera = view.centre - p[seen]
                cos = np.abs(np.einsum("ij,ij->i", normals[seen], to_camera)) / np.linalg.norm(to_camera, axis=1)
                footprint = footprint * np.maximum(cos, 0.2)
            count[seen] += np.minimum(footprint, 1.0)
        if seen.size:
            bins[seen] |= np.left_shift(np.uint64(1), view_bins(view.centre - p[seen]).astype(np.uint64))
    return count, bins


VisibilityFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``visibility(centres (N, 3), unit normals (N, 3)) -> (frames expected to hit each voxel, bins in view)``."""


def mean_normals(sum_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit mean normals from summed normals (N, 3) and whether each has one (a zero sum has none: zeros)."""
    length = np.linalg.norm(sum_normal, axis=1)
    has = length > 0
    return sum_normal / np.where(has, length, 1.0)[:, None], has


def neighbourhood_support(stats: VoxelStats, radius: int,
                          plane_voxels: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel, lower bounds of the support of the ``(2 radius + 1)^3`` voxels around it: the most frames
    any of them saw (so at least that many distinct frames saw the neighbourhood) and the union of their
    viewing-direction bins (exact). ``radius`` 0 returns the voxel's own.

    ``plane_voxels`` > 0 keeps only the neighbours whose centre lies within that many voxels of the voxel's
    tangent plane (the plane through it normal to its mean normal). Depth noise spreads a surface over
    layers along the normal; a cube lends an off-surface voxel the support of the surface voxel beside it
    and keeps the noise layer, the tangent plane lends support only along the surface (holes where
    frames thinned out). A voxel without a normal keeps its own support."""
    frames = stats.n_frames.copy()
    bins = stats.view_mask.copy()
    if radius <= 0 or len(stats) == 0:
        return frames, bins
    ijk = unpack_keys(stats.keys)
    normals = None
    if plane_voxels > 0:
        unit, has = mean_normals(stats.sum_normal)
        normals = np.where(has[:, None], unit, np.nan)
    r = range(-radius, radius + 1)
    for offset in [(i, j, k) for i in r for j in r for k in r if (i, j, k) != (0, 0, 0)]:
        keys = pack_keys(ijk + np.array(offset, np.int64))
        pos = np.minimum(np.searchsorted(stats.keys, keys), len(stats) - 1)
        found = stats.keys[pos] == keys
        if normals is not None:
            found &= np.abs(normals @ np.asarray(offset, np.float64)) <= plane_voxels  # NaN (no normal): False
        frames[found] = np.maximum(frames[found], stats.n_frames[pos[found]])
        bins[found] |= stats.view_mask[pos[found]]
    return frames, bins


def supported_voxels(stats: VoxelStats, settings: FusionSettings, visibility: VisibilityFn | None = None,
                     counts: dict[str, int] | None = None, cells: VoxelStats | None = None) -> np.ndarray:
    """Boolean (M,): the voxels with enough support (fixed counts, or adapted with ``visibility``), counted
    over each voxel's neighbourhood with ``support_neighbourhood`` and, with ``cells`` (the same frames'
    :func:`~darp.reconstruction.voxel_stats.cell_stats` at ``support_cell_voxels``), over the cell that holds
    it (both for the voxels at least ``neighbourhood_own_frames`` frames saw; the others keep their own
    counts). With ``neighbourhood_holes_only`` a voxel kept only through such borrowed support is dropped
    again where a voxel of its own support lies that close along its normal (:func:`second_layer`)."""
    borrows = settings.support_neighbourhood > 0 or cells is not None
    if not borrows or settings.neighbourhood_holes_only <= 0:
        return _supported(stats, settings, visibility, counts, cells)
    own = _supported(stats, dataclasses.replace(settings, support_neighbourhood=0), visibility)
    borrowed = _supported(stats, settings, visibility, counts, cells) & ~own
    layer = second_layer(stats, own, np.flatnonzero(borrowed), settings.neighbourhood_holes_only)
    if counts is not None:
        counts["second_layer"] = int(layer.sum())
    keep = own.copy()
    keep[np.flatnonzero(borrowed)[~layer]] = True
    return keep


def second_layer(stats: VoxelStats, own: np.ndarray, idx: np.ndarray, depth_voxels: int) -> np.ndarray:
    """Boolean (len(idx),): voxels ``idx`` that have an ``own``-supported voxel within ``depth_voxels`` voxels
    along their mean normal, either way (a surface seen twice, offset by pose or depth error, not a hole)."""
    hit = np.zeros(idx.size, bool)
    if idx.size == 0:
        return hit
    normals, has = mean_normals(stats.sum_normal[idx])
    ijk = unpack_keys(stats.keys[idx])
    for step in range(1, depth_voxels + 1):
        for sign in (1.0, -1.0):
            keys = pack_keys(ijk + np.rint(sign * step * normals).astype(np.int64))
            pos = np.minimum(np.searchsorted(stats.keys, keys), len(stats) - 1)
            hit |= (stats.keys[pos] == keys) & own[pos] & has
    return hit


def _supported(stats: VoxelStats, settings: FusionSettings, visibility: VisibilityFn | None = None,
               counts: dict[str, int] | None = None, cells: VoxelStats | None = None) -> np.ndarray:
    """:func:`supported_voxels` without the hole rule."""
    n_frames, view_mask = neighbourhood_support(stats, settings.support_neighbourhood,
                                                settings.neighbourhood_plane_voxels)
    if cells is not None and len(cells) and len(stats):
        keys = cell_keys(stats.keys, settings.support_cell_voxels)
        pos = np.minimum(np.searchsorted(cells.keys, keys), len(cells) - 1)
        found = cells.keys[pos] == keys
        n_frames = np.where(found, np.maximum(n_frames, cells.n_frames[pos]), n_frames)
        view_mask = np.where(found, view_mask | cells.view_mask[pos], view_mask)
    borrows = settings.support_neighbourhood > 0 or cells is not None
    if borrows and settings.neighbourhood_own_frames > 1:
        # a voxel only one frame hit is where noise scatters: it keeps its own count
        alone = stats.n_frames < settings.neighbourhood_own_frames
        n_frames = np.where(alone, stats.n_frames, n_frames)
        view_mask = np.where(alone, stats.view_mask, view_mask)
    if borrows:
        stats = dataclasses.replace(stats, n_frames=n_frames, view_mask=view_mask)
    n_views = popcount64(stats.view_mask)
    fixed = (stats.n_frames >= settings.min_frames) & (n_views >= settings.min_view_bins)
    if visibility is None or not settings.adaptive_support:
        return fixed
    floor = min(settings.min_frames_floor, settings.min_frames)
    candidate = ~fixed & (stats.n_frames >= floor)
    idx = np.flatnonzero(candidate)
    if idx.size == 0:
        return fixed
    centres = stats.sum_xyz[idx] / stats.n_points[idx].astype(np.float64)[:, None]
    normals, _ = mean_normals(stats.sum_normal[idx])
    visible, visible_bins = visibility(centres, normals)
    frames = stats.n_frames[idx]
    frames_ok = (frames >= settings.min_frames) | (frames >= np.ceil(settings.support_fraction * visible))
    bins_ok = n_views[idx] >= np.minimum(settings.min_view_bins, np.maximum(popcount64(visible_bins), 1))
    supported = fixed.copy()
    supported[idx] = frames_ok & bins_ok
    if counts is not None:
        counts["adapted"] = int((frames_ok & bins_ok).sum())
    return supported


__all__ = ["FrameView", "VisibilityFn", "in_view", "mean_normals", "neighbourhood_support", "second_layer",
           "supported_voxels"]
