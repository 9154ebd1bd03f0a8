"""Depth images to world-frame points: metric depth, back-projection, edge rejection, normals, colour.

For one depth frame (raw Z16 values, the recording's depth scale, its intrinsics and the eq. 1 pose):

1. ``z = raw * depth_scale`` (metres); 0 and values outside ``[min_depth_m, max_depth_m]`` are invalid.
2. A pixel ``(u, v)`` (pixel centres at integer coordinates) with depth ``z`` is the camera-frame point
   ``((u - ppx) z / fx, (v - ppy) z / fy, z)``, after undistortion when the model has non-zero
   coefficients (``Brown Conrady`` and ``Inverse Brown Conrady``, matching librealsense's deprojection).
3. Optionally only pixels whose world point lies in a region (the object envelope) are kept; the rest of
   the work is done in the bounding window of those pixels, which is what makes a frame cheap.
4. Local depth discontinuities are rejected: two 8-neighbours whose depths differ by more than
   ``discontinuity_abs_m + discontinuity_rel * z`` mark both pixels, and every pixel within
   ``edge_margin_px`` of a marked pixel, an edge hole (a hole at a silhouette or occlusion band, see
   :mod:`darp.reconstruction.depth_edges`) or the image border is dropped. This removes the flying
   pixels and the fattened foreground that stereo depth leaves at silhouettes. Holes inside a smooth
   surface (material dropouts) only cost ``hole_margin_px`` (default 0).
5. Normals come from the depth image (cross product of central differences ``normal_step_px`` apart,
   one-sided where the stencil meets a hole), oriented toward the camera; points seen at more than
   ``max_incidence_deg`` from their normal are dropped (grazing stereo depth is the least accurate).
6. Points and normals are moved to the world frame with ``T_world_cam``; colours are looked up in a
   colour image aligned to the depth image when one is given.

Pure numpy, float32 per pixel; no Open3D.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from darp.errors import ReconstructionError
from darp.formats.realsense.types import Intrinsics
from darp.geometry.pinhole import backproject_rays, distort_normalised, normalised_pixels, undistort_normalised
from darp.geometry.rigid import check_rigid
from darp.geometry.transforms import transform_columns
from darp.reconstruction.depth_edges import HOLE_SEARCH_PX, depth_normals, edge_free_mask, normals_at

_UNDISTORT_ITERATIONS = 30
_UNDISTORT_TOLERANCE = 1e-7  # normalised image units (about 4e-5 px at fx = 383)


@dataclass(frozen=True)
class DepthFilterSettings:
    """Per-frame depth filters, shared by fusion and held-out evaluation (defaults: see docs/processing.md)."""

    min_depth_m: float = 0.10  # below the D435's minimum range (~0.15 m at 640x480) nothing is valid
    max_depth_m: float = 1.0  # the paper's standoffs are 0.34-0.52 m; farther is background
    discontinuity_abs_m: float = 0.002  # neighbour depth jump that marks an edge: abs + rel * z
    discontinuity_rel: float = 0.01  # 1 % of z: a plane up to ~80 deg from frontal stays smooth at 0.35 m
    edge_margin_px: int = 2  # pixels dropped around an edge or edge hole (D4 edge fattening is 1-2 px)
    hole_margin_px: int = 0  # pixels dropped around a hole inside a smooth surface (material dropouts)
    stereo_baseline_m: float = 0.050  # D435 baseline: sets the occlusion-band test that finds edge holes
    normal_step_px: int = 2  # half-width of the central differences behind the normals
    max_incidence_deg: float = 80.0  # drop points seen this far from their normal or more

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_depth_m < self.max_depth_m:
            raise ReconstructionError(
                f"depth range [{self.min_depth_m}, {self.max_depth_m}] m is empty or negative")
        if self.discontinuity_abs_m < 0 or self.discontinuity_rel < 0:
            raise ReconstructionError("discontinuity thresholds must be >= 0")
        if self.edge_margin_px < 0 or self.hole_margin_px < 0 or self.normal_step_px < 1:
            raise ReconstructionError("edge_margin_px and hole_margin_px must be >= 0 and normal_step_px >= 1")
        if not (math.isfinite(self.stereo_baseline_m) and self.stereo_baseline_m > 0):
            raise ReconstructionError(f"stereo_baseline_m must be > 0, got {self.stereo_baseline_m}")
        if not 0.0 < self.max_incidence_deg <= 90.0:
            raise ReconstructionError(f"max_incidence_deg must be in (0, 90], got {self.max_incidence_deg}")


@dataclass(frozen=True, eq=False)
class PosedDepth:
    """One depth frame ready to back-project: raw depth, its scale, intrinsics and world pose."""

    arm: str
    frame_id: int  # unique per arm (e.g. the device frame number)
    depth: np.ndarray  # (H, W) uint16 raw Z16 values (0 = no depth)
    depth_scale: float  # metres per depth unit
    intrinsics: Intrinsics
    T_world_cam: np.ndarray  # (4, 4) eq. 1 pose of the depth camera
    colour: np.ndarray | None = None  # (H, W, 3) uint8 RGB aligned to the depth image


@dataclass(frozen=True, eq=False)
class FrameCloud:
    """The surviving pixels of one frame as world points (float32), with normals toward the camera."""

    points: np.ndarray  # (N, 3) world frame, metres
    normals: np.ndarray  # (N, 3) unit, world frame, pointing toward the camera
    colours: np.ndarray | None  # (N, 3) uint8 RGB or None
    pixels: np.ndarray  # (N,) int64 flat pixel index v * W + u
    camera_centre: np.ndarray  # (3,) world position of the camera

    def __len__(self) -> int:
        return int(self.points.shape[0])


class Region(Protocol):
    """A world-frame region: ``contains(points (N, 3)) -> bool (N,)``."""

    def contains(self, points_world: np.ndarray) -> np.ndarray: ...


# -- metric depth and rays ------------------------------------------------------------------------
CORRECTED_DEPTH_SCALE = 0.00025
"""Metres per unit of depth written after a depth correction: a quarter millimetre keeps the corrected
values' rounding (0.07 mm RMS) well below the sensor's noise, and 16 bits still reach 16.4 m."""


class DepthCorrectionModel(Protocol):
    """A per-camera depth correction (``darp.formats.calibration.DepthCorrection``)."""

    def apply(self, depth_m: np.ndarray) -> np.ndarray: ...


def correct_raw_depth(depth: np.ndarray, depth_scale: float, correction: DepthCorrectionModel
                      ) -> tuple[np.ndarray, float]:
    """Raw Z16 depth corrected by ``correction``: ``(uint16 depth, its depth scale)``.

    The corrected metric depth is re-quantised to :data:`CORRECTED_DEPTH_SCALE` so every consumer of the
    raw-depth contract (``metres = depth * depth_scale``) sees corrected depth; 0 stays 0 and a value
    beyond the 16-bit range becomes 0 (no depth).
    """
    metres = correction.apply(np.asarray(depth, np.float64) * float(depth_scale))
    units = np.rint(metres / CORRECTED_DEPTH_SCALE)
    return np.where((units > 0) & (units <= 65535), units, 0).astype(np.uint16), CORRECTED_DEPTH_SCALE


def depth_to_metres(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """Raw Z16 depth (or already-metric float depth with scale 1) to float32 metres; 0 stays 0."""
    if depth.ndim != 2:
        raise ReconstructionError(f"depth image must be 2-D, got shape {depth.shape}")
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ReconstructionError(f"depth scale must be positive, got {depth_scale}")
    depth_m = depth.astype(np.float32) * np.float32(depth_scale)
    if not np.issubdtype(depth.dtype, np.integer):
        depth_m[~np.isfinite(depth_m)] = 0.0
    return depth_m


def _has_distortion(intrinsics: Intrinsics) -> bool:
    return intrinsics.model.lower() != "none" and any(abs(c) > 0.0 for c in intrinsics.coeffs)


def _undistort(xd: np.ndarray, yd: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    model = intrinsics.model.lower()
    if model not in ("brown conrady", "inverse brown conrady"):
        raise ReconstructionError(
            f"cannot back-project through {intrinsics.model!r} distortion with non-zero coefficients "
            f"{intrinsics.coeffs} (supported: Brown Conrady, Inverse Brown Conrady)")
    inverse = model == "inverse brown conrady"  # tangential terms on the radially scaled coordinates
    x, y = undistort_normalised(xd, yd, intrinsics.coeffs, inverse, _UNDISTORT_ITERATIONS)
    dx, dy = distort_normalised(x, y, intrinsics.coeffs, inverse)
    residual = float(np.max(np.hypot(dx - xd, dy - yd)))
    if not residual < _UNDISTORT_TOLERANCE:
        raise ReconstructionError(
            f"{intrinsics.model} undistortion did not converge (residual {residual:.2e}); "
            f"coefficients {intrinsics.coeffs} look implausible")
    return x, y


@functools.lru_cache(maxsize=16)
def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 2) float32 normalised coordinates ``(x/z, y/z)`` of every pixel centre (cached)."""
    w, h = int(intrinsics.width), int(intrinsics.height)
    if w <= 0 or h <= 0 or not (intrinsics.fx > 0 and intrinsics.fy > 0):
        raise ReconstructionError(f"invalid intrinsics {intrinsics}")
    u, v = normalised_pixels(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64), intrinsics.fx,
                             intrinsics.fy, intrinsics.ppx, intrinsics.ppy)
    x, y = np.meshgrid(u, v)
    if _has_distortion(intrinsics):
        x, y = _undistort(x, y, intrinsics)
    rays = np.stack([x, y], axis=-1).astype(np.float32)
    rays.flags.writeable = False
    return rays


