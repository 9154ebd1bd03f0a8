"""``MeshSettings.split_sides``: a surface whose fused normals point both ways (half of the points flipped,
as on the seed-3 mug's patch in docs/accuracy.md) is meshed; plain ball pivoting stops at every pair of
neighbours whose normals disagree. Both faces of a thin wall stay meshed."""

from __future__ import annotations

import numpy as np
import pytest

from darp.evaluation.point_to_mesh import MeshDistance
from darp.processing.settings import ProcessSettings
from darp.reconstruction.mesh import MeshSettings, ball_pivoting_mesh, normal_sides

SPACING = 0.0015


def _shell(radius: float, inward: bool, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points on a vertical cylinder (40 mm high), normals along -radial when ``inward``."""
    n_around = int(2 * np.pi * radius / SPACING)
    a, z = np.meshgrid(np.linspace(0, 2 * np.pi, n_around, endpoint=False), np.arange(0.01, 0.05, SPACING))
    a, z = a.ravel() + rng.normal(0, 0.1 * SPACING / radius, a.size), z.ravel()
    radial = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    points = radial * radius + np.column_stack([np.zeros((a.size, 2)), z])
    return points, -radial if inward else radial


@pytest.fixture(scope="module")
def wall() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    outer = _shell(0.040, False, rng)
    inner = _shell(0.0385, True, rng)  # the wall's other face, 1.5 mm in (one point spacing)
    return outer[0], outer[1], inner[0], inner[1]


def _covered(mesh: object, points: np.ndarray) -> float:
    import open3d as o3d

    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    if len(mesh.triangles) == 0:
        return 0.0
    d = MeshDistance(np.asarray(mesh.vertices), np.asarray(mesh.triangles)).distances(points)
    return float(np.mean(d < 0.5 * SPACING))


def test_normal_sides_follow_the_wall_faces(wall: tuple[np.ndarray, ...]) -> None:
    po, no, pi, ni = wall
    outward, inward = normal_sides(np.vstack([po, pi]), np.vstack([no, ni]))
    assert outward[: len(po)].all() and inward[len(po):].all() and not (outward & inward).any()


def test_split_sides_meshes_a_surface_with_normals_both_ways() -> None:
    rng = np.random.default_rng(1)
    points, normals = _shell(0.040, False, rng)
    points = points + rng.normal(0, 0.0003, points.shape) * [1, 1, 0]  # 0.3 mm radial depth noise
    normals = np.where((rng.random(len(points)) < 0.5)[:, None], -normals, normals)
    plain = ball_pivoting_mesh(points, normals, settings=MeshSettings(spacing_m=SPACING))
    split = ball_pivoting_mesh(points, normals, settings=MeshSettings(spacing_m=SPACING, split_sides=True))
    assert _covered(plain, points) < 0.4  # plain pivoting: a few pieces (0.20 when written)
    assert _covered(split, points) > 0.95  # split: the whole surface (0.997)


def test_split_sides_keeps_both_faces_of_a_thin_wall(wall: tuple[np.ndarray, ...]) -> None:
    po, no, pi, ni = wall
    split = ball_pivoting_mesh(np.vstack([po, pi]), np.vstack([no, ni]),
                               settings=MeshSettings(spacing_m=SPACING, split_sides=True))
    assert _covered(split, pi) > 0.95 and _covered(split, po) > 0.95


def test_split_sides_is_off_by_default_and_left_out_of_records() -> None:
    assert MeshSettings().split_sides is False
    assert "split_sides" not in ProcessSettings().to_dict()["mesh"]
    on = ProcessSettings(mesh=MeshSettings(split_sides=True))
    assert on.to_dict()["mesh"]["split_sides"] is True
    assert on.fingerprint("mesh") != ProcessSettings().fingerprint("mesh")
