"""The object envelope estimated from the survey itself, for surveys whose envelope has no geometry.

``manip_envelope.json`` may lack the object's centre, radius and height (the DARP release's Red Bull
survey has none; envelopes written by other tools may not either), but fusion needs the cylinder to
crop the object. The survey orbits the object, so its depth frames already say where it is:

1. **Where the cameras look.** Every still run of settled frames (the keyframe rule:
   :func:`darp.reconstruction.keyframes.settled_mask`) of both arms gives one optical axis (its middle
   frame's); runs from the same pose (an arm parking twice) count once. The point nearest to all
   axes (least squares) is refined by dropping axes that pass far from it or point away from it
   (the park poses look at the middle of the table, not at the object), until the set is stable.
2. **A search cylinder** around that point: ``search_radius_m`` (0.25 m), shrunk so that it stays
   ``base_clearance_m`` away from each arm's base; from ``table_band_m`` below the table (world
   z = 0 by definition, docs/rig-and-poses.md) to ``search_top_m`` above it.
3. **Depth of a few settled frames.** Per arm, the ``views_per_arm`` most diverse views (dwells)
   about the look-at point, ``frames_per_view`` frames each (the keyframe selection:
   :func:`darp.reconstruction.keyframes.select_survey_keyframes`), are back-projected with fusion's
   depth filters (:func:`darp.reconstruction.backproject.backproject`), cropped to the search
   cylinder and reduced to ``voxel_size_m`` voxels (:mod:`darp.reconstruction.voxel_stats`: a frame
   counts once per voxel; which arms saw it).
4. **The table.** The table height is the mode of the points' z within ``table_band_m`` of z = 0,
   refined by the median of the points near the mode (a calibration whose world z is off by a few
   millimetres still cuts at the table it sees); with too few table points it is taken as z = 0.
5. **The object.** Voxels whose mean lies ``min_height_m`` above the table and that at least
   ``min_frames`` frames saw (two noise draws of a view, or two views) are grouped into clusters:
   voxels at most ``link_voxels`` apart along every axis are linked (a one-voxel gap does not split
   a sparsely seen object; the two sides of a thin plate, each seen by one arm only, join). Of the
   clusters with at least ``min_cluster_voxels`` voxels that come within ``near_m`` of the look-at
   point (horizontally), the object is the one seen by every arm (the other arm, seen by one camera
   only, is not), then the largest. Its spurs (voxels with fewer than ``min_neighbours`` cluster
   neighbours within ``link_voxels``) are dropped.
6. **The cylinder.** The smallest vertical cylinder standing on the table that holds the cluster's
   voxel means: the centre and radius of their smallest enclosing circle (seen from above), the
   height of the highest one above the table, and the centre's z ``table + height / 2`` (the
   convention of ``manip_envelope.json``: :meth:`darp.reconstruction.crop.EnvelopeCrop.from_envelope`
   puts the table at the cylinder's bottom). This is close to how the twin measures an object's
   envelope (largest horizontal distance from its footprint centre, height of its top), so thin
   parts count: no percentile trimming (a mug's handle would be trimmed away first); outliers are
   kept out by the frame support, the clustering and the spur rule instead.

What no view sees cannot be estimated: a side that no settled frame sees is missing from the
estimate as it is from the fused cloud (fusion's crop adds its ``envelope_margin_m``, 1 cm, around
the estimate as around any envelope).

Deterministic: no random choice anywhere. When nothing stands above the table near where the
cameras look, a :class:`~darp.errors.ReconstructionError` names the survey.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from darp.errors import ReconstructionError
from darp.formats.envelope import Envelope
from darp.formats.realsense.recording import Recording
from darp.formats.realsense.types import Intrinsics
from darp.geometry.circle import min_enclosing_circle
from darp.reconstruction.backproject import DepthFilterSettings, PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.keyframes import (
    KeyframeSettings,
    look_at_point,
    select_survey_keyframes,
    settled_mask,
)
from darp.reconstruction.voxel_stats import VoxelStats, frame_stats, merge_stats, popcount64, voxel_indices

SOURCE_FILE, SOURCE_ESTIMATED = "manip_envelope.json", "estimated"
TABLE_SAMPLES_PER_FRAME = 20_000


@dataclass(frozen=True)
class EnvelopeEstimateSettings:
    """Every parameter of the estimate (see the module docstring for the steps they belong to)."""

    views_per_arm: int = 8  # views (dwells) per arm whose depth is back-projected, the most diverse ones
    frames_per_view: int = 2  # frames per view: independent noise draws of the same view
    search_radius_m: float = 0.25  # search cylinder around where the cameras look
    base_clearance_m: float = 0.15  # ... kept this far from each arm's base axis
    search_top_m: float = 0.5  # ... up to this height above the world's z = 0
    table_band_m: float = 0.01  # the table is looked for within this of z = 0
    min_table_points: int = 500  # fewer table points than this: the table is taken as z = 0
    min_height_m: float = 0.006  # object voxels lie this far above the table (D4 noise on the table: ~1-3 mm)
    voxel_size_m: float = 0.004  # voxels of the support count and the clusters
    min_frames: int = 2  # distinct frames that must see a voxel
    min_cluster_voxels: int = 25  # smaller clusters are noise (25 voxels of 4 mm: a 2 x 2 cm patch)
    near_m: float = 0.08  # the object's cluster comes this close (horizontally) to the look-at point
    link_voxels: int = 2  # voxels this many voxels apart (or closer, per axis) belong to one cluster
    min_neighbours: int = 3  # cluster voxels with fewer cluster neighbours within link_voxels are spurs
    axis_inlier_m: float = 0.03  # look-at: axes this close to the point are always kept ...
    axis_inlier_factor: float = 2.5  # ... and those within this many times the median distance

    def __post_init__(self) -> None:
        positive = ("search_radius_m", "search_top_m", "table_band_m", "min_height_m", "voxel_size_m", "near_m",
                    "axis_inlier_m", "axis_inlier_factor")
        bad = [name for name in positive if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0)]
        if bad:
            raise ReconstructionError(f"envelope estimate: {', '.join(bad)} must be finite and > 0")
        counts = (self.views_per_arm, self.frames_per_view, self.min_frames, self.min_cluster_voxels,
                  self.link_voxels, self.min_table_points)
        if min(counts) < 1 or self.min_neighbours < 0 or self.base_clearance_m < 0:
            raise ReconstructionError("envelope estimate: views_per_arm, frames_per_view, min_frames, "
                                      "min_cluster_voxels, link_voxels, min_table_points must be >= 1, "
                                      "min_neighbours and base_clearance_m >= 0")


@dataclass(frozen=True)
class EnvelopeEstimate:
    """The estimated object cylinder (world frame, metres) and how it was found."""

    center_m: tuple[float, float, float]  # z = table_z_m + height_m / 2
    radius_m: float
    height_m: float  # from the table plane to the object's top
    table_z_m: float
    table_measured: bool  # False: too few table points, z = 0 assumed
    look_at_m: tuple[float, float, float]
    frames: dict[str, int]  # depth frames back-projected, per arm
    cluster_voxels: int

    def envelope(self, base: Envelope | None = None) -> Envelope:
        """``base`` (the survey's envelope, kept otherwise unchanged) with this geometry."""
        return dataclasses.replace(base if base is not None else Envelope(schema_version=None),
                                   center_m=self.center_m, radius_m=self.radius_m, height_m=self.height_m)

    def to_dict(self) -> dict[str, Any]:
        """The ``envelope`` record of results.json and the keyframe index (``source: estimated``)."""
        return {"source": SOURCE_ESTIMATED, "center_m": [round(v, 6) for v in self.center_m],
                "radius_m": round(self.radius_m, 6), "height_m": round(self.height_m, 6),
                "table_z_m": round(self.table_z_m, 6), "table_measured": self.table_measured,
                "look_at_m": [round(v, 6) for v in self.look_at_m], "frames": dict(self.frames),
                "cluster_voxels": self.cluster_voxels}


def envelope_record(envelope: Envelope) -> dict[str, Any]:
    """The ``envelope`` record of an envelope read from the survey (``source: manip_envelope.json``)."""
    assert envelope.center_m is not None and envelope.radius_m is not None and envelope.height_m is not None
    return {"source": SOURCE_FILE, "center_m": [float(v) for v in envelope.center_m],
            "radius_m": float(envelope.radius_m), "height_m": float(envelope.height_m)}


# -- 1. where the cameras look -----------------------------------------------------------------------------
def still_view_poses(trajectories: Mapping[str, Any], settings: KeyframeSettings | None = None,
                     same_m: float = 0.01, same_deg: float = 2.0) -> np.ndarray:
    """(V, 4, 4) one pose per still run of settled frames of every arm, poses repeated across runs once.

    ``trajectories`` are ``SurveyPoses.trajectories`` (CameraTrajectory by arm).
    """
    settings = settings or KeyframeSettings()
    poses: list[np.ndarray] = []
    for traj in trajectories.values():
        order = np.argsort(traj.timestamps_ms, kind="stable")
        T = np.asarray(traj.poses.T_world_cam, np.float64)[order]
        posed = np.all(np.isfinite(T.reshape(len(T), 16)), axis=1)
        threshold = settings.still_threshold(float(getattr(traj, "speed_noise_rad_s", 0.0)))
        settled = settled_mask(traj.poses.t_s[order], traj.poses.joint_speed_rad_s[order], settings, threshold) & posed
        edges = np.diff(np.concatenate(([0], settled.view(np.int8), [0])))
        for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
            pose = T[(start + stop - 1) // 2]
            if not any(np.linalg.norm(pose[:3, 3] - p[:3, 3]) < same_m
                       and float(pose[:3, 2] @ p[:3, 2]) > math.cos(math.radians(same_deg)) for p in poses):
                poses.append(pose)
    return np.array(poses).reshape(-1, 4, 4)


def axis_distances(point_m: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance of ``point_m`` to each optical axis, and its signed depth along the axis."""
    rel = np.asarray(point_m, np.float64) - T_world_cam[:, :3, 3]
    along = np.einsum("ni,ni->n", rel, T_world_cam[:, :3, 2])
    return np.linalg.norm(rel - along[:, None] * T_world_cam[:, :3, 2], axis=1), along


def robust_look_at(T_world_cam: np.ndarray, settings: EnvelopeEstimateSettings | None = None,
                   iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """The point nearest the optical axes, ignoring axes far from it or looking away; (point, inliers)."""
    settings = settings or EnvelopeEstimateSettings()
    T = np.asarray(T_world_cam, np.float64)
    keep = np.ones(len(T), bool)
    point = look_at_point(T)
    for _ in range(iterations):
        distance, along = axis_distances(point, T)
        limit = max(settings.axis_inlier_m, settings.axis_inlier_factor * float(np.median(distance[keep])))
        inliers = (distance <= limit) & (along > 0)
        if inliers.sum() < 2 or np.array_equal(inliers, keep):
            break
        keep = inliers
        point = look_at_point(T[keep])
    return point, keep


def search_region(look_at_m: np.ndarray, base_xy_m: Iterable[np.ndarray],
                  settings: EnvelopeEstimateSettings | None = None) -> EnvelopeCrop:
    """The search cylinder about the look-at point, clear of the arms' bases."""
    settings = settings or EnvelopeEstimateSettings()
    radius = settings.search_radius_m
    for base in base_xy_m:
        radius = min(radius, float(np.linalg.norm(np.asarray(look_at_m[:2]) - np.asarray(base)[:2]))
                     - settings.base_clearance_m)
    radius = max(radius, 2 * settings.voxel_size_m)
    bottom, top = -settings.table_band_m, settings.search_top_m
    return EnvelopeCrop(center_m=(float(look_at_m[0]), float(look_at_m[1]), 0.5 * (bottom + top)),
                        radius_m=radius, height_m=top - bottom, table_z_m=bottom, margin_m=0.0, table_margin_m=0.0)


# -- 4.-6. table, object cluster, cylinder ------------------------------------------------------------------
def table_height(z_m: np.ndarray, settings: EnvelopeEstimateSettings | None = None) -> float | None:
    """The table's z from points near z = 0: the mode (1 mm bins) refined by the median around it."""
    settings = settings or EnvelopeEstimateSettings()
    band = settings.table_band_m
    z = np.asarray(z_m, np.float64)
    z = z[np.abs(z) <= band]
    if z.size < settings.min_table_points:
        return None
    counts, edges = np.histogram(z, bins=max(round(2 * band / 0.001), 1), range=(-band, band))
    peak = 0.5 * (edges[np.argmax(counts)] + edges[np.argmax(counts) + 1])
    near = z[np.abs(z - peak) <= 0.003]
    return float(np.median(near)) if near.size >= settings.min_table_points else None


def object_cluster(stats: VoxelStats, table_z_m: float, look_at_m: np.ndarray, n_arms: int,
                   settings: EnvelopeEstimateSettings | None = None) -> np.ndarray | None:
    """Mean points (N, 3) of the object's voxel cluster (module docstring, step 5), or None."""
    settings = settings or EnvelopeEstimateSettings()
    if len(stats) == 0:
        return None
    mean = stats.sum_xyz / stats.n_points[:, None]
    keep = (mean[:, 2] > table_z_m + settings.min_height_m) & (stats.n_frames >= settings.min_frames)
    if not keep.any():
        return None
    mean, arm_mask = mean[keep], stats.arm_mask[keep]
    ijk = voxel_indices(mean, settings.voxel_size_m)
    tree = cKDTree(ijk)
    reach = settings.link_voxels + 0.5  # Chebyshev distance between integer voxel coordinates
    pairs = tree.query_pairs(reach, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(mean), len(mean)))
    n, label = connected_components(graph, directed=False)
    size = np.bincount(label, minlength=n)
    seen_by = np.zeros(n, np.int64)  # arms (bits) that saw some voxel of each cluster
    for bit in range(8):
        seen_by |= (np.bincount(label, weights=(arm_mask >> bit) & 1, minlength=n) > 0).astype(np.int64) << bit
    every_arm = popcount64(seen_by.astype(np.uint64)) >= n_arms
    horizontal = np.linalg.norm(mean[:, :2] - np.asarray(look_at_m)[:2], axis=1)
    nearest = np.full(n, np.inf)
    np.minimum.at(nearest, label, horizontal)
    candidates = [k for k in range(n) if size[k] >= settings.min_cluster_voxels and nearest[k] <= settings.near_m]
    if not candidates:
        return None
    best = max(candidates, key=lambda k: (bool(every_arm[k]), int(size[k]), -float(nearest[k])))
    members = mean[label == best]
    member_ijk = ijk[label == best]
    neighbours = cKDTree(member_ijk).query_ball_point(member_ijk, reach, p=np.inf, return_length=True) - 1
    kept: np.ndarray = members[neighbours >= settings.min_neighbours]
    return kept


def fit_cylinder(points_m: np.ndarray, table_z_m: float) -> tuple[np.ndarray, float, float]:
    """``(centre_xy, radius, height)``: the smallest vertical cylinder standing on the table that holds the points."""
    p = np.asarray(points_m, np.float64)
    centre_xy, radius = min_enclosing_circle(p[:, :2])  # the one localisation uses: exact, float64
    return centre_xy, float(radius), float(p[:, 2].max()) - table_z_m


# -- the whole estimate -------------------------------------------------------------------------------------
def envelope_from_frames(frames: Iterable[PosedDepth], look_at_m: np.ndarray, region: EnvelopeCrop, *,
                         depth_settings: DepthFilterSettings | None = None,
                         settings: EnvelopeEstimateSettings | None = None,
                         path: str | Path | None = None) -> EnvelopeEstimate:
    """Steps 3-6 of the module docstring on the given posed depth frames (any number of arms)."""
    settings = settings or EnvelopeEstimateSettings()
    arms: list[str] = []
    parts: list[VoxelStats] = []
    band_z: list[np.ndarray] = []
    counts: dict[str, int] = {}
    for frame in frames:
        if frame.arm not in arms:
            arms.append(frame.arm)
        counts[frame.arm] = counts.get(frame.arm, 0) + 1
        cloud = backproject(frame, depth_settings, region)
        if len(cloud) == 0:
            continue
        z = cloud.points[:, 2]
        near_table = z[np.abs(z) <= settings.table_band_m]
        band_z.append(near_table[::max(1, near_table.size // TABLE_SAMPLES_PER_FRAME)])  # enough for a mode
        parts.append(frame_stats(cloud.points, cloud.normals, None, cloud.camera_centre, settings.voxel_size_m,
                                 min(arms.index(frame.arm), 7)))
    per_arm = f" ({', '.join(f'{arm}: {n}' for arm, n in counts.items())})" if len(counts) > 1 else ""
    table = table_height(np.concatenate(band_z) if band_z else np.empty(0), settings)
    table_z = 0.0 if table is None else table
    cluster = object_cluster(merge_stats(parts), table_z, look_at_m, len(arms), settings)
    if cluster is None:
        raise ReconstructionError(
            f"the envelope has no centre/radius/height and no object could be found to estimate it: nothing "
            f"stands {settings.min_height_m * 1000:.0f} mm above the table within {settings.near_m * 100:.0f} cm "
            f"of where the cameras look ({look_at_m[0]:.3f}, {look_at_m[1]:.3f}) m in "
            f"{sum(counts.values())} depth frames{per_arm}", path)
    centre_xy, radius, height = fit_cylinder(cluster, table_z)
    return EnvelopeEstimate(
        center_m=(float(centre_xy[0]), float(centre_xy[1]), table_z + 0.5 * height), radius_m=radius,
        height_m=height, table_z_m=table_z, table_measured=table is not None,
        look_at_m=(float(look_at_m[0]), float(look_at_m[1]), float(look_at_m[2])), frames=counts,
        cluster_voxels=len(cluster))


def estimate_survey_envelope(poses: Any, recording: Callable[[str], Recording], base_xy_m: Sequence[np.ndarray],
                             *,
                             keyframe_settings: KeyframeSettings | None = None,
                             depth_settings: DepthFilterSettings | None = None,
                             settings: EnvelopeEstimateSettings | None = None,
                             path: str | Path | None = None) -> EnvelopeEstimate:
    """Estimate the object envelope of a survey from its poses (``SurveyPoses``) and depth frames.

    ``recording(arm)`` opens (or hands out) an arm's recording; ``base_xy_m`` are the arms' base
    positions in the world (the search region keeps clear of them); ``path`` names the survey in errors.
    """
    settings = settings or EnvelopeEstimateSettings()
    keyframe_settings = keyframe_settings or KeyframeSettings()
    views = still_view_poses(poses.trajectories, keyframe_settings)
    if len(views) < 2:
        raise ReconstructionError(
            f"the envelope has no centre/radius/height and the survey has {len(views)} still view(s): "
            "cannot find where the cameras look to estimate it", path)
    try:
        look_at, _ = robust_look_at(views, settings)
    except ReconstructionError as err:
        raise ReconstructionError(f"the envelope has no centre/radius/height: {err.message}", path) from None
    region = search_region(look_at, base_xy_m, settings)
    picking = dataclasses.replace(keyframe_settings, per_view=settings.frames_per_view,
                                  max_views=settings.views_per_arm)
    found = {arm: recording(arm).stream("depth").intrinsics for arm in poses.trajectories}
    intrinsics: dict[str, Intrinsics] = {}
    for arm, intr in found.items():
        if intr is None:
            raise ReconstructionError(f"{arm}'s depth stream has no intrinsics: cannot estimate the envelope", path)
        intrinsics[arm] = intr
    selection = select_survey_keyframes(poses.trajectories, look_at, picking, intrinsics)

    def frames() -> Iterable[PosedDepth]:
        for arm, picked in selection.items():
            rec = recording(arm)
            traj = poses.trajectories[arm]
            for index in picked.indices.tolist():
                depth = rec.read_frame("depth", index)
                yield PosedDepth(arm, depth.info.frame_number, np.asarray(depth.data), float(rec.depth_scale),
                                 intrinsics[arm], traj.poses.T_world_cam[index])

    return envelope_from_frames(frames(), look_at, region, depth_settings=depth_settings, settings=settings,
                                path=path)


__all__ = [
    "SOURCE_ESTIMATED",
    "SOURCE_FILE",
    "EnvelopeEstimate",
    "EnvelopeEstimateSettings",
    "axis_distances",
    "envelope_from_frames",
    "envelope_record",
    "estimate_survey_envelope",
    "fit_cylinder",
    "object_cluster",
    "robust_look_at",
    "search_region",
    "still_view_poses",
    "table_height",
]
