"""Rigid registration of depth clouds for the survey-level refinement (:mod:`darp.reconstruction.refine`): small
rigid transforms measured about a centre (angle, displacement, fractional power, mean, twists) and the
**regularised point-to-plane ICP**, a maximum a posteriori alignment: Gauss-Newton on the point-to-plane
residuals (Tukey weights, nearest neighbours from a k-d tree, coarse to fine) plus a Gaussian prior that holds
the correction near identity with the calibration's stated uncertainty, so that a direction the overlap does
not constrain stays at zero instead of drifting.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from darp.geometry.transforms import skew


class IcpSettings(Protocol):
    """What :func:`regularised_icp` reads of its settings (:class:`~darp.reconstruction.refine.RefineSettings`)."""

    @property
    def max_correspondence_m(self) -> tuple[float, ...]: ...  # scales, coarse to fine
    @property
    def iterations(self) -> int: ...  # Gauss-Newton iterations per scale
    @property
    def tukey_k_m(self) -> float: ...  # robust kernel width at the finest scale
    @property
    def point_sigma_m(self) -> float: ...  # a point-to-plane residual's standard deviation
    @property
    def min_normal_cos(self) -> float: ...  # a correspondence's normals must agree this well


# -- small rigid-transform helpers --------------------------------------------------------------------
def rotation_angle_deg(T: np.ndarray) -> float:
    """Rotation angle of a rigid transform (degrees)."""
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(np.trace(T[:3, :3])) - 1.0) / 2.0))))


def displacement_m(T: np.ndarray, point: np.ndarray) -> float:
    """How far ``T`` moves ``point`` (metres)."""
    return float(np.linalg.norm(T[:3, :3] @ point + T[:3, 3] - point))


def rigid_power(T: np.ndarray, s: float) -> np.ndarray:
    """``T`` to the power ``s`` (e.g. 0.5: the half transform), via the rotation vector and screw motion."""
    from scipy.spatial.transform import Rotation

    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    Rs = Rotation.from_rotvec(s * rotvec).as_matrix()
    theta = float(np.linalg.norm(rotvec))
    out = np.eye(4)
    out[:3, :3] = Rs
    if theta < 1e-9:
        out[:3, 3] = s * T[:3, 3]
        return out
    k = rotvec / theta
    K = skew(k)

    def V(a: float) -> np.ndarray:  # SE(3) exponential: maps the twist's translation part u to t = V u
        out: np.ndarray = np.eye(3) + (1 - math.cos(a)) / a * K + (a - math.sin(a)) / a * (K @ K)
        return out

    u = np.linalg.solve(V(theta), T[:3, 3])
    out[:3, 3] = V(s * theta) @ (s * u) if s != 0 else 0.0
    return out


def mean_transform(transforms: Sequence[np.ndarray], centre: np.ndarray) -> np.ndarray:
    """The mean rigid transform: mean rotation (chordal, scipy) and the mean position of ``centre``."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_matrix(np.array([T[:3, :3] for T in transforms])).mean().as_matrix()
    moved = np.mean([T[:3, :3] @ centre + T[:3, 3] for T in transforms], axis=0)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, moved - R @ centre
    return out


