"""Measured-surface fusion: keyframes of both arms -> supported voxels -> per-arm and fused clouds.

Every keyframe is back-projected with its own eq. 1 pose (:mod:`darp.reconstruction.backproject`),
cropped to the object envelope, and reduced to per-voxel statistics that are merged as frames stream
in (memory grows with the observed surface, not with the number of frames). At the end, per arm and
for both arms together:

1. **voxel support**: a voxel is kept if at least ``min_frames`` distinct frames and
   ``min_view_bins`` distinct viewing-direction bins (64 bins on the sphere, ~25 deg apart) saw it;
   isolated and single-view measurements (flying pixels, multipath, one bad frame) fall out. With
   ``adaptive_support`` the count asked is adapted to how often the voxel was *in view*: a voxel is
   in view of a fused frame when it projects into the image, in front of the camera, no more than
   ``visibility_tolerance_m`` behind that frame's measured depth there (not occluded, not in a hole).
   A voxel seen by fewer than ``min_frames`` frames is still kept when at least ``min_frames_floor``
   frames saw it and they are at least ``support_fraction`` of the frames it was in view of; and the
   view bins asked are never more than the bins it was in view from. A sparse survey (one view per
   arm, a corner seen by two frames) keeps what every frame that could see it confirmed; a voxel that
   most frames looking at it did not measure still goes;
2. each kept voxel becomes one point: the mean of its points, colours and camera-oriented normals;
3. statistical outlier removal: points whose mean distance to their ``sor_neighbours`` nearest
   neighbours exceeds the cloud's mean of that distance by ``sor_std_ratio`` standard deviations go;
4. a local surface fit: each point moves along its normal onto the weighted mean plane of its
   neighbours within ``surface_fit_radius_voxels`` voxels, which collapses the noise layer; points
   that then share a voxel are merged.

No ICP, no centroid alignment: the two arms meet where their calibrated poses put them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import ReconstructionError
from darp.formats.envelope import Envelope
from darp.reconstruction.backproject import DepthFilterSettings, FrameCloud, PosedDepth, Region, backproject
from darp.reconstruction.cloud_filters import fit_to_local_surface, statistical_outliers
from darp.reconstruction.cloud_io import write_cloud_ply
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.voxel_stats import (
    VoxelStats,
    cell_stats,
    frame_stats,
    merge_stats,
    pack_keys,
    popcount64,
    unpack_keys,
    voxel_indices,
)
from darp.reconstruction.voxel_support import (
    FrameView,
    VisibilityFn,
    in_view,
    mean_normals,
    neighbourhood_support,
    second_layer,
    supported_voxels,
)

ARM_COLOURS = {"arm110": (220, 40, 40), "arm111": (40, 70, 220)}


@dataclass(frozen=True)
class FusionSettings:
    """Every fusion parameter; defaults and reasons in docs/processing.md."""

    depth: DepthFilterSettings = field(default_factory=DepthFilterSettings)
    voxel_size_m: float = 0.0015  # 1.5 mm: ~1.6 pixel footprints at 0.35 m; several points per frame
    min_frames: int = 3  # distinct frames that must see a voxel
    min_view_bins: int = 2  # distinct viewing-direction bins that must see a voxel
    envelope_margin_m: float = 0.01  # envelope crop: radial and top margin (at least; see calibration_margin_factor)
    calibration_margin_factor: float = 2.0  # ... and at least this times the calibration's held-out p90 error
    table_margin_m: float = 0.003  # envelope crop: kept only above table + this (at least; see next)
    table_calibration_factor: float = 1.5  # ... and at least this times the calibration's held-out p90 error
    sor_neighbours: int = 20  # statistical outlier removal: neighbours per point (0 = off)
    sor_std_ratio: float = 2.0  # ... and the tolerated excess of the mean neighbour distance, in std
    sor_local_ratio: float = 0.0  # > 0: SOR spares a point not sparser than this x its neighbours' median (0 = off)
    surface_fit_radius_voxels: float = 1.5  # local plane fit along the normal (0 = off), in voxels
    surface_fit_neighbours: int = 16  # at most this many neighbours enter a plane fit
    merge_rows: int = 400_000  # pending per-frame voxel rows merged into the state beyond this
    adaptive_support: bool = True  # adapt the support asked to how often the voxel was in view (module doc)
    min_frames_floor: int = 2  # ... but never fewer frames than this
    support_fraction: float = 0.5  # ... and at least this fraction of the frames it was in view of
    visibility_tolerance_m: float = 0.01  # in view: not more than this behind the frame's measured depth
    visibility_stride_px: int = 4  # the in-view test reads every n-th depth pixel (memory: ~W*H/n^2 per frame)
    support_neighbourhood: int = 0  # count support over the (2n+1)^3 voxels around each voxel (0 = the voxel alone)
    neighbourhood_own_frames: int = 1  # ... only for voxels that at least this many frames saw themselves
    neighbourhood_plane_voxels: float = 0.0  # > 0: ... only from neighbours within this many voxels of the
    # voxel's tangent plane (its mean normal), so support spreads along the surface, not onto the noise layer
    support_cell_voxels: int = 1  # > 1: a voxel also counts the distinct frames and bins of the cell of this
    # many voxels a side that holds it (frames whose hits scattered over the cell's voxels; borrowed support)
    neighbourhood_holes_only: int = 0  # > 0: borrowed support only fills holes: a voxel with a voxel of its own
    # support within this many voxels along its normal is a second layer of that surface and is not kept
    arm_support_from_fused: int = 0  # an arm's cloud also keeps voxels the fused cloud supports that this many
    # of the arm's own frames saw (0 = off: each arm's cloud needs the support from its own frames alone)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.voxel_size_m) and 1e-4 <= self.voxel_size_m <= 0.1):
            raise ReconstructionError(f"voxel_size_m must be within 0.1 mm .. 10 cm, got {self.voxel_size_m}")
        if self.min_frames < 1 or self.min_view_bins < 1:
            raise ReconstructionError("min_frames and min_view_bins must be >= 1")
        if self.sor_neighbours < 0 or self.sor_std_ratio <= 0:
            raise ReconstructionError("sor_neighbours must be >= 0 and sor_std_ratio > 0")
        if not (math.isfinite(self.sor_local_ratio) and (self.sor_local_ratio == 0 or self.sor_local_ratio >= 1)):
            raise ReconstructionError(f"sor_local_ratio must be 0 (off) or >= 1, got {self.sor_local_ratio}")
        if self.surface_fit_radius_voxels < 0 or self.surface_fit_neighbours < 2:
            raise ReconstructionError("surface_fit_radius_voxels must be >= 0 and surface_fit_neighbours >= 2")
        if self.merge_rows < 1:
            raise ReconstructionError("merge_rows must be >= 1")
        if not (self.calibration_margin_factor >= 0 and self.envelope_margin_m >= 0 and self.table_margin_m >= 0
                and self.table_calibration_factor >= 0):
            raise ReconstructionError("envelope_margin_m, table_margin_m, calibration_margin_factor and "
                                      "table_calibration_factor must be >= 0")
        if self.arm_support_from_fused < 0:
            raise ReconstructionError("arm_support_from_fused must be >= 0")
        if self.neighbourhood_own_frames < 1:
            raise ReconstructionError(f"neighbourhood_own_frames must be >= 1, got {self.neighbourhood_own_frames}")
        if not (math.isfinite(self.neighbourhood_plane_voxels) and self.neighbourhood_plane_voxels >= 0):
            raise ReconstructionError(
                f"neighbourhood_plane_voxels must be >= 0 (0 = the whole cube), got {self.neighbourhood_plane_voxels}")
        if not 1 <= self.support_cell_voxels <= 4:
            raise ReconstructionError(f"support_cell_voxels must be 1 (off) .. 4, got {self.support_cell_voxels}")
        if not 0 <= self.neighbourhood_holes_only <= 3:
            raise ReconstructionError(
                f"neighbourhood_holes_only must be 0 (off) .. 3 voxels, got {self.neighbourhood_holes_only}")
        if not 0 <= self.support_neighbourhood <= 2:
            raise ReconstructionError(f"support_neighbourhood must be 0, 1 or 2, got {self.support_neighbourhood}")
        if not (self.min_frames_floor >= 1 and 0 < self.support_fraction <= 1 and self.visibility_tolerance_m > 0
                and self.visibility_stride_px >= 1):
            raise ReconstructionError("min_frames_floor and visibility_stride_px must be >= 1, support_fraction "
                                      "in (0, 1] and visibility_tolerance_m > 0")

    def crop(self, envelope: Envelope, table_z_m: float | None = None,
             calibration_uncertainty_m: float | None = None) -> EnvelopeCrop:
        """The envelope crop with this fusion's margins: the radial, top and table margins grow with the
        calibration's stated uncertainty (:func:`calibration_uncertainty_m`) when it is given."""
        return EnvelopeCrop.from_envelope(envelope, table_z_m=table_z_m,
                                          margin_m=self.crop_margin(calibration_uncertainty_m),
                                          table_margin_m=self.crop_table_margin(calibration_uncertainty_m))

    def crop_table_margin(self, calibration_uncertainty_m: float | None = None) -> float:
        """``table_margin_m``, or ``table_calibration_factor`` x the calibration's uncertainty if larger.

        The table plane of the crop is the calibrated world's z = table height; a calibration off by a few
        millimetres puts the real table that far above it in some views, and those table points would be
        fused and held out as object surface (the paper profile's heavy held-out tail)."""
        if calibration_uncertainty_m is None or not math.isfinite(calibration_uncertainty_m):
            return self.table_margin_m
        return max(self.table_margin_m, self.table_calibration_factor * float(calibration_uncertainty_m))

    def crop_margin(self, calibration_uncertainty_m: float | None = None) -> float:
        """``envelope_margin_m``, or ``calibration_margin_factor`` x the calibration's uncertainty if larger."""
        if calibration_uncertainty_m is None or not math.isfinite(calibration_uncertainty_m):
            return self.envelope_margin_m
        return max(self.envelope_margin_m, self.calibration_margin_factor * float(calibration_uncertainty_m))


