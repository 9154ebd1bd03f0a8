"""Cross-arm consistency on two partial samplings of one plane with a known separation."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import EvaluationError
from darp.evaluation.cross_arm import co_observed, cross_arm_consistency


def plane_patch(x_range: tuple[float, float], z: float, spacing: float = 0.0015) -> np.ndarray:
    xs = np.arange(x_range[0], x_range[1], spacing)
    ys = np.arange(-0.03, 0.03, spacing)
    x, y = np.meshgrid(xs, ys)
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def test_known_separation_in_the_overlap_both_directions() -> None:
    a = plane_patch((-0.05, 0.01), 0.0)  # arm A saw x < 1 cm
    b = plane_patch((-0.01 + 0.0007, 0.05), 0.002)  # arm B saw x > -1 cm, 2 mm higher, offset grid
    up = np.tile([0.0, 0.0, 1.0], (len(b), 1))
    result = cross_arm_consistency(a, b, normals_a=np.tile([0.0, 0.0, 1.0], (len(a), 1)), normals_b=up)
    for direction in (result.a_to_b, result.b_to_a):
        assert direction.point_to_plane.median_m == pytest.approx(0.002, abs=1e-9)
        assert direction.point_to_plane.p90_m == pytest.approx(0.002, abs=1e-9)
        assert 0.002 < direction.point_to_point.median_m < 0.0025  # includes the lateral grid offset
    # the co-observed points are those of the 2 cm wide overlap strip (not the rest of each patch)
    overlap_a = np.count_nonzero((a[:, 0] >= -0.0093) & (a[:, 0] <= 0.01))
    assert abs(result.a_to_b.n_co_observed - overlap_a) <= 2 * 40
    assert result.a_to_b.n_co_observed < 0.5 * len(a)
    assert result.to_dict()["directions"][0]["co_observed_pct"] < 50


def test_without_normals_point_to_plane_falls_back_to_point_to_point() -> None:
    a = plane_patch((-0.02, 0.02), 0.0)
    b = plane_patch((-0.02, 0.02), 0.001)
    result = cross_arm_consistency(a, b)
    assert result.a_to_b.point_to_plane.median_m == pytest.approx(result.a_to_b.point_to_point.median_m)
    assert result.a_to_b.point_to_point.median_m == pytest.approx(0.001, abs=1e-9)


def test_disjoint_clouds_have_no_overlap() -> None:
    a = plane_patch((-0.05, -0.03), 0.0)
    b = plane_patch((0.03, 0.05), 0.0)
    assert not co_observed(a, b, 0.005).any()
    result = cross_arm_consistency(a, b)
    assert result.a_to_b.n_co_observed == 0 and np.isnan(result.a_to_b.point_to_plane.median_m)
    with pytest.raises(EvaluationError, match="normals"):
        cross_arm_consistency(a, b, normals_a=np.zeros((3, 3)))


def test_opposite_faces_of_a_thin_wall_are_not_paired() -> None:
    """A wall 3 mm thick seen from outside by one arm and inside by the other is two surfaces."""
    from darp.evaluation.cross_arm import cross_arm_consistency

    g = np.stack(np.meshgrid(np.linspace(0, 0.05, 60), np.linspace(0, 0.05, 60)), -1).reshape(-1, 2)
    outer = np.column_stack([g, np.zeros(len(g))])
    inner = np.column_stack([g, np.full(len(g), 0.003)])
    up = np.tile([0.0, 0.0, -1.0], (len(g), 1))
    down = -up
    paired = cross_arm_consistency(outer, inner, normals_a=up, normals_b=up, cell_m=0.005)
    assert paired.a_to_b.point_to_plane.median_m == pytest.approx(0.003, abs=1e-4)
    separate = cross_arm_consistency(outer, inner, normals_a=up, normals_b=down, cell_m=0.005)
    assert separate.a_to_b.n_co_observed == 0 and separate.b_to_a.n_co_observed == 0