def camera_points(depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points of a metric depth image (z = 0 where there is no depth)."""
    rays = depth_pixel_rays(depth_m, intrinsics)
    z = depth_m.astype(np.float32, copy=False)
    return backproject_rays(rays[..., 0], rays[..., 1], z)


def depth_pixel_rays(depth_m: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """:func:`pixel_rays` of ``intrinsics``, after checking that they are the depth image's size."""
    rays = pixel_rays(intrinsics)
    if depth_m.shape != rays.shape[:2]:
        raise ReconstructionError(
            f"depth image is {depth_m.shape[1]}x{depth_m.shape[0]} but the intrinsics are "
            f"{intrinsics.width}x{intrinsics.height}")
    return rays


def check_pose(T: np.ndarray, what: str = "T_world_cam") -> np.ndarray:
    """``T`` as a float64 4x4 rigid transform (:func:`darp.geometry.rigid.check_rigid`), or a ReconstructionError
    saying why not."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ReconstructionError(f"{what} must be a finite 4x4 matrix (an unposed frame has NaN)")
    return check_rigid(T, what, error=ReconstructionError)


def world_points(depth_m: np.ndarray, intrinsics: Intrinsics, T_world_cam: np.ndarray,
                 pixel_index: np.ndarray) -> np.ndarray:
    """World points (N, 3) float32 of the given flat pixel indices of a metric depth image."""
    rays = depth_pixel_rays(depth_m, intrinsics).reshape(-1, 2)
    z = depth_m.reshape(-1)[pixel_index]
    return transform_columns(T_world_cam, rays[pixel_index, 0] * z, rays[pixel_index, 1] * z, z)


# -- filters --------------------------------------------------------------------------------------
def valid_depth_mask(depth_m: np.ndarray, settings: DepthFilterSettings) -> np.ndarray:
    """Pixels with a depth inside the settings' range."""
    return (depth_m >= max(settings.min_depth_m, 1e-9)) & (depth_m <= settings.max_depth_m)


# -- the whole frame ------------------------------------------------------------------------------
def backproject(frame: PosedDepth, settings: DepthFilterSettings | None = None,
                region: Region | None = None) -> FrameCloud:
    """Back-project one frame to filtered world points (see the module docstring for the steps).

    ``region`` (e.g. :class:`darp.reconstruction.crop.EnvelopeCrop`) keeps only points inside it.
    """
    settings = settings or DepthFilterSettings()
    T = check_pose(frame.T_world_cam)
    depth = np.asarray(frame.depth)
    if depth.ndim != 2:
        raise ReconstructionError(f"depth image must be 2-D, got shape {depth.shape}")
    rays = depth_pixel_rays(depth, frame.intrinsics)
    h, w = depth.shape
    colour = None if frame.colour is None else np.asarray(frame.colour)
    if colour is not None and (colour.ndim != 3 or colour.shape[:2] != (h, w) or colour.shape[2] < 3):
        raise ReconstructionError(f"colour image {colour.shape} is not aligned to the {w}x{h} depth image")
    # candidates: valid pixels (of the window that can see the region) whose point lies in the region
    window = region_window(region, T, frame.intrinsics) if region is not None else None
    r0, r1, c0, c1 = (0, h, 0, w) if window is None else window
    depth_w = depth_to_metres(depth[r0:r1, c0:c1], frame.depth_scale)
    rows, cols = np.nonzero(valid_depth_mask(depth_w, settings))
    if region is not None and rows.size:
        z = depth_w[rows, cols]
        ray = rays[rows + r0, cols + c0]
        inside = region.contains(transform_columns(T, ray[:, 0] * z, ray[:, 1] * z, z))
        rows, cols = rows[inside], cols[inside]
    if rows.size == 0:
        return _empty_cloud(T, frame.colour is not None)

    # filters run in the candidates' bounding box, grown by the reach of the margins, stencils and
    # hole scans (so that the result is the same as on the whole image)
    pad = max(settings.edge_margin_px, settings.hole_margin_px) + max(settings.normal_step_px, HOLE_SEARCH_PX) + 1
    rows, cols = rows + r0, cols + c0
    r0, r1 = max(int(rows.min()) - pad, 0), min(int(rows.max()) + pad + 1, h)
    c0, c1 = max(int(cols.min()) - pad, 0), min(int(cols.max()) + pad + 1, w)
    rows, cols = rows - r0, cols - c0
    depth_w = depth_to_metres(depth[r0:r1, c0:c1], frame.depth_scale)
    valid_w = valid_depth_mask(depth_w, settings)
    depth_w[~valid_w] = 0.0
    intr = frame.intrinsics
    keep = edge_free_mask(depth_w, valid_w, settings, intr.fx, intr.fy)[rows, cols]
    # image borders are holes too (the window's own border is an image border only where it touches one)
    border = settings.edge_margin_px
    keep &= (rows + r0 >= border) & (rows + r0 < h - border) & (cols + c0 >= border) & (cols + c0 < w - border)
    rows, cols = rows[keep], cols[keep]

    rays_w = rays[r0:r1, c0:c1]
    pts_w = backproject_rays(rays_w[..., 0], rays_w[..., 1], depth_w)
    normals_cam, ok = normals_at(pts_w, rows, cols, settings.normal_step_px,
                                 settings.discontinuity_abs_m, settings.discontinuity_rel)
    pts_cam = pts_w[rows, cols]
    cos_incidence = -np.einsum("ij,ij->i", normals_cam, pts_cam) / np.linalg.norm(pts_cam, axis=1)
    ok &= cos_incidence >= np.float32(math.cos(math.radians(settings.max_incidence_deg)))
    pts_cam, normals_cam = pts_cam[ok], normals_cam[ok]
    candidates = (rows[ok] + r0).astype(np.int64) * w + (cols[ok] + c0)

    colours = None if colour is None else colour.reshape(h * w, -1)[candidates, :3].astype(np.uint8)
    return FrameCloud(
        points=transform_columns(T, *np.asarray(pts_cam, np.float32).T),
        normals=transform_columns(_rotation_only(T), *np.asarray(normals_cam, np.float32).T),
        colours=colours,
        pixels=candidates.astype(np.int64),
        camera_centre=T[:3, 3].copy(),
    )


def region_window(region: Region, T_world_cam: np.ndarray,
                  intrinsics: Intrinsics) -> tuple[int, int, int, int] | None:
    """Pixel rows/cols ``(r0, r1, c0, c1)`` that can see the region's bounding box, or None (all).

    The box's corners are projected with the pinhole model; with lens distortion, or when a corner
    lies behind the camera, no window is used.
    """
    bounds = getattr(region, "bounds_m", None)
    if bounds is None or _has_distortion(intrinsics):
        return None
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    T_cam_world = np.linalg.inv(T_world_cam)
    cam = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    if np.any(cam[:, 2] <= 1e-6):
        return None
    u = intrinsics.fx * cam[:, 0] / cam[:, 2] + intrinsics.ppx
    v = intrinsics.fy * cam[:, 1] / cam[:, 2] + intrinsics.ppy
    c0, c1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, intrinsics.width)
    r0, r1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, intrinsics.height)
    return (r0, max(r1, r0), c0, max(c1, c0))


def _rotation_only(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3]
    return out


def _empty_cloud(T: np.ndarray, with_colour: bool) -> FrameCloud:
    return FrameCloud(
        points=np.empty((0, 3), np.float32), normals=np.empty((0, 3), np.float32),
        colours=np.empty((0, 3), np.uint8) if with_colour else None,
        pixels=np.empty(0, np.int64), camera_centre=T[:3, 3].copy(),
    )


__all__ = [
    "DepthFilterSettings",
    "FrameCloud",
    "PosedDepth",
    "Region",
    "backproject",
    "camera_points",
    "check_pose",
    "depth_normals",
    "depth_pixel_rays",
    "depth_to_metres",
    "edge_free_mask",
    "pixel_rays",
    "region_window",
    "valid_depth_mask",
    "world_points",
]
