"""Colour-to-depth alignment: the colour image resampled onto the depth image's pixel grid.

For every depth pixel ``(u, v)`` with depth ``z`` (metres):

1. the camera-frame point ``p_d = z * ray(u, v)`` (undistorted rays of the depth intrinsics, the same
   rays fusion uses: :func:`darp.reconstruction.backproject.pixel_rays`);
2. ``p_c = T_colour_depth @ p_d`` (the recording's depth -> colour extrinsic);
3. ``(u_c, v_c)`` = projection of ``p_c`` with the colour intrinsics and their distortion model
   (librealsense's ``rs2_project_point_to_pixel``: "Brown Conrady" as OpenCV; "Modified" and
   "Inverse Brown Conrady" with the tangential terms on the radially scaled coordinates);
4. the aligned pixel takes the colour of the nearest colour pixel (no blending across edges).

Depth pixels without depth, projecting outside the colour image, behind the colour camera, or hidden
from it by a nearer surface (a z-buffer over the projected depth points, widened by one pixel so that
sparse foreground points still cover the colour pixels between them) get colour 0. The colour camera
sits ~15 mm beside the left imager, so near a silhouette the background seen by the depth camera can
be occluded from the colour camera: without the test it would take the object's colour.

Vectorised numpy (one pass over the valid depth pixels), plus one OpenCV erosion for the z-buffer.
"""

from __future__ import annotations

import math

import numpy as np

from darp.errors import ReconstructionError
from darp.formats.realsense.types import Intrinsics
from darp.reconstruction.backproject import check_pose, depth_pixel_rays, depth_to_metres

DEFAULT_OCCLUSION_TOLERANCE_M = 0.01  # deeper than the z-buffer by more than this (+1 % of z): hidden
_MODIFIED_MODELS = ("inverse brown conrady", "modified brown conrady")


def _has_distortion(intrinsics: Intrinsics) -> bool:
    return intrinsics.model.lower() != "none" and any(abs(c) > 0.0 for c in intrinsics.coeffs)


def project_points(points_cam: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates ``(u, v)`` (float64) of camera-frame points, and a mask of points in front (z > 0).

    Pixel centres are at integer coordinates; the distortion follows librealsense's projection.
    """
    p = np.asarray(points_cam, np.float64).reshape(-1, 3)
    z = p[:, 2]
    front = z > 1e-9
    safe_z = np.where(front, z, 1.0)
    x, y = p[:, 0] / safe_z, p[:, 1] / safe_z
    if _has_distortion(intrinsics):
        model = intrinsics.model.lower()
        k1, k2, p1, p2, k3 = (float(c) for c in intrinsics.coeffs)
        r2 = x * x + y * y
        f = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        if model == "brown conrady":
            x, y = (x * f + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * f + 2 * p2 * x * y + p1 * (r2 + 2 * y * y))
        elif model in _MODIFIED_MODELS:
            x, y = x * f, y * f
            x, y = x + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        else:
            raise ReconstructionError(
                f"cannot project through {intrinsics.model!r} distortion with non-zero coefficients "
                f"{intrinsics.coeffs} (supported: Brown Conrady, Modified/Inverse Brown Conrady)")
    return x * intrinsics.fx + intrinsics.ppx, y * intrinsics.fy + intrinsics.ppy, front


def colour_to_rgb(image: np.ndarray, pixel_format: str) -> np.ndarray:
    """An (H, W, 3) RGB uint8 view of a decoded colour frame (bgr8, rgb8, bgra8, rgba8, y8)."""
    fmt = pixel_format.lower()
    img = np.asarray(image)
    if fmt in ("rgb8", "rgba8"):
        return np.ascontiguousarray(img[..., :3])
    if fmt in ("bgr8", "bgra8"):
        return np.ascontiguousarray(img[..., 2::-1])
    if fmt in ("y8", "mono8") and img.ndim == 2:
        return np.repeat(img[..., None], 3, axis=2)
    raise ReconstructionError(f"cannot turn colour pixel format {pixel_format!r} into RGB")


def colour_pixel_of_depth(depth_m: np.ndarray, depth_intrinsics: Intrinsics, colour_intrinsics: Intrinsics,
                          T_colour_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For the pixels with depth: their flat indices, colour-camera depth and colour pixel ``(u_c, v_c)``."""
    T = check_pose(T_colour_depth, "T_colour_depth")
    rays = depth_pixel_rays(depth_m, depth_intrinsics)
    flat = np.flatnonzero(depth_m > 0)
    z = depth_m.reshape(-1)[flat].astype(np.float64)
    ray_x, ray_y = (rays[..., i].reshape(-1)[flat].astype(np.float64) for i in (0, 1))
    x, y = ray_x * z, ray_y * z
    R, t = T[:3, :3], T[:3, 3]
    # column by column: numpy's (N, 3) @ (3, 3) matmul is several times slower than this
    p_c = np.empty((flat.size, 3))
    for i in range(3):
        p_c[:, i] = R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i]
    u, v, front = project_points(p_c, colour_intrinsics)
    return flat, np.where(front, p_c[:, 2], np.nan), u, v


