"""Point-cloud filters of the fused cloud: statistical outlier removal and the local surface fit (docs/processing.md
section 3, steps 3-4). Split out of :mod:`darp.reconstruction.fusion`, which re-exports them."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def statistical_outliers(points: np.ndarray, neighbours: int, std_ratio: float,
                         local_ratio: float = 0.0) -> np.ndarray:
    """Boolean (N,) inliers: mean distance to the ``neighbours`` nearest points <= mean + ratio * std.

    The same rule as Open3D's ``remove_statistical_outlier`` (population std over the cloud). With
    ``local_ratio`` > 0 a point that rule rejects is kept when its mean distance is at most ``local_ratio``
    times the median of its neighbours' mean distances: a uniformly sparse region (a rim or a side seen by
    few frames) is as sparse as its neighbours and stays; a stray point beside a denser surface still goes.
    """
    n = points.shape[0]
    if neighbours <= 0 or n <= neighbours:
        return np.ones(n, bool)
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=neighbours + 1, workers=-1)  # the first neighbour is the point itself
    mean_d = dist[:, 1:].mean(axis=1)
    inliers: np.ndarray = mean_d <= mean_d.mean() + std_ratio * mean_d.std()
    if local_ratio > 0:
        out = np.flatnonzero(~inliers)
        inliers[out] = mean_d[out] <= local_ratio * np.median(mean_d[idx[out, 1:]], axis=1)
    return inliers


def fit_to_local_surface(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, radius_m: float,
                         neighbours: int) -> np.ndarray:
    """Move each point along its normal onto the weighted mean plane of its neighbours within ``radius_m``.

    Voxel means of noisy depth form a layer a few noise sigmas thick; this order-1 moving-least-squares
    step collapses it onto the surface (and lets ball pivoting use every point). It only moves points
    along their own normals, by at most ``radius_m``; it rounds edges sharper than the radius.
    """
    n = points.shape[0]
    if radius_m <= 0 or n < 2:
        return points
    k = min(neighbours, n)
    p = points.astype(np.float64)
    dist, idx = cKDTree(p).query(p, k=k, distance_upper_bound=radius_m, workers=-1)
    found = np.isfinite(dist)
    idx = np.where(found, idx, 0)
    w = np.where(found, weights[idx].astype(np.float64), 0.0)
    offsets = np.einsum("ikj,ij->ik", p[idx] - p[:, None, :], normals.astype(np.float64))
    shift = (w * offsets).sum(axis=1) / w.sum(axis=1)  # the point itself is always found (w > 0)
    fitted: np.ndarray = (p + shift[:, None] * normals).astype(np.float32)
    return fitted


__all__ = ["fit_to_local_surface", "statistical_outliers"]
