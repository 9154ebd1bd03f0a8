"""Small geometry shared by the calibration modules: pose perturbations, pinhole projection, undistortion.

Poses are perturbed on the right, ``T = T0 @ delta(xi)`` with ``xi = (rotvec, translation)`` in the
frame of ``T0``, so the optimiser's parameters start at zero and stay far from the rotation-vector
singularity at pi whatever the pose.

Detected pixels are *undistorted* once, with the stream's own distortion model, to the ideal pinhole
image of the same ``K``; everything after works with a plain pinhole. librealsense's models, as its
``rs2_project_point_to_pixel`` applies them (ideal -> distorted; inverted here by fixed-point iteration,
as ``rs2_deproject_pixel_to_point`` does):

- ``Brown Conrady``: OpenCV's k1, k2, p1, p2, k3;
- ``Modified Brown Conrady`` and ``Inverse Brown Conrady``: the radial factor first, then the
  tangential terms on the radially distorted point (with the undistorted radius);
- ``None``, or any model with all coefficients zero: nothing to do.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from darp.errors import CalibrationError
from darp.formats.realsense.types import Intrinsics
from darp.kinematics.transforms import rotation_to_rotvec, rotvec_to_rotation

FORWARD_MODELS = ("Brown Conrady", "Modified Brown Conrady", "Inverse Brown Conrady")
MODIFIED_MODELS = ("Modified Brown Conrady", "Inverse Brown Conrady")


def delta(xi: np.ndarray) -> np.ndarray:
    """4x4 (or (..., 4, 4)) transform of a 6-vector perturbation ``(rotvec, translation)``."""
    xi = np.asarray(xi, dtype=np.float64)
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotvec_to_rotation(xi[..., :3])
    T[..., :3, 3] = xi[..., 3:]
    T[..., 3, 3] = 1.0
    return T


def log_delta(T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`delta`: ``(rotvec, translation)`` of a transform."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([rotation_to_rotvec(T[..., :3, :3]), T[..., :3, 3]], axis=-1)


def project(P_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points (..., 3) to pixels (..., 2)."""
    z = P_cam[..., 2:3]
    return cast(np.ndarray, (P_cam[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]]))


def transform(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply transforms (..., 4, 4) to points (..., N, 3) (broadcasting the transform over N)."""
    return cast(np.ndarray, np.einsum("...ij,...nj->...ni", T[..., :3, :3], P) + T[..., None, :3, 3])


def _brown(x: np.ndarray, y: np.ndarray, c: np.ndarray, modified: bool) -> tuple[np.ndarray, np.ndarray]:
    r2 = x * x + y * y
    f = 1.0 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2
    if modified:  # tangential terms on the radially distorted point, with the undistorted radius
        x, y = x * f, y * f
        return (x + 2.0 * c[2] * x * y + c[3] * (r2 + 2.0 * x * x),
                y + 2.0 * c[3] * x * y + c[2] * (r2 + 2.0 * y * y))
    return (x * f + 2.0 * c[2] * x * y + c[3] * (r2 + 2.0 * x * x),
            y * f + 2.0 * c[3] * x * y + c[2] * (r2 + 2.0 * y * y))


def undistort_pixels(uv: np.ndarray, intr: Intrinsics, iterations: int = 20) -> np.ndarray:
    """Pixels (N, 2) of a stream -> pixels of the ideal pinhole camera with the same K."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    c = np.asarray(intr.coeffs, dtype=np.float64)
    if intr.model == "None" or not np.any(c):
        return uv.copy()
    x = (uv[:, 0] - intr.ppx) / intr.fx
    y = (uv[:, 1] - intr.ppy) / intr.fy
    if intr.model in FORWARD_MODELS:
        modified = intr.model in MODIFIED_MODELS
        xu, yu = x.copy(), y.copy()
        for _ in range(iterations):  # fixed point: ideal = distorted - (forward(ideal) - ideal)
            xd, yd = _brown(xu, yu, c, modified)
            xu, yu = xu - (xd - x), yu - (yd - y)
    else:
        raise CalibrationError(f"distortion model {intr.model!r} is not supported for calibration "
                               f"(supported: None, {', '.join(FORWARD_MODELS)})")
    return np.stack([xu * intr.fx + intr.ppx, yu * intr.fy + intr.ppy], axis=1)


def mean_pose(T: np.ndarray) -> np.ndarray:
    """Chordal mean of poses (N, 4, 4): mean translation, rotation projected from the mean matrix."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:, :3, :3].mean(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    out = np.eye(4)
    out[:3, :3] = U @ D @ Vt
    out[:3, 3] = T[:, :3, 3].mean(axis=0)
    return out


__all__ = ["delta", "log_delta", "mean_pose", "project", "transform", "undistort_pixels"]