def calibration_uncertainty_m(residuals_by_arm: Iterable[dict[str, Any]]) -> float | None:
    """The calibration's stated uncertainty: the largest held-out p90 corner error over the arms (metres)
    from ``residuals.heldout.corner_3d_mm`` (written by ``darp calib solve``); None when none states it."""
    worst = None
    for residuals in residuals_by_arm:
        held = residuals.get("heldout") if isinstance(residuals, dict) else None
        corner = held.get("corner_3d_mm") if isinstance(held, dict) else None
        p90 = corner.get("p90") if isinstance(corner, dict) else None
        if isinstance(p90, (int, float)) and math.isfinite(p90) and 0 <= p90 < 1e4:
            worst = max(worst or 0.0, float(p90) / 1000.0)
    return worst


@dataclass(frozen=True, eq=False)
class VoxelCloud:
    """A fused point cloud: one point per supported voxel, with how it was supported."""

    points: np.ndarray  # (N, 3) float32 world, metres
    normals: np.ndarray  # (N, 3) float32 unit, toward the cameras that saw the voxel
    colours: np.ndarray | None  # (N, 3) uint8 RGB
    n_points: np.ndarray  # (N,) int32 observations averaged
    n_frames: np.ndarray  # (N,) int32 distinct frames
    n_views: np.ndarray  # (N,) int32 distinct viewing-direction bins
    arm_mask: np.ndarray  # (N,) uint8 bit i: arm ``arms[i]`` saw the voxel
    voxel_ijk: np.ndarray  # (N, 3) int64 voxel coordinates
    arms: tuple[str, ...]  # arm names by bit

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def seen_by(self, arm: str) -> np.ndarray:
        """Boolean (N,): the points of voxels that ``arm`` saw."""
        if arm not in self.arms:
            return np.zeros(len(self), bool)
        return (self.arm_mask & np.uint8(1 << self.arms.index(arm))) > 0

    def select(self, keep: np.ndarray) -> VoxelCloud:
        return VoxelCloud(self.points[keep], self.normals[keep],
                          None if self.colours is None else self.colours[keep], self.n_points[keep],
                          self.n_frames[keep], self.n_views[keep], self.arm_mask[keep], self.voxel_ijk[keep],
                          self.arms)


