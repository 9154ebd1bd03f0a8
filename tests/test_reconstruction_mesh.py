"""Ball pivoting: vertices on the sampled surface, outward triangles, unobserved regions left open."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from darp.errors import ReconstructionError
from darp.reconstruction.cloud_io import read_mesh_ply
from darp.reconstruction.mesh import (
    MeshSettings,
    ball_pivoting_mesh,
    ball_pivoting_radii,
    boundary_edges,
    mesh_area,
    mesh_arrays,
    point_spacing,
    write_mesh,
)

R = 0.04


def fibonacci_sphere(n: int, radius: float = R) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (3 - np.sqrt(5)) * i
    return radius * np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def test_sphere_mesh_lies_on_the_samples_and_faces_outward() -> None:
    pts = fibonacci_sphere(6000)
    mesh = ball_pivoting_mesh(pts, pts / R)
    v, t = mesh_arrays(mesh)
    assert len(t) > 10000
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), R, atol=1e-9)  # vertices are input points
    centroids = v[t].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", np.asarray(mesh.triangle_normals), centroids) > 0)
    assert mesh_area(mesh) == pytest.approx(4 * np.pi * R**2, rel=0.03)
    assert len(boundary_edges(t)) < 0.01 * len(t)  # essentially closed: the whole sphere was sampled


def test_hemisphere_stays_open_where_nothing_was_seen() -> None:
    pts = fibonacci_sphere(8000)
    pts = pts[pts[:, 2] >= 0.0]
    mesh = ball_pivoting_mesh(pts, pts / R)
    v, t = mesh_arrays(mesh)
    rim = boundary_edges(t)
    assert len(rim) > 50, "the open side of the hemisphere was closed"
    rim_z = v[np.unique(rim)][:, 2]
    assert np.percentile(rim_z, 90) < 0.004  # the boundary runs along the equator, not through holes
    assert v[t].mean(axis=1)[:, 2].min() > -1e-9  # no triangle spans the opening
    assert mesh_area(mesh) == pytest.approx(2 * np.pi * R**2, rel=0.05)


def test_radii_follow_the_spacing() -> None:
    grid = np.stack(np.meshgrid(np.arange(30), np.arange(30)), -1).reshape(-1, 2) * 0.002
    pts = np.column_stack([grid, np.zeros(len(grid))])
    assert point_spacing(pts) == pytest.approx(0.002)
    assert ball_pivoting_radii(pts) == pytest.approx([0.004, 0.008, 0.016])
    assert ball_pivoting_radii(pts, MeshSettings(radius_factors=(3.0, 1.0), spacing_m=0.001)) == \
        pytest.approx([0.001, 0.003])


def test_bad_inputs_are_refused() -> None:
    pts = fibonacci_sphere(100)
    with pytest.raises(ReconstructionError, match="unit normals"):
        ball_pivoting_mesh(pts, pts)
    with pytest.raises(ReconstructionError, match=r"\(N, 3\)"):
        ball_pivoting_mesh(pts, pts[:10] / R)
    with pytest.raises(ReconstructionError, match="cannot mesh"):
        ball_pivoting_mesh(pts[:2], pts[:2] / R)
    with pytest.raises(ReconstructionError, match="radius_factors"):
        MeshSettings(radius_factors=())


def test_mesh_ply_is_readable_by_open3d_and_darp(tmp_path) -> None:
    pts = fibonacci_sphere(3000)
    mesh = ball_pivoting_mesh(pts, pts / R, np.tile([200, 30, 10], (len(pts), 1)).astype(np.uint8))
    path = write_mesh(tmp_path / "mesh.ply", mesh)
    v, t = read_mesh_ply(path)
    np.testing.assert_allclose(v, np.asarray(mesh.vertices), atol=1e-7)
    np.testing.assert_array_equal(t, np.asarray(mesh.triangles))
    theirs = o3d.io.read_triangle_mesh(str(path))
    np.testing.assert_array_equal(np.asarray(theirs.triangles), t)
    assert np.allclose(np.asarray(theirs.vertex_colors)[0], np.array([200, 30, 10]) / 255.0)
    assert not list(tmp_path.glob("*.partial"))
