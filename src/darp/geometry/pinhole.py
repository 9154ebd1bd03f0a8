"""The pinhole camera: pixels to normalised rays and camera-frame points, points to pixels, lens distortion.

Pixel centres are at integer coordinates (OpenCV's and librealsense's convention). A pixel ``(u, v)`` is the
normalised ray ``((u - ppx) / fx, (v - ppy) / fy)``; with depth ``z`` (along the optical axis) it is the
camera-frame point ``(x z, y z, z)``. Callers keep their own filtering (valid depth, edges, strides).

Distortion is librealsense's, as ``rs2_project_point_to_pixel`` applies it to normalised coordinates
(undistorted -> distorted), with coefficients ``k1 k2 p1 p2 k3``:

- Brown-Conrady (OpenCV's model): radial factor and tangential terms on the undistorted point;
- ``tangential_on_radial`` (librealsense's Modified and Inverse Brown-Conrady): the tangential terms on the
  radially distorted point, with the undistorted radius.

:func:`undistort_normalised` inverts it by fixed-point iteration, as ``rs2_deproject_pixel_to_point`` does;
the callers choose the number of iterations and check convergence where they need to.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def normalised_pixels(u: ArrayLike, v: ArrayLike, fx: float, fy: float, ppx: float, ppy: float
                      ) -> tuple[Array, Array]:
    """Normalised ray coordinates ``((u - ppx) / fx, (v - ppy) / fy)`` of pixels (any shape, float64)."""
    return (np.asarray(u) - ppx) / fx, (np.asarray(v) - ppy) / fy


def backproject_rays(x: NDArray[np.floating], y: NDArray[np.floating], z: NDArray[np.floating]
                     ) -> NDArray[np.floating]:
    """Camera-frame points (..., 3) ``(x z, y z, z)`` of normalised rays with depth ``z`` (in their dtype)."""
    return np.stack([x * z, y * z, z], axis=-1)


def project(P_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame points (..., 3) to pixels (..., 2) (no distortion)."""
    z = P_cam[..., 2:3]
    return cast(np.ndarray, (P_cam[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]]))


def distort_normalised(x: Array, y: Array, coeffs: Sequence[float] | np.ndarray, tangential_on_radial: bool
                       ) -> tuple[Array, Array]:
    """librealsense's forward distortion of normalised coordinates (see the module docstring)."""
    k = tuple(float(c) for c in coeffs)
    r2 = x * x + y * y
    f = 1.0 + k[0] * r2 + k[1] * r2 * r2 + k[4] * r2 * r2 * r2
    if tangential_on_radial:
        xf, yf = x * f, y * f
        return (xf + 2.0 * k[2] * xf * yf + k[3] * (r2 + 2.0 * xf * xf),
                yf + 2.0 * k[3] * xf * yf + k[2] * (r2 + 2.0 * yf * yf))
    return (x * f + 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x),
            y * f + 2.0 * k[3] * x * y + k[2] * (r2 + 2.0 * y * y))


def undistort_normalised(xd: Array, yd: Array, coeffs: Sequence[float] | np.ndarray, tangential_on_radial: bool,
                         iterations: int) -> tuple[Array, Array]:
    """The undistorted normalised coordinates whose :func:`distort_normalised` is ``(xd, yd)``: fixed point
    ``x <- x + (xd - distort(x))`` from ``x = xd``, ``iterations`` times."""
    x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
    for _ in range(iterations):
        dx, dy = distort_normalised(x, y, coeffs, tangential_on_radial)
        x += xd - dx
        y += yd - dy
    return x, y


__all__ = ["backproject_rays", "distort_normalised", "normalised_pixels", "project", "undistort_normalised"]
