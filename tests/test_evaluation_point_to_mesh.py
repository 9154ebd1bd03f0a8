"""Point-to-mesh distances against analytic distances to a box, and the statistics against numpy."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from darp.errors import EvaluationError
from darp.evaluation.point_to_mesh import MeshDistance, distance_stats, point_to_mesh_distances

HALF = np.array([0.03, 0.02, 0.05])


def box_distance(p: np.ndarray) -> np.ndarray:
    """Exact unsigned distance to the surface of the box [-HALF, HALF]."""
    q = np.abs(p) - HALF
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = -np.max(q, axis=1)
    return np.where(np.all(q <= 0, axis=1), inside, outside)


@pytest.fixture(scope="module")
def box_mesh() -> MeshDistance:
    box = trimesh.creation.box(extents=2 * HALF)
    return MeshDistance(box.vertices, box.faces)


def test_distances_are_exact_for_a_box(box_mesh: MeshDistance) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.08, 0.08, size=(20000, 3))
    np.testing.assert_allclose(box_mesh.distances(pts), box_distance(pts), atol=2e-7)
    # points at known offsets from the top face, its edge and its corner
    known = np.array([[0.0, 0.0, 0.05 + 0.004], [0.0, 0.0, 0.05 - 0.003], [0.03 + 0.003, 0.0, 0.05 + 0.004],
                      [0.03 + 0.001, 0.02 + 0.002, 0.05 + 0.002]])
    np.testing.assert_allclose(box_mesh.distances(known), [0.004, 0.003, 0.005, 0.003], atol=2e-7)
    closest, tri = box_mesh.closest_points(known[:1])
    np.testing.assert_allclose(closest, [[0.0, 0.0, 0.05]], atol=1e-7)
    assert 0 <= tri[0] < box_mesh.n_triangles


def test_one_shot_helper_and_bad_meshes() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    assert point_to_mesh_distances(np.array([[0.2, 0.2, 0.5]]), v, np.array([[0, 1, 2]]))[0] == pytest.approx(0.5)
    with pytest.raises(EvaluationError, match="no triangles"):
        MeshDistance(v, np.empty((0, 3), int))
    with pytest.raises(EvaluationError, match="past the vertex"):
        MeshDistance(v, np.array([[0, 1, 3]]))
    with pytest.raises(EvaluationError, match="NaN"):
        MeshDistance(v, np.array([[0, 1, 2]])).distances(np.array([[np.nan, 0, 0]]))


def test_statistics_match_numpy() -> None:
    d = np.array([0.001, 0.002, 0.003, 0.004, 0.006, 0.008, 0.011, 0.020])
    s = distance_stats(d)
    assert s.count == 8
    assert s.median_m == pytest.approx(0.005)
    assert s.mean_m == pytest.approx(d.mean())
    assert s.rmse_m == pytest.approx(np.sqrt(np.mean(d**2)))
    assert s.p90_m == pytest.approx(np.percentile(d, 90))  # 0.0137 by linear interpolation
    assert s.p90_m == pytest.approx(0.011 + 0.3 * 0.009)
    assert s.max_m == pytest.approx(0.020)
    assert s.within_pct == pytest.approx({0.005: 50.0, 0.010: 75.0})
    out = s.to_dict()
    assert out["median_mm"] == pytest.approx(5.0) and out["within_5mm_pct"] == pytest.approx(50.0)
    assert out["within_10mm_pct"] == pytest.approx(75.0)


def test_statistics_of_nothing_and_of_bad_values() -> None:
    empty = distance_stats(np.empty(0))
    assert empty.count == 0 and np.isnan(empty.median_m)
    assert empty.to_dict()["median_mm"] is None
    with pytest.raises(EvaluationError, match="non-negative"):
        distance_stats(np.array([0.001, -0.002]))
