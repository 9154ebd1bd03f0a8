"""Small geometry shared by the calibration modules: pose perturbations, undistortion of a stream's pixels.

Poses are perturbed on the right, ``T = T0 @ delta(xi)`` with ``xi = (rotvec, translation)`` in the
frame of ``T0``, so the optimiser's parameters start at zero and stay far from the rotation-vector
singularity at pi whatever the pose. Pinhole projection and point transforms are :mod:`darp.geometry`'s.

Detected pixels are *undistorted* once, with the stream's own distortion model, to the ideal pinhole
image of the same ``K``; everything after works with a plain pinhole. librealsense's models, as its
``rs2_project_point_to_pixel`` applies them (ideal -> distorted; inverted here by fixed-point iteration,
as ``rs2_deproject_pixel_to_point`` does; the equations are :mod:`darp.geometry.pinhole`'s):

- ``Brown Conrady``: OpenCV's k1, k2, p1, p2, k3;
- ``Modified Brown Conrady`` and ``Inverse Brown Conrady``: the radial factor first, then the
  tangential terms on the radially distorted point (with the undistorted radius);
- ``None``, or any model with all coefficients zero: nothing to do.
"""

from __future__ import annotations

import numpy as np

from darp.errors import CalibrationError
from darp.formats.realsense.types import Intrinsics
from darp.geometry.pinhole import normalised_pixels, undistort_normalised
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


def undistort_pixels(uv: np.ndarray, intr: Intrinsics, iterations: int = 20) -> np.ndarray:
    """Pixels (N, 2) of a stream -> pixels of the ideal pinhole camera with the same K."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    c = np.asarray(intr.coeffs, dtype=np.float64)
    if intr.model == "None" or not np.any(c):
        return uv.copy()
    x, y = normalised_pixels(uv[:, 0], uv[:, 1], intr.fx, intr.fy, intr.ppx, intr.ppy)
    if intr.model in FORWARD_MODELS:
        xu, yu = undistort_normalised(x, y, c, intr.model in MODIFIED_MODELS, iterations)
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


__all__ = ["delta", "log_delta", "mean_pose", "undistort_pixels"]
