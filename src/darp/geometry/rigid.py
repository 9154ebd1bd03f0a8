"""The one rigidity rule: when a 4x4 matrix is a rigid transform, and what to do with a nearly rigid one.

A rigid transform is finite, its last row is ``0 0 0 1`` and its rotation is orthonormal and right-handed:
``max |R^T R - I| <= RIGID_TOLERANCE`` (entrywise) and ``|det R - 1| <= RIGID_TOLERANCE``.

Why 1e-5: a rotation written as text with six decimals (``%.6f``, the usual way poses are saved) is off
orthonormal by up to a few 1e-6 (the real 3DMatch ``pose.txt`` files in ``shared/realdata``: 3.0e-6, the
Doosan arm's poses: 1.3e-6); a float32 rotation by about 1e-7. 1e-5 accepts those with a margin and refuses
anything that is not a rotation as written (a scale, a shear, an approximated matrix). Its effect on a
point 1 m away is at most 10 um, far below what darp measures. (Before, three tolerances were used: 1e-6,
which refused six-decimal files, 1e-5, and 2e-3 for trajectory files that processing then refused.)

A rotation off by more than that but at most ``NEAR_RIGID_LIMIT`` (2e-3, what darp's trajectory and pose
readers accept) is a rotation written with too few digits or drifted by chained products (real 7-Scenes
poses are 1.4e-4 off): :func:`orthonormalised` replaces it by the nearest rotation (:func:`orthonormalize`)
and reports the error, so that what import accepts, processing accepts too.

Every check names ``what`` (a field or frame) and raises the caller's error class with the caller's file.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from darp.errors import DarpError, DarpWarning
from darp.geometry.transforms import orthonormalize

Array = NDArray[np.float64]

RIGID_TOLERANCE = 1e-5  # max |R^T R - I| entry, |det R - 1| and last-row error of a rigid transform
NEAR_RIGID_LIMIT = 2e-3  # rotation error up to which a pose read from a file is re-orthonormalised, not refused


class OrthonormalisedWarning(DarpWarning):
    """Rotations read from a file were off orthonormal (more than RIGID_TOLERANCE) and were replaced by the
    nearest rotations."""


def rotation_error(T: ArrayLike) -> Array | float:
    """``max |R^T R - I|`` of the rotation of 4x4 (or 3x3) matrices (batched): how far from orthonormal."""
    R = np.asarray(T, dtype=np.float64)[..., :3, :3]
    err = np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)), axis=(-2, -1))
    return float(err) if err.ndim == 0 else cast(Array, err)


def check_rigid(T: ArrayLike, what: str, path: str | Path | None = None, *,
                error: type[DarpError] = DarpError) -> Array:
    """``T`` (4, 4) or a stack (..., 4, 4) as float64 rigid transforms (last rows set exactly to ``0 0 0 1``),
    or ``error`` naming ``what`` (with the index of the first bad one in a stack) and ``path``, and the first
    rule it breaks (see the module docstring)."""
    M = np.array(T, dtype=np.float64)
    if M.ndim < 2 or M.shape[-2:] != (4, 4):
        raise error(f"{what}: expected a 4x4 matrix, got shape {M.shape}", path)
    flat = M.reshape(-1, 4, 4)
    finite = np.all(np.isfinite(flat), axis=(1, 2))
    safe = np.where(finite[:, None, None], flat, np.eye(4))
    bottom = np.max(np.abs(safe[:, 3] - [0.0, 0.0, 0.0, 1.0]), axis=1)
    det = np.linalg.det(safe[:, :3, :3])
    ortho = np.asarray(rotation_error(safe))
    bad = ~finite | (bottom > RIGID_TOLERANCE) | (det < 0) | (ortho > RIGID_TOLERANCE) \
        | (np.abs(det - 1.0) > RIGID_TOLERANCE)
    if np.any(bad):
        i = int(np.argmax(bad))
        name = what if M.ndim == 2 else f"{what}[{', '.join(map(str, np.unravel_index(i, M.shape[:-2])))}]"
        if not finite[i]:
            raise error(f"{name}: values must be finite (NaN or infinite found)", path)
        if bottom[i] > RIGID_TOLERANCE:
            raise error(f"{name}: not a rigid transform: last row must be [0, 0, 0, 1], got {flat[i, 3].tolist()}",
                        path)
        if det[i] < 0:
            raise error(f"{name}: not a rigid transform: rotation is a reflection (det {det[i]:+.3f})", path)
        raise error(f"{name}: not a rigid transform: rotation is not orthonormal (error {ortho[i]:.1e}, det "
                    f"{det[i]:.6f}; at most {RIGID_TOLERANCE:g})", path)
    M[..., 3, :] = [0.0, 0.0, 0.0, 1.0]
    return M


def orthonormalised(T: ArrayLike, what: str, path: str | Path | None = None, *,
                    error: type[DarpError] = DarpError) -> tuple[Array, float]:
    """``(T', error)``: ``T`` checked by :func:`check_rigid`, except that a rotation off orthonormal by more
    than ``RIGID_TOLERANCE`` but at most ``NEAR_RIGID_LIMIT`` is replaced by the nearest rotation; ``error``
    is its orthonormality error (0.0 when ``T`` was rigid as given). Warn with :func:`warn_orthonormalised`
    once per file."""
    M = np.array(T, dtype=np.float64)
    if M.shape == (4, 4) and np.all(np.isfinite(M)):
        ortho = float(rotation_error(M))
        if RIGID_TOLERANCE < ortho <= NEAR_RIGID_LIMIT and np.linalg.det(M[:3, :3]) > 0:
            M[:3, :3] = orthonormalize(M[:3, :3])
            return check_rigid(M, what, path, error=error), ortho
    return check_rigid(M, what, path, error=error), 0.0


def warn_orthonormalised(errors: list[float], path: str | Path | None, what: str = "pose") -> None:
    """One warning for a file's re-orthonormalised rotations (``errors``: :func:`orthonormalised`'s, 0 for
    rigid ones), naming the file, how many and the largest error; nothing when none was changed."""
    import warnings

    fixed = [e for e in errors if e > 0.0]
    if fixed:
        warnings.warn(OrthonormalisedWarning(
            f"{len(fixed)} {what} rotation(s) off orthonormal by up to {max(fixed):.1e} (more than "
            f"{RIGID_TOLERANCE:g}) were replaced by the nearest rotation", path), stacklevel=3)


__all__ = ["NEAR_RIGID_LIMIT", "RIGID_TOLERANCE", "OrthonormalisedWarning", "check_rigid",
           "orthonormalised", "rotation_error", "warn_orthonormalised"]
