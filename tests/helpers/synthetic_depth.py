"""Exact depth images of simple scenes for reconstruction and evaluation tests (and benchmarks/fusion.py).

Open3D's RaycastingScene is the oracle: every pixel centre (u, v) casts the ray
``R @ ((u - ppx) / fx, (v - ppy) / fy, 1)`` from the camera centre, so the returned ray parameter is
the camera-frame z of the hit. Poses follow darp's convention: ``T_world_cam`` maps camera points
(OpenCV: x right, y down, z forward) to the world.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d

from darp.formats.realsense.types import Intrinsics

D435_INTRINSICS = Intrinsics(640, 480, 383.0, 383.0, 319.5, 239.5)


def small_intrinsics(width: int = 160, height: int = 120, f: float = 96.0) -> Intrinsics:
    """A small camera (fast tests) with the D435's field of view."""
    return Intrinsics(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_cam`` of a camera at ``eye`` looking at ``target`` (image up roughly along ``up``)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def orbit_poses(centre: Sequence[float], distance_m: float, elevations_deg: Sequence[float],
                azimuths_deg: Sequence[float]) -> list[np.ndarray]:
    """Cameras on a sphere around ``centre`` looking at it (elevation above the horizontal)."""
    c = np.asarray(centre, np.float64)
    poses = []
    for el in elevations_deg:
        for az in azimuths_deg:
            e, a = np.radians(el), np.radians(az)
            eye = c + distance_m * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            poses.append(look_at(eye, c))
    return poses


class Scene:
    """Triangle meshes (legacy Open3D) cast against exactly."""

    def __init__(self, meshes: Sequence[o3d.geometry.TriangleMesh]) -> None:
        self.meshes = list(meshes)
        self.scene = o3d.t.geometry.RaycastingScene()
        for mesh in self.meshes:
            self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    def render(self, T_world_cam: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(depth_m float32 (H, W) with 0 for misses, geometry id int (H, W) with -1 for misses)."""
        u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
        d_cam = np.stack([(u - intrinsics.ppx) / intrinsics.fx, (v - intrinsics.ppy) / intrinsics.fy,
                          np.ones_like(u, dtype=np.float64)], axis=-1)
        d_world = d_cam @ T_world_cam[:3, :3].T
        origin = np.broadcast_to(T_world_cam[:3, 3], d_world.shape)
        rays = np.concatenate([origin, d_world], axis=-1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy()
        geometry = hit["geometry_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t)
        depth = np.where(miss, 0.0, t).astype(np.float32)
        geometry[miss] = -1
        return depth, geometry


def sphere(radius: float, centre: Sequence[float], resolution: int = 120) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution)
    mesh.translate(np.asarray(centre, np.float64))
    return mesh


def box(size: Sequence[float], min_corner: Sequence[float]) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(np.asarray(min_corner, np.float64))
    return mesh


def table(size_m: float = 1.0, z_m: float = 0.0) -> o3d.geometry.TriangleMesh:
    """A thin slab whose top face is the plane z = ``z_m``."""
    return box((size_m, size_m, 0.01), (-size_m / 2, -size_m / 2, z_m - 0.01))


def to_z16(depth_m: np.ndarray, depth_scale: float = 0.001) -> np.ndarray:
    """Metric depth to raw Z16 units (rounded), 0 stays 0."""
    return np.clip(np.rint(depth_m / depth_scale), 0, 65535).astype(np.uint16)


def add_depth_noise(depth_m: np.ndarray, rng: np.random.Generator, fx: float = 383.0, baseline_m: float = 0.05,
                    subpixel_px: float = 0.08) -> np.ndarray:
    """D4-like noise: depth sigma = z^2 * subpixel / (fx * baseline) per pixel (uncorrelated)."""
    sigma = depth_m.astype(np.float64) ** 2 * subpixel_px / (fx * baseline_m)
    noisy = depth_m + rng.normal(size=depth_m.shape) * sigma
    return np.where(depth_m > 0, noisy, 0.0).astype(np.float32)