@dataclass(frozen=True, eq=False)
class FusionResult:
    """The fused cloud of both arms, each arm's own partial cloud, and counts of what happened."""

    fused: VoxelCloud
    per_arm: dict[str, VoxelCloud]
    settings: FusionSettings
    stats: dict[str, Any]
    stages: dict[str, np.ndarray] | None = None  # with ``result(keep_stages=True)``: see :meth:`VoxelFusion.result`

    def to_dict(self) -> dict[str, Any]:
        """Settings and counts (frames, points in, voxels, supported, after SOR, points out), for JSON."""
        return {"settings": dataclasses.asdict(self.settings), "counts": self.stats,
                "points": {"fused": len(self.fused), **{arm: len(c) for arm, c in self.per_arm.items()}}}


def cloud_from_stats(stats: VoxelStats, settings: FusionSettings, arms: tuple[str, ...],
                     counts: dict[str, int] | None = None, visibility: VisibilityFn | None = None,
                     also_keys: np.ndarray | None = None, supported: np.ndarray | None = None,
                     stages: dict[str, np.ndarray] | None = None, cells: VoxelStats | None = None) -> VoxelCloud:
    """Apply voxel support, average each voxel and remove statistical outliers. ``also_keys`` (sorted voxel
    keys, e.g. those the fused cloud supports) are kept too where ``arm_support_from_fused`` frames saw them.
    ``supported`` is :func:`supported_voxels`' answer when the caller already has it. ``stages`` (a dict)
    receives the points after each step: ``in_envelope`` (every voxel's mean), ``supported``, ``after_sor``."""
    n_views = popcount64(stats.view_mask)
    if supported is None:
        supported = supported_voxels(stats, settings, visibility, counts, cells)
    if also_keys is not None and also_keys.size and len(stats) and settings.arm_support_from_fused > 0:
        pos = np.minimum(np.searchsorted(also_keys, stats.keys), also_keys.size - 1)
        confirmed = (also_keys[pos] == stats.keys) & (stats.n_frames >= settings.arm_support_from_fused)
        if counts is not None:
            counts["from_fused"] = int((confirmed & ~supported).sum())
        supported = supported | confirmed
    kept = stats.select(supported)
    n = kept.n_points.astype(np.float64)[:, None]
    points = (kept.sum_xyz / n).astype(np.float32)
    normals = mean_normals(kept.sum_normal)[0].astype(np.float32)
    colours = None if kept.sum_rgb is None else np.clip(np.rint(kept.sum_rgb / n), 0, 255).astype(np.uint8)
    cloud = VoxelCloud(points, normals, colours, kept.n_points.astype(np.int32), kept.n_frames,
                       n_views[supported], kept.arm_mask, unpack_keys(kept.keys), arms)
    inliers = statistical_outliers(points, settings.sor_neighbours, settings.sor_std_ratio, settings.sor_local_ratio)
    if stages is not None:
        stages["in_envelope"] = (stats.sum_xyz / np.maximum(stats.n_points, 1)[:, None]).astype(np.float32)
        stages["supported"] = points
        stages["after_sor"] = points[inliers]
    if counts is not None:
        counts.update(voxels=len(stats), supported=int(supported.sum()), after_sor=int(inliers.sum()))
    cloud = cloud.select(inliers)
    radius = settings.surface_fit_radius_voxels * settings.voxel_size_m
    fitted = fit_to_local_surface(cloud.points, cloud.normals, cloud.n_points, radius,
                                  settings.surface_fit_neighbours)
    merged = merge_coincident(dataclasses.replace(cloud, points=fitted), settings.voxel_size_m)
    if counts is not None:
        counts["points"] = len(merged)
    return merged