def align_colour_to_depth(depth: np.ndarray, depth_scale: float, depth_intrinsics: Intrinsics,
                          colour_rgb: np.ndarray, colour_intrinsics: Intrinsics, T_colour_depth: np.ndarray, *,
                          occlusion: bool = True,
                          occlusion_tolerance_m: float = DEFAULT_OCCLUSION_TOLERANCE_M) -> np.ndarray:
    """(H, W, 3) uint8 colour for every depth pixel (module docstring); 0 where unseen.

    ``depth`` is raw Z16 (with ``depth_scale``) or metric float depth (scale 1); ``colour_rgb`` is
    (Hc, Wc, 3) of the colour intrinsics' size.
    """
    import cv2  # heavy: loaded when depth images are filtered, not when darp is imported
    colour = np.asarray(colour_rgb)
    if colour.ndim != 3 or colour.shape[:2] != (colour_intrinsics.height, colour_intrinsics.width):
        raise ReconstructionError(
            f"colour image {colour.shape} does not match its intrinsics "
            f"{colour_intrinsics.width}x{colour_intrinsics.height}")
    if not (math.isfinite(occlusion_tolerance_m) and occlusion_tolerance_m >= 0):
        raise ReconstructionError(f"occlusion tolerance must be >= 0, got {occlusion_tolerance_m}")
    depth_m = depth_to_metres(np.asarray(depth), depth_scale)
    h, w = depth_m.shape
    aligned = np.zeros((h, w, colour.shape[2]), colour.dtype)
    flat, z_c, u, v = colour_pixel_of_depth(depth_m, depth_intrinsics, colour_intrinsics, T_colour_depth)
    ui, vi = np.rint(u), np.rint(v)
    ok = (np.isfinite(z_c) & (ui >= 0) & (ui < colour_intrinsics.width) & (vi >= 0)
          & (vi < colour_intrinsics.height))
    flat, z_c, ui, vi = flat[ok], z_c[ok], ui[ok].astype(np.int64), vi[ok].astype(np.int64)
    target = vi * colour_intrinsics.width + ui
    if occlusion and flat.size:
        zbuf: np.ndarray = np.full(colour_intrinsics.height * colour_intrinsics.width, np.inf, np.float32)
        np.minimum.at(zbuf, target, z_c.astype(np.float32))
        zbuf = cv2.erode(zbuf.reshape(colour_intrinsics.height, colour_intrinsics.width),
                         np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf).reshape(-1)
        visible = z_c <= zbuf[target] + occlusion_tolerance_m + 0.01 * z_c
        flat, target = flat[visible], target[visible]
    aligned.reshape(h * w, -1)[flat] = colour.reshape(-1, colour.shape[2])[target]
    return aligned


__all__ = [
    "DEFAULT_OCCLUSION_TOLERANCE_M",
    "align_colour_to_depth",
    "colour_pixel_of_depth",
    "colour_to_rgb",
    "project_points",
]
