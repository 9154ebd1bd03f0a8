"""Cross-arm consistency: how far apart the two arms' partial clouds are where both saw the object.

Each arm's cloud comes from its own keyframes and eq. 1 poses only, so in the co-observed region the
remaining separation measures the calibration (hand-eye, base-to-base, joint zeros) and the pose
timing, not any registration (there is none).

Co-observed region: space is cut into cubic cells of ``cell_m``; a point of arm A is co-observed when
arm B has at least ``min_points`` points in the same cell or one of its 26 neighbours (so a
misalignment up to about one cell still counts as overlap instead of hiding it). For those points the
distance to the other arm's surface is measured two ways: to the nearest point (point-to-point, which
includes up to half the sampling spacing) and along the other point's normal (point-to-plane, the
surface separation), in both directions A->B and B->A. With normals, points whose nearest neighbour
lies more than ``max_lateral_m`` beside (not below) them are beyond the other arm's rim and left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from darp.errors import EvaluationError
from darp.evaluation.point_to_mesh import DistanceStats, distance_stats
from darp.reconstruction.voxel_stats import pack_keys, voxel_indices

DEFAULT_CELL_M = 0.005
DEFAULT_MAX_LATERAL_M = 0.002  # about the fused clouds' point spacing (1.5 mm voxels)
DEFAULT_MIN_NORMAL_DOT = 0.5  # paired points' normals within 60 deg: the same side of the surface
_NEIGHBOUR_OFFSETS = np.array([[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], np.int64)


def co_observed(points_a: np.ndarray, points_b: np.ndarray, cell_m: float = DEFAULT_CELL_M,
                min_points: int = 1) -> np.ndarray:
    """Boolean (N_a,): points of A with at least ``min_points`` B points in their cell or its neighbours."""
    if not cell_m > 0 or min_points < 1:
        raise EvaluationError("co_observed: cell_m must be > 0 and min_points >= 1")
    if len(points_a) == 0 or len(points_b) == 0:
        return np.zeros(len(points_a), bool)
    keys_b, counts_b = np.unique(pack_keys(voxel_indices(points_b, cell_m)), return_counts=True)
    occupied = keys_b[counts_b >= min_points]
    ijk_a = voxel_indices(points_a, cell_m)
    found = np.zeros(len(points_a), bool)
    if occupied.size == 0:
        return found
    for offset in _NEIGHBOUR_OFFSETS:  # occupied is sorted (np.unique): binary search per neighbour cell
        keys = pack_keys(ijk_a + offset)
        pos = np.minimum(np.searchsorted(occupied, keys), occupied.size - 1)
        found |= occupied[pos] == keys
    return found


@dataclass(frozen=True)
class DirectionResult:
    """Distances from one arm's co-observed points to the other arm's cloud."""

    source: str
    target: str
    n_points: int  # points of the source arm
    n_co_observed: int
    point_to_point: DistanceStats
    point_to_plane: DistanceStats

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source, "target": self.target, "points": self.n_points,
            "co_observed": self.n_co_observed,
            "co_observed_pct": round(100.0 * self.n_co_observed / self.n_points, 3) if self.n_points else None,
            "point_to_point": self.point_to_point.to_dict(),
            "point_to_plane": self.point_to_plane.to_dict(),
        }


@dataclass(frozen=True)
class CrossArmResult:
    """Both directions of the cross-arm comparison."""

    a_to_b: DirectionResult
    b_to_a: DirectionResult
    cell_m: float

    def to_dict(self) -> dict[str, Any]:
        return {"cell_mm": self.cell_m * 1000.0, "directions": [self.a_to_b.to_dict(), self.b_to_a.to_dict()]}


def _direction(name_a: str, points_a: np.ndarray, normals_a: np.ndarray | None, name_b: str,
               points_b: np.ndarray, normals_b: np.ndarray | None, cell_m: float, min_points: int,
               max_lateral_m: float, min_normal_dot: float) -> DirectionResult:
    mask = co_observed(points_a, points_b, cell_m, min_points)
    query = np.asarray(points_a, np.float64)[mask]
    dist = plane = np.empty(0)
    n_co = int(mask.sum())
    if query.shape[0]:
        dist, idx = cKDTree(np.asarray(points_b, np.float64)).query(query, k=1, workers=-1)
        plane = dist
        if normals_b is not None:
            diff = query - np.asarray(points_b, np.float64)[idx]
            plane = np.abs(np.einsum("ij,ij->i", diff, np.asarray(normals_b, np.float64)[idx]))
            # beyond the other arm's rim the nearest point lies beside, not below: not co-observed
            lateral = np.sqrt(np.maximum(dist * dist - plane * plane, 0.0))
            under = lateral <= max_lateral_m
            if normals_a is not None:
                # the two sides of a thin wall (a mug seen outside by one arm, inside by the other) are
                # different surfaces: pair only points whose normals agree
                agree = np.einsum("ij,ij->i", np.asarray(normals_a, np.float64)[mask],
                                  np.asarray(normals_b, np.float64)[idx])
                under &= agree >= min_normal_dot
            dist, plane, n_co = dist[under], plane[under], int(under.sum())
    return DirectionResult(name_a, name_b, len(points_a), n_co, distance_stats(dist), distance_stats(plane))


def cross_arm_consistency(points_a: np.ndarray, points_b: np.ndarray, *, normals_a: np.ndarray | None = None,
                          normals_b: np.ndarray | None = None, names: tuple[str, str] = ("arm110", "arm111"),
                          cell_m: float = DEFAULT_CELL_M, min_points: int = 3,
                          max_lateral_m: float = DEFAULT_MAX_LATERAL_M,
                          min_normal_dot: float = DEFAULT_MIN_NORMAL_DOT) -> CrossArmResult:
    """Median/p90 separation of the two arms' clouds in their co-observed region, both directions.

    With the target's normals, a point also needs its nearest target point within ``max_lateral_m``
    of the foot of its normal (so points beyond the other arm's rim do not count as overlap).
    With both arms' normals, paired points must also face the same way (normal dot product at least
    ``min_normal_dot``), so opposite faces of a thin wall are not taken for one surface.
    Without normals the point-to-plane statistics equal the point-to-point ones.
    """
    for pts, nrm, name in ((points_a, normals_a, names[0]), (points_b, normals_b, names[1])):
        if np.asarray(pts).ndim != 2 or np.asarray(pts).shape[1] != 3:
            raise EvaluationError(f"{name}: points must be (N, 3)")
        if nrm is not None and np.asarray(nrm).shape != np.asarray(pts).shape:
            raise EvaluationError(f"{name}: normals must have the points' shape")
    return CrossArmResult(
        a_to_b=_direction(names[0], points_a, normals_a, names[1], points_b, normals_b, cell_m, min_points,
                          max_lateral_m, min_normal_dot),
        b_to_a=_direction(names[1], points_b, normals_b, names[0], points_a, normals_a, cell_m, min_points,
                          max_lateral_m, min_normal_dot),
        cell_m=cell_m,
    )


__all__ = ["DEFAULT_CELL_M", "DEFAULT_MAX_LATERAL_M", "DEFAULT_MIN_NORMAL_DOT", "CrossArmResult", "DirectionResult",
           "co_observed", "cross_arm_consistency"]
