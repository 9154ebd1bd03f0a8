"""Depth-based object estimate from one eye-in-hand view: the envelope (centre, radius, height).

For one or a few live depth frames (:func:`estimate_from_depth`):

1. back-project the valid depth (pixel centres at integer coordinates) and move the points to the
   world with the camera pose of eq. 1 (the arm's joint state and the calibration used for live
   decisions);
2. fit the table plane to the points within ``plane_band_m`` of the nominal table height (least
   squares, trimmed three times): with a nominal calibration the table appears shifted and tilted by
   millimetres, and heights are measured from the plane the camera sees, not from the nominal one;
3. keep points above that plane by more than the view's own noise floor and inside the search region
   (the placement workspace grown by ``region_margin_m``); bin them on a 1 cm grid of the table and keep
   the largest 8-connected blob (by points); fewer than ``noise_points`` per frame is noise. The noise
   floor (:func:`table_noise_floor`): the table's scatter about the fitted plane grows with the square of
   the range (stereo depth: ``sigma_z ~ z^2 sigma_d / (f B)``, plus low-frequency depth waves), so it is
   measured per view as a robust ``sigma / z^2`` of the plane's band and a point counts as above the table
   when ``h > max(table_margin_m, noise_floor_k * sigma * z^2)``. A fixed margin is what a noisier
   camera or a lower resolution breaks: the far table then rises above it as one wide, flat blob
   that outweighs the object (issue 12, 2x the ``paper`` profile at 424x240);
4. reject the blob with a reason when it is too small (``too_small``), not in the workspace
   (``outside_workspace``, ``too_tall``), not supported (``few_points``, ``low_valid_fraction``) or
   cut by the image border (``truncated``); the rejected estimate is kept as a hint for a closer look;
5. the estimate: the footprint's centre is the centre of the smallest circle enclosing the blob's
   points seen from above (after trimming the farthest 0.5 %: flying pixels), radius = the 99.5th
   percentile of the horizontal distances from that centre axis, height = the 99.5th percentile of
   the heights above the plane, and ``centre_m = (x, y, table + height / 2)``, the middle of the
   envelope cylinder (the twin's truth uses the same convention).

Seen from one side at a camera elevation of 35-60 deg, the top of most objects and the near half of
their sides are visible; the enclosing circle of a visible half circle is the full circle, so the
centre is nearly unbiased for round objects (a little towards the camera when less than half the side
shows). Cross-arm confirmation averages the two sides' centres. The enclosing circle is also what an
envelope means: the smallest vertical cylinder holding the object, whatever its shape.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from darp.errors import AcquisitionError
from darp.formats.realsense.types import Intrinsics
from darp.geometry.circle import min_enclosing_circle
from darp.geometry.pinhole import backproject_rays, normalised_pixels
from darp.kinematics.rig import Rig, Workspace

Array = NDArray[np.float64]
IndexArray = NDArray[np.intp]

REJECTION_REASONS = ("no_depth", "low_valid_fraction", "no_object", "few_points", "too_small", "truncated",
                     "outside_workspace", "too_tall", "unreachable")


@dataclass(frozen=True)
class LocaliseSettings:
    """Thresholds of the estimator and the search."""

    min_range_m: float = 0.12
    max_range_m: float = 1.5
    max_points: int = 80_000  # back-projected points per frame (the image is subsampled above this)
    plane_band_m: float = 0.04  # table-plane candidates: within this of the nominal table height
    max_plane_tilt_deg: float = 5.0
    table_margin_m: float = 0.006  # object points: at least this far above the fitted table plane
    noise_floor_k: float = 4.0  # ... and more than this many times the view's table scatter at their range
    max_noise_margin_m: float = 0.05  # the noise margin's cap: a table noisier than this is no table
    region_margin_m: float = 0.15  # search region = workspace grown by this (objects just outside are seen)
    cell_m: float = 0.01  # grid of the connected-blob clustering
    min_cell_points: int = 2
    min_points: int = 60  # per frame, on the object
    noise_points: int = 15  # per frame: a blob smaller than this is noise, not an object
    min_valid_fraction: float = 0.25  # of the image's pixels
    min_radius_m: float = 0.01
    min_height_m: float = 0.01
    border_px: int = 3  # a blob this close to the image border is truncated
    workspace_tolerance_m: float = 0.02  # a centre this far outside the workspace is still accepted
    frames_per_view: int = 2
    frame_interval_s: float = 0.1
    search_distance_m: float = 0.55
    search_elevation_deg: float = 50.0
    refine_elevation_deg: float = 45.0
    refine_extra_standoff_m: float = 0.05
    refine_tolerance_m: float = 0.01
    max_refinements: int = 2

    def __post_init__(self) -> None:
        if not 0 < self.min_range_m < self.max_range_m:
            raise AcquisitionError("localisation needs 0 < min_range_m < max_range_m")
        if self.frames_per_view < 1 or self.min_points < 1 or self.cell_m <= 0:
            raise AcquisitionError("localisation needs frames_per_view >= 1, min_points >= 1, cell_m > 0")
        if not (self.noise_floor_k >= 0 and self.max_noise_margin_m >= self.table_margin_m):
            raise AcquisitionError("localisation needs noise_floor_k >= 0 and max_noise_margin_m >= table_margin_m")


@dataclass
class ObjectEstimate:
    """A depth-based object estimate in the world frame (the envelope: a vertical cylinder)."""

    arm_id: str
    centre_m: Array  # (x, y, table + height / 2)
    radius_m: float
    height_m: float
    n_points: int
    valid_fraction: float
    stage: str = ""  # search, refine, confirm, reobserve
    camera_m: Array | None = None  # camera position of the view (world)
    plane: dict[str, float] = field(default_factory=dict)
    points_m: Array | None = field(default=None, repr=False)  # the blob's points (world), not recorded

    def to_record(self) -> dict[str, Any]:
        return {"arm": self.arm_id, "stage": self.stage,
                "centre_m": [round(float(v), 5) for v in self.centre_m],
                "radius_m": round(self.radius_m, 5), "height_m": round(self.height_m, 5),
                "n_points": self.n_points, "valid_fraction": round(self.valid_fraction, 4),
                "camera_m": None if self.camera_m is None else [round(float(v), 4) for v in self.camera_m],
                "plane": {k: round(v, 6) for k, v in self.plane.items()}}


@dataclass
class Observation:
    """What one view gave: an estimate, or the reason there is none (and the rejected estimate)."""

    estimate: ObjectEstimate | None
    reason: str = ""  # one of REJECTION_REASONS when estimate is None
    detail: str = ""
    candidate: ObjectEstimate | None = None  # a rejected estimate (e.g. outside the workspace)
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.estimate is not None

    def to_record(self) -> dict[str, Any]:
        est = self.estimate or self.candidate
        return {"ok": self.ok, "reason": self.reason, "detail": self.detail, "stats": self.stats,
                "estimate": None if est is None else est.to_record()}


# -- geometry helpers -----------------------------------------------------------------------------
def backproject(depth_m: Array, intrinsics: Intrinsics, stride: int = 1) -> tuple[Array, IndexArray, IndexArray]:
    """Valid pixels of a depth image as camera-frame points: (points (N, 3), u (N,), v (N,))."""
    d = np.asarray(depth_m, dtype=np.float64)[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u]
    u, v = u * stride, v * stride
    x, y = normalised_pixels(u, v, intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy)
    return np.asarray(backproject_rays(x, y, z), np.float64), u, v


def fit_table_plane(points: Array, table_z: float, band_m: float) -> tuple[Array, int] | None:
    """Least-squares plane ``z = a x + b y + c`` of the points near the nominal table height, trimmed
    three times; None when fewer than 200 points are near the table."""
    near = points[np.abs(points[:, 2] - table_z) < band_m]
    if len(near) < 200:
        return None
    coef = np.array([0.0, 0.0, table_z])
    sel = near
    for keep in (0.02, 0.008, 0.004):
        A = np.column_stack([sel[:, 0], sel[:, 1], np.ones(len(sel))])
        coef, *_ = np.linalg.lstsq(A, sel[:, 2], rcond=None)
        res = near[:, 2] - (near[:, 0] * coef[0] + near[:, 1] * coef[1] + coef[2])
        inliers = np.abs(res) < keep
        if inliers.sum() < 100:
            break
        sel = near[inliers]
    return coef, len(sel)


def table_noise_floor(heights_m: Array, ranges_m: Array, band_m: float) -> float:
    """The table's scatter about its fitted plane per square metre of range (``sigma / z^2``, 1/m).

    ``heights_m``: the points' heights above the fitted plane, ``ranges_m``: their camera depths. Only the
    points within ``band_m`` of the plane count (the table and an object's foot); the scale is the median
    absolute deviation (x 1.4826, a Gaussian's sigma), robust to the object's few points in the band.
    0 when fewer than 200 points are in the band.
    """
    h = np.asarray(heights_m, dtype=np.float64)
    z = np.asarray(ranges_m, dtype=np.float64)
    near = (np.abs(h) < band_m) & (z > 0)
    if int(near.sum()) < 200:
        return 0.0
    s = h[near] / z[near] ** 2
    return float(1.4826 * np.median(np.abs(s - np.median(s))))


def _grid_shape(lo: Array, hi: Array, cell_m: float) -> IndexArray:
    shape: IndexArray = np.maximum(np.ceil((hi - lo) / cell_m).astype(int), 1)
    return shape


def _cells(xy: Array, lo: Array, hi: Array, cell_m: float) -> IndexArray:
    """Each point's flat grid-cell index on the table grid from ``lo`` to ``hi``."""
    shape = _grid_shape(lo, hi, cell_m)
    ij = np.clip(((xy - lo) / cell_m).astype(int), 0, shape - 1)
    flat: IndexArray = ij[:, 0] * shape[1] + ij[:, 1]
    return flat


def _largest_blob(xy: Array, lo: Array, hi: Array, cell_m: float, min_cell_points: int) -> IndexArray:
    """Indices of the points in the largest 8-connected blob of occupied grid cells (by points)."""
    shape = _grid_shape(lo, hi, cell_m)
    flat = _cells(xy, lo, hi, cell_m)
    counts = np.bincount(flat, minlength=shape[0] * shape[1]).reshape(shape)
    labels, n = ndimage.label(counts >= min_cell_points, structure=np.ones((3, 3), dtype=int))
    if n == 0:
        return np.zeros(0, dtype=int)
    point_labels = labels.ravel()[flat]
    sizes = np.bincount(point_labels, minlength=n + 1)
    sizes[0] = 0
    return np.flatnonzero(point_labels == int(np.argmax(sizes)))


def in_workspace_xy(centre: Array, workspace: Workspace, tolerance_m: float) -> bool:
    """The centre's (x, y) within the workspace box grown by ``tolerance_m``."""
    (x0, x1), (y0, y1) = workspace.x_range_m, workspace.y_range_m
    x, y = float(centre[0]), float(centre[1])
    return x0 - tolerance_m <= x <= x1 + tolerance_m and y0 - tolerance_m <= y <= y1 + tolerance_m


# -- the estimator --------------------------------------------------------------------------------
def estimate_from_depth(frames: list[tuple[Array, Intrinsics, Array]], rig: Rig, arm_id: str,
                        settings: LocaliseSettings | None = None) -> Observation:
    """Estimate the object from depth frames ``[(depth_m (H, W), intrinsics, T_world_cam)]`` of one view."""
    s = settings if settings is not None else LocaliseSettings()
    if not frames:
        raise AcquisitionError("no frames to estimate from")
    table_z = rig.table.height_m
    ws = rig.workspace
    pts_all, uv_all, range_all, valid_fracs = [], [], [], []
    shape = np.asarray(frames[0][0]).shape
    for depth_m, intr, T_world_cam in frames:
        d = np.asarray(depth_m, dtype=np.float64)
        d = np.where((d >= s.min_range_m) & (d <= s.max_range_m), d, 0.0)
        valid_fracs.append(float(np.mean(d > 0)))
        stride = max(1, int(np.ceil(np.sqrt(d.size / s.max_points))))
        pc, u, v = backproject(d, intr, stride)
        T = np.asarray(T_world_cam, dtype=np.float64)
        pts_all.append(pc @ T[:3, :3].T + T[:3, 3])
        uv_all.append(np.column_stack([u, v]))
        range_all.append(pc[:, 2])
    valid_fraction = float(np.mean(valid_fracs))
    camera = np.asarray(frames[-1][2], dtype=np.float64)[:3, 3]
    stats: dict[str, Any] = {"valid_fraction": round(valid_fraction, 4)}
    if valid_fraction == 0.0:
        return Observation(None, "no_depth", "no valid depth pixel", stats=stats)
    if valid_fraction < s.min_valid_fraction:
        return Observation(None, "low_valid_fraction", f"only {valid_fraction:.0%} of the depth pixels are valid "
                           f"(minimum {s.min_valid_fraction:.0%})", stats=stats)
    pts = np.vstack(pts_all)
    uv = np.vstack(uv_all)
    ranges = np.concatenate(range_all)
    fit = fit_table_plane(pts, table_z, s.plane_band_m)
    if fit is None:
        coef, n_plane, plane_source = np.array([0.0, 0.0, table_z]), 0, "nominal"
    else:
        coef, n_plane = fit
        plane_source = "fitted"
        if np.degrees(np.arctan(np.hypot(coef[0], coef[1]))) > s.max_plane_tilt_deg:
            coef, plane_source = np.array([0.0, 0.0, table_z]), "nominal (fitted plane too tilted)"
    plane = {"a": float(coef[0]), "b": float(coef[1]), "c": float(coef[2]), "n_points": float(n_plane)}
    stats["plane"] = plane_source
    h = pts[:, 2] - (pts[:, 0] * coef[0] + pts[:, 1] * coef[1] + coef[2])
    sigma_per_m2 = table_noise_floor(h, ranges, s.plane_band_m)
    margin = np.clip(s.noise_floor_k * sigma_per_m2 * ranges ** 2, s.table_margin_m, s.max_noise_margin_m)
    stats["table_noise_mm_at_1m"] = round(1000.0 * sigma_per_m2, 3)
    stats["table_margin_mm"] = [round(1000.0 * float(np.min(margin)), 2), round(1000.0 * float(np.median(margin)), 2)]
    lo = np.array([max(ws.x_range_m[0] - s.region_margin_m, rig.table.x_range_m[0]),
                   max(ws.y_range_m[0] - s.region_margin_m, rig.table.y_range_m[0])])
    hi = np.array([min(ws.x_range_m[1] + s.region_margin_m, rig.table.x_range_m[1]),
                   min(ws.y_range_m[1] + s.region_margin_m, rig.table.y_range_m[1])])
    candidates = ((h > s.table_margin_m) & (h < ws.z_range_m[1] + 0.2) & np.all(pts[:, :2] >= lo, axis=1)
                  & np.all(pts[:, :2] <= hi, axis=1))
    pts, uv, h, margin = pts[candidates], uv[candidates], h[candidates], margin[candidates]
    keep = np.flatnonzero(h > margin)
    stats["above_table_points"] = len(keep)
    blob = (keep[_largest_blob(pts[keep, :2], lo, hi, s.cell_m, s.min_cell_points)] if len(keep)
            else np.zeros(0, int))
    if len(blob) == 0:
        return Observation(None, "no_object", "nothing stands on the table in view", stats=stats)
    # The noise margin finds the object; its extent is measured down to the fixed margin inside the cells the
    # object occupies (a foot between the two margins would otherwise be cut, moving the centre by millimetres).
    blob = np.flatnonzero(np.isin(_cells(pts[:, :2], lo, hi, s.cell_m), _cells(pts[blob, :2], lo, hi, s.cell_m)))
    pts, uv, h = pts[blob], uv[blob], h[blob]
    stats["blob_points"] = len(pts)
    n_frames = len(frames)
    if len(pts) < s.noise_points * n_frames:
        return Observation(None, "no_object", f"only {len(pts)} stray points above the table (noise)", stats=stats)
    xy = pts[:, :2]
    med = np.median(xy, axis=0)
    dist = np.linalg.norm(xy - med, axis=1)
    trimmed = xy[dist <= np.percentile(dist, 99.5)]
    centre_xy, _ = min_enclosing_circle(trimmed)
    radius = float(np.percentile(np.linalg.norm(xy - centre_xy, axis=1), 99.5))
    height = float(np.percentile(h, 99.5))
    estimate = ObjectEstimate(arm_id, np.array([centre_xy[0], centre_xy[1], table_z + 0.5 * height]), radius,
                              height, len(pts), valid_fraction, camera_m=camera, plane=plane, points_m=pts)
    if radius < s.min_radius_m or height < s.min_height_m:
        return Observation(None, "too_small", f"blob {radius * 100:.1f} cm in radius, {height * 100:.1f} cm high "
                           "(noise, not an object)", candidate=estimate, stats=stats)
    H, W = shape
    b = s.border_px
    touches = bool(np.any((uv[:, 0] < b) | (uv[:, 0] >= W - b) | (uv[:, 1] < b) | (uv[:, 1] >= H - b)))
    stats["truncated"] = touches
    if not in_workspace_xy(estimate.centre_m, ws, s.workspace_tolerance_m):
        return Observation(None, "outside_workspace",
                           f"object at ({centre_xy[0]:.3f}, {centre_xy[1]:.3f}) m is outside the workspace "
                           f"x {ws.x_range_m[0]:.2f}..{ws.x_range_m[1]:.2f}, "
                           f"y {ws.y_range_m[0]:.2f}..{ws.y_range_m[1]:.2f}",
                           candidate=estimate, stats=stats)
    if height > ws.z_range_m[1] - ws.z_range_m[0]:
        return Observation(None, "too_tall", f"object is {height:.3f} m tall (workspace height "
                           f"{ws.z_range_m[1] - ws.z_range_m[0]:.2f} m)", candidate=estimate, stats=stats)
    if len(pts) < s.min_points * n_frames:
        return Observation(None, "few_points", f"only {len(pts)} depth points on the object "
                           f"(minimum {s.min_points * n_frames} over {n_frames} frame(s))", candidate=estimate,
                           stats=stats)
    if touches:
        return Observation(None, "truncated", "the object touches the image border (partly out of view)",
                           candidate=estimate, stats=stats)
    return Observation(estimate, stats=stats)


__all__ = ["REJECTION_REASONS", "LocaliseSettings", "ObjectEstimate", "Observation", "backproject",
           "estimate_from_depth", "fit_table_plane", "in_workspace_xy", "table_noise_floor"]