def merge_coincident(cloud: VoxelCloud, voxel_size_m: float) -> VoxelCloud:
    """Merge points that share a voxel after the surface fit (weighted by their observation counts).

    Noise spreads a surface over two voxel layers; once the fit has put both layers' means on the
    surface they nearly coincide, and near-duplicate points make ball pivoting leave holes.
    """
    if len(cloud) == 0:
        return cloud
    ijk = voxel_indices(cloud.points, voxel_size_m)
    keys, first, inverse = np.unique(pack_keys(ijk), return_index=True, return_inverse=True)
    if keys.size == len(cloud):
        return dataclasses.replace(cloud, voxel_ijk=ijk)
    m = keys.size
    w = cloud.n_points.astype(np.float64)
    total = np.bincount(inverse, weights=w, minlength=m)

    def weighted(values: np.ndarray) -> np.ndarray:
        return np.column_stack([np.bincount(inverse, weights=w * values[:, j], minlength=m)
                                for j in range(values.shape[1])])

    points = (weighted(cloud.points.astype(np.float64)) / total[:, None]).astype(np.float32)
    normal_sum = weighted(cloud.normals.astype(np.float64))
    normals = (normal_sum / np.maximum(np.linalg.norm(normal_sum, axis=1), 1e-12)[:, None]).astype(np.float32)
    colours = None
    if cloud.colours is not None:
        colours = np.clip(np.rint(weighted(cloud.colours.astype(np.float64)) / total[:, None]), 0, 255)
        colours = colours.astype(np.uint8)
    order = np.argsort(inverse, kind="stable")
    starts = np.searchsorted(inverse[order], np.arange(m))
    return VoxelCloud(
        points=points, normals=normals, colours=colours,
        n_points=np.rint(total).astype(np.int32),
        n_frames=np.maximum.reduceat(cloud.n_frames[order], starts),
        n_views=np.maximum.reduceat(cloud.n_views[order], starts),
        arm_mask=np.bitwise_or.reduceat(cloud.arm_mask[order], starts),
        voxel_ijk=ijk[first], arms=cloud.arms,
    )