def twist_transform(xi: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The rigid transform of a twist ``(rotation vector, displacement of centre)`` about ``centre``."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
    T[:3, 3] = centre - T[:3, :3] @ centre + xi[3:]
    return T


def transform_twist(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Inverse of :func:`twist_transform`: ``(rotation vector, displacement of centre)``."""
    from scipy.spatial.transform import Rotation

    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, :3] @ centre + T[:3, 3] - centre])


@dataclass(frozen=True)
class Alignment:
    """The result of :func:`regularised_icp`."""

    T: np.ndarray  # the correction of the source (world frame)
    overlap: float  # fraction of the source points with a correspondence at the finest scale
    rmse_m: float  # robust-weighted point-to-plane RMS at the finest scale
    points: int
    information: np.ndarray | None = None  # the data's information about the twist at the end (J^T W J, 6x6)


def normal_space_weights(normals: np.ndarray) -> np.ndarray:
    """Per point, 1 / (points with a similar normal), mean 1: every surface orientation counts the same, so a
    large plane (the table) does not hold the points of the object's few other faces to where they started
    (normal-space sampling, Rusinkiewicz & Levoy 2001, as weights)."""
    keys = np.round(np.asarray(normals) * 2.0).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    w = 1.0 / counts[inverse.reshape(-1)]
    out: np.ndarray = w * (len(w) / w.sum())
    return out


def regularised_icp(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, centre: np.ndarray,
                    prior_sigma: tuple[float, float], settings: IcpSettings, init: np.ndarray | None = None,
                    tree: Any = None, exclude: tuple[np.ndarray, int] | None = None,
                    source_normals: np.ndarray | None = None) -> Alignment:
    """Point-to-plane Gauss-Newton of ``source`` onto ``target`` with a Gaussian prior on the correction.

    The correction is a twist about ``centre``: rotation vector (prior std ``prior_sigma[1]`` rad) and
    displacement of ``centre`` (prior std ``prior_sigma[0]`` m), both measured from identity (the source is
    in the uncorrected world frame; ``init`` is where to start). ``tree`` (a scipy cKDTree of ``target``)
    and ``exclude`` (target labels, the source's own label) let many views share one tree of all views.
    ``source_normals`` give the points :func:`normal_space_weights`.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(target) if tree is None else tree
    T = np.eye(4) if init is None else np.array(init, np.float64)
    prior = np.diag([1 / prior_sigma[1] ** 2] * 3 + [1 / prior_sigma[0] ** 2] * 3)
    finest = min(settings.max_correspondence_m)
    overlap, rmse, information = 0.0, math.inf, np.zeros((6, 6))
    k = 4 if exclude is not None else 1
    balance = np.ones(len(source)) if source_normals is None else normal_space_weights(source_normals)
    for distance in settings.max_correspondence_m:
        kernel = settings.tukey_k_m * distance / finest
        for _ in range(settings.iterations):
            moved = source @ T[:3, :3].T + T[:3, 3]
            dist, idx = tree.query(moved, k=k, distance_upper_bound=distance)
            if k > 1:
                labels, own = exclude  # type: ignore[misc]
                valid = np.isfinite(dist)
                safe = np.where(valid, idx, 0)
                valid &= labels[safe] != own
                first = np.argmax(valid, axis=1)
                rows = np.arange(len(moved))
                ok = valid[rows, first]
                idx = safe[rows, first]
            else:
                ok = np.isfinite(dist)
            if source_normals is not None:  # the two sides of a thin wall face opposite ways: not a match
                turned = source_normals @ T[:3, :3].T
                ok &= np.einsum("ij,ij->i", turned, target_normals[np.where(ok, idx, 0)]) >= settings.min_normal_cos
            if ok.sum() < 10:
                return Alignment(T, 0.0, math.inf, int(ok.sum()))
            p, q, n = moved[ok], target[idx[ok]], target_normals[idx[ok]]
            r = np.einsum("ij,ij->i", n, p - q)
            tukey = np.where(np.abs(r) < kernel, (1 - (r / kernel) ** 2) ** 2, 0.0)
            w = tukey * balance[ok] / settings.point_sigma_m ** 2
            J = np.hstack([np.cross(p - centre, n), n])
            xi = transform_twist(T, centre)
            H = J.T @ (J * w[:, None]) + prior
            g = J.T @ (w * r) + prior @ xi
            delta = -np.linalg.solve(H, g)
            T = twist_transform(delta, centre) @ T
            overlap = float(ok.mean())
            rmse = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-12)))
            information = H - prior
            if np.linalg.norm(delta[:3]) < 1e-7 and np.linalg.norm(delta[3:]) < 1e-7:
                break
    return Alignment(T, overlap, rmse, len(source), information)


def information_ratios(information: np.ndarray, prior_sigma: tuple[float, float]) -> np.ndarray:
    """The generalised eigenvalues of the data's information against the prior's, ascending (twists about the
    centre; ``prior_sigma`` = (displacement m, rotation rad)): how many times the prior's information the overlap
    gives along each direction. A value well below 1 is a direction the overlap does not see (the turn of a round
    object about its axis); the prior then holds the correction there."""
    s = np.array([prior_sigma[1]] * 3 + [prior_sigma[0]] * 3)
    out: np.ndarray = np.linalg.eigvalsh((information * s[:, None]) * s[None, :])
    return out


__all__ = ["Alignment", "IcpSettings", "displacement_m", "information_ratios", "mean_transform",
           "normal_space_weights", "regularised_icp", "rigid_power", "rotation_angle_deg", "transform_twist",
           "twist_transform"]