class VoxelFusion:
    """Streaming accumulator: add frames (any order, both arms), then :meth:`result`."""

    def __init__(self, settings: FusionSettings | None = None, region: Region | None = None) -> None:
        self.settings = settings or FusionSettings()
        self.region = region
        self.arms: list[str] = []
        self._state: dict[str, VoxelStats] = {}
        self._pending: dict[str, list[VoxelStats]] = {}
        self._cells: dict[str, list[VoxelStats]] = {}  # per-frame cell statistics (support_cell_voxels > 1)
        self._pending_rows = 0
        self._seen: set[tuple[str, int]] = set()
        self._colour: bool | None = None
        self.points_in: dict[str, int] = {}
        self.peak_rows = 0
        self.views: list[FrameView] = []  # for the adaptive support's in-view test

    @property
    def frames(self) -> dict[str, int]:
        """Frames added, per arm."""
        out: dict[str, int] = {}
        for arm, _ in self._seen:
            out[arm] = out.get(arm, 0) + 1
        return out

    @property
    def rows(self) -> int:
        """Voxel rows held (state and pending): the accumulator's memory in rows."""
        return sum(len(s) for s in self._state.values()) + self._pending_rows

    def add(self, frame: PosedDepth, region: Region | None = None) -> int:
        """Back-project, filter and accumulate one frame; returns the number of points it added.
        ``region``: this frame's own region instead of the fusion's (e.g. its fitted table crop)."""
        self._check_new(frame.arm, frame.frame_id)
        cloud = backproject(frame, self.settings.depth, self.region if region is None else region)
        added = self._accumulate(frame.arm, frame.frame_id, cloud)
        if self.settings.adaptive_support:
            self.views.append(FrameView.of(frame, self.arms.index(frame.arm), self.settings.visibility_stride_px))
        return added

    def add_cloud(self, arm: str, frame_id: int, cloud: FrameCloud) -> int:
        """Accumulate an already back-projected (and filtered) frame."""
        self._check_new(arm, frame_id)
        return self._accumulate(arm, frame_id, cloud)

    def _check_new(self, arm: str, frame_id: int) -> None:
        if (arm, int(frame_id)) in self._seen:
            raise ReconstructionError(f"frame {frame_id} of {arm} was already fused")

    def _accumulate(self, arm: str, frame_id: int, cloud: FrameCloud) -> int:
        self._seen.add((arm, int(frame_id)))
        if arm not in self.arms:
            if len(self.arms) == 8:
                raise ReconstructionError("fusion supports at most 8 arms")
            self.arms.append(arm)
        with_colour = cloud.colours is not None
        if self._colour is None:
            self._colour = with_colour
        elif self._colour != with_colour and len(cloud):
            raise ReconstructionError(f"frame {frame_id} of {arm}: mixing frames with and without colour")
        self.points_in[arm] = self.points_in.get(arm, 0) + len(cloud)
        if len(cloud) == 0:
            return 0
        stats = frame_stats(cloud.points, cloud.normals, cloud.colours, cloud.camera_centre,
                            self.settings.voxel_size_m, self.arms.index(arm))
        self._pending.setdefault(arm, []).append(stats)
        self._pending_rows += len(stats)
        if self.settings.support_cell_voxels > 1:
            cells = cell_stats(stats, self.settings.support_cell_voxels)
            self._cells.setdefault(arm, []).append(cells)
            self._pending_rows += len(cells)
        self.peak_rows = max(self.peak_rows, self.rows)
        if self._pending_rows >= self.settings.merge_rows:
            self._merge()
        return len(cloud)

    def _merge(self) -> None:
        for arm, parts in self._pending.items():
            if parts:
                self._state[arm] = merge_stats([self._state.get(arm, VoxelStats.empty(bool(self._colour))),
                                                *parts])
        for arm, parts in self._cells.items():  # kept as one merged part per arm
            self._cells[arm] = [merge_stats(parts)] if parts else []
        self._pending = {}
        self._pending_rows = 0

    def _cells_of(self, arms: Iterable[str]) -> VoxelStats | None:
        """The merged cell statistics of ``arms`` (None when cells are off)."""
        if self.settings.support_cell_voxels <= 1:
            return None
        return merge_stats([part for arm in arms for part in self._cells.get(arm, [])])

    def result(self, keep_stages: bool = False) -> FusionResult:
        """Support, averaging and outlier removal per arm and for all arms together. With ``keep_stages`` the
        result's ``stages`` holds the fused cloud's points after each step (``in_envelope``: every voxel's
        mean, ``supported``, ``after_sor``, ``fused``), for finding where true surface is lost."""
        self._merge()
        if not self._state:
            raise ReconstructionError("nothing to fuse: no frame left any point inside the envelope")
        arms = tuple(self.arms)
        per_arm: dict[str, VoxelCloud] = {}
        counts: dict[str, Any] = {}
        tolerance = self.settings.visibility_tolerance_m

        def visibility(bits: int) -> VisibilityFn | None:
            if not self.views:
                return None
            voxel = self.settings.voxel_size_m
            return lambda points, normals: in_view(points, self.views, tolerance, bits, normals, voxel)

        c: dict[str, int] = {"frames": len(self._seen), "points_in": sum(self.points_in.values())}
        all_stats = merge_stats(list(self._state.values()))
        fused_supported = supported_voxels(all_stats, self.settings, visibility(0xFF), c, self._cells_of(self.arms))
        stages: dict[str, np.ndarray] | None = {} if keep_stages else None
        fused = cloud_from_stats(all_stats, self.settings, arms, c, supported=fused_supported, stages=stages)
        if stages is not None:
            stages["fused"] = fused.points
        counts["fused"] = c
        fused_keys = all_stats.keys[fused_supported] if self.settings.arm_support_from_fused > 0 else None
        for bit, arm in enumerate(arms):
            c = {"frames": self.frames.get(arm, 0), "points_in": self.points_in.get(arm, 0)}
            per_arm[arm] = cloud_from_stats(self._state.get(arm, VoxelStats.empty(bool(self._colour))),
                                            self.settings, arms, c, visibility(1 << bit), fused_keys,
                                            cells=self._cells_of([arm]))
            counts[arm] = c
        counts["fused"] = counts.pop("fused")  # the per-arm counts first, as recorded before
        counts["peak_rows"] = self.peak_rows
        return FusionResult(fused=fused, per_arm=per_arm, settings=self.settings, stats=counts, stages=stages)


def write_voxel_cloud(path: str | Path, cloud: VoxelCloud) -> Path:
    """Write a fused cloud as binary PLY with its support counts (``n_frames``, ``n_views``, ...)."""
    return write_cloud_ply(
        path, cloud.points, normals=cloud.normals, colours=cloud.colours,
        fields={"n_points": cloud.n_points.astype(np.int32), "n_frames": cloud.n_frames.astype(np.int32),
                "n_views": cloud.n_views.astype(np.uint8), "arm_mask": cloud.arm_mask.astype(np.uint8)},
        comments=[f"arms {' '.join(cloud.arms)}"],
    )


def fuse(frames: Iterable[PosedDepth], settings: FusionSettings | None = None,
         region: Region | None = None) -> FusionResult:
    """Fuse ``frames`` (streamed: each frame is reduced and dropped before the next one is read)."""
    fusion = VoxelFusion(settings, region)
    for frame in frames:
        fusion.add(frame)
    return fusion.result()


__all__ = [
    "ARM_COLOURS",
    "FusionResult",
    "FrameView",
    "FusionSettings",
    "VoxelCloud",
    "VoxelFusion",
    "calibration_uncertainty_m",
    "cloud_from_stats",
    "fit_to_local_surface",
    "fuse",
    "in_view",
    "merge_coincident",
    "neighbourhood_support",
    "second_layer",
    "statistical_outliers",
    "supported_voxels",
    "write_voxel_cloud",
]
