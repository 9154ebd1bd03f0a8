"""Depth-image edge tests behind back-projection: discontinuities, edge holes vs surface holes, normals.

Why holes are told apart: D4 stereo leaves a hole wherever it could not match, and the pixels next to a
hole are only suspect when the hole sits at a silhouette or an occlusion (fattened foreground, flying
pixels). Dark or glossy materials drop depth in blobs all over a smooth surface; the pixels next to such
a blob are as good as any, and dropping a margin around every blob erases dark objects.

A hole pixel is an **edge hole** when, scanning its row (or its column), the nearest valid pixels on its
two sides are not both within ``HOLE_SEARCH_PX`` pixels (or the image ends first), or their depths
``z1, z2`` differ by more than what a smooth surface can do over the gap::

    |z1 - z2| > discontinuity_abs_m + BAND_FRACTION * n * z1 * z2 / (fx * B)

with ``n`` the number of hole pixels between them and ``B`` the stereo baseline. The second term is the
depth change across an occlusion band of ``n`` pixels: the left imager sees a band of background that
the right imager cannot, ``L = fx B (1/z_near - 1/z_far)`` pixels wide (the disparity difference), so
across it depth changes by ``L z_near z_far / (fx B)`` (D4 edge fattening only narrows the band,
making the change per hole pixel larger). A smooth surface at angle ``theta`` from frontal changes by
``(n + 1) (z / fx) tan(theta)`` over the same gap; half the band's change lies between the two, so a
surface is called an edge only when ``tan(theta) > BAND_FRACTION z / B`` (about 72 deg at 0.30 m, 74 deg at
0.35 m, 77 deg at 0.45 m; a little more for short gaps, where the absolute term dominates). Columns
use ``fy``: there is no occlusion band vertically, and the same rule is then just that slope bound.
An edge hole costs the ``edge_margin_px`` valid pixels next to it along the scan line that found it
(where fattened foreground and flying pixels sit); a surface hole costs ``hole_margin_px``. The
derivation, the surfaces that get flagged and the measured effect are in docs/processing.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from darp.reconstruction.backproject import DepthFilterSettings

BAND_FRACTION = 0.5  # an edge hole changes depth by more than this fraction of an occlusion band's change
HOLE_SEARCH_PX = 24  # a hole wider than this is an edge: over it the bound would pass a 100 mm step


def _edge_runs_along_rows(z: np.ndarray, valid: np.ndarray, abs_m: float, slope_m: float,
                          margin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Row scan: ``(edge_hole, near)``, the hole pixels of every run of holes that is an edge (see the
    module docstring) and those runs widened by ``margin_px`` along the row.

    ``slope_m`` is ``BAND_FRACTION / (f B)``, so the band term is ``slope_m * n * z1 * z2``. Works on runs
    (found from the flattened hole mask with one guard column per row end), not pixels: a few passes
    over the image, then per-run arithmetic.
    """
    h, w = z.shape
    stride = w + 2
    hole = np.zeros((h, stride), np.int8)
    hole[:, 1:-1] = ~valid
    change = np.diff(hole.reshape(-1))
    starts = np.flatnonzero(change == 1) + 1  # padded flat index of each run's first hole
    ends = np.flatnonzero(change == -1) + 1  # ... of the first pixel after it
    row = starts // stride
    first = starts - row * stride - 1  # image column of the first hole
    after = ends - row * stride - 1  # image column of the valid pixel after the run (w: none)
    n = after - first
    z1 = z[row, np.maximum(first - 1, 0)]
    z2 = z[row, np.minimum(after, w - 1)]
    limit = np.float32(abs_m) + np.float32(slope_m) * n.astype(np.float32) * z1 * z2
    edge = (first == 0) | (after == w) | (n > HOLE_SEARCH_PX) | (np.abs(z1 - z2) > limit)
    row, first, after = row[edge], first[edge], after[edge]
    return (_paint(row, first, after, h, w),
            _paint(row, np.maximum(first - margin_px, 0), np.minimum(after + margin_px, w), h, w))


def _paint(row: np.ndarray, first: np.ndarray, after: np.ndarray, h: int, w: int) -> np.ndarray:
    """(h, w) mask set on the column spans ``[first, after)`` of the given rows (spans may overlap)."""
    size = h * (w + 1)
    steps = (np.bincount(row * (w + 1) + first, minlength=size)
             - np.bincount(row * (w + 1) + after, minlength=size))
    return (np.cumsum(steps).reshape(h, w + 1)[:, :w] > 0)


def _edge_runs(z: np.ndarray, valid: np.ndarray, settings: DepthFilterSettings, fx_px: float,
               fy_px: float, margin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns scanned: edge-hole pixels, and those widened by ``margin_px`` along the scan."""
    band = BAND_FRACTION / settings.stereo_baseline_m
    hole_r, near_r = _edge_runs_along_rows(z, valid, settings.discontinuity_abs_m, band / fx_px, margin_px)
    hole_c, near_c = _edge_runs_along_rows(np.ascontiguousarray(z.T), np.ascontiguousarray(valid.T),
                                           settings.discontinuity_abs_m, band / fy_px, margin_px)
    return hole_r | hole_c.T, near_r | near_c.T


def edge_holes(depth_m: np.ndarray, valid: np.ndarray, settings: DepthFilterSettings,
               fx_px: float, fy_px: float) -> np.ndarray:
    """Hole pixels (not ``valid``) that lie at a silhouette, an occlusion band or the image's end.

    The remaining holes are inside a smooth surface (material dropouts). Rows and columns are scanned
    separately and either one calling a pixel an edge makes it one. The window's own end counts as the
    image's end: callers pad their window by at least ``HOLE_SEARCH_PX``.
    """
    z = np.where(valid, depth_m, np.float32(0.0)).astype(np.float32, copy=False)
    return _edge_runs(z, valid, settings, fx_px, fy_px, 0)[0]


def edge_free_mask(depth_m: np.ndarray, valid: np.ndarray, settings: DepthFilterSettings,
                   fx_px: float, fy_px: float) -> np.ndarray:
    """Valid pixels farther than ``edge_margin_px`` from a discontinuity or the window's end, and from an
    edge hole along the row or column that found it, and farther than ``hole_margin_px`` from a hole
    inside a surface.

    A pixel is on a discontinuity when one of its valid 8-neighbours differs from it by more than
    ``abs + rel * (the nearer of the two depths)``; that marks both pixels of the pair. The 3x3
    maximum and minimum over valid neighbours (OpenCV dilate/erode) find every such pair at once.
    The margin around an edge hole runs along its scan line only: that is where fattened foreground
    and flying pixels sit (across a silhouette); the hole's other neighbours are checked by the other
    scan and the discontinuity test.
    """
    import cv2  # heavy: loaded when depth images are filtered, not when darp is imported
    abs_m, rel = np.float32(settings.discontinuity_abs_m), np.float32(settings.discontinuity_rel)
    kernel3 = np.ones((3, 3), np.uint8)
    z = np.where(valid, depth_m, np.float32(0.0)).astype(np.float32)
    highest = cv2.dilate(z, kernel3)  # invalid pixels (0) never win the maximum
    lowest = cv2.erode(np.where(valid, z, np.float32(np.inf)), kernel3)  # ... nor the minimum
    jump = (highest - z > abs_m + rel * z) | (z - lowest > abs_m + rel * lowest)
    jump &= valid  # a hole is not a discontinuity by itself (the scans decide)
    edge_hole, near_edge_hole = _edge_runs(z, valid, settings, fx_px, fy_px, settings.edge_margin_px)
    bad = _grow(jump, settings.edge_margin_px)
    bad |= near_edge_hole
    if settings.hole_margin_px > 0:
        bad |= _grow(~valid & ~edge_hole, settings.hole_margin_px)
    good: np.ndarray = ~bad & valid
    return good


def _grow(mask: np.ndarray, margin: int) -> np.ndarray:
    """``mask`` dilated by a (2 margin + 1) square; beyond the window everything counts as set."""
    import cv2  # heavy: loaded when depth images are filtered, not when darp is imported
    if margin <= 0:
        return mask.copy()
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    grown = cv2.dilate(mask.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return grown.view(bool)


# -- normals --------------------------------------------------------------------------------------
def _axis_pairs(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, axis: int, step_px: int,
                jump_abs_m: float, jump_rel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the two stencil offsets along one image axis whose point difference is used, and
    whether there is one: ``(behind (N,), ahead (N,), found (N,))``, offsets in pixels (0 = the pixel).

    Tries, in order, the central pair ``step_px`` either side, the one-sided pairs (ahead - centre,
    centre - behind) at the same step, then the same three at one pixel. One-sided pairs whose depths
    differ by more than ``step * (abs + rel * z_near)`` (the 3x3 discontinuity bound over that many
    pixels) straddle a depth jump and are not used. Pixels whose central stencil would leave the image
    get none. Only the depths are read here; the rare fallbacks work on the pixels still undecided.
    """
    pos = rows if axis == 0 else cols
    size = z.shape[axis]
    behind_off = np.zeros(rows.size, np.int32)
    ahead_off = np.zeros(rows.size, np.int32)
    found = np.zeros(rows.size, bool)
    todo = np.flatnonzero((pos >= step_px) & (pos < size - step_px))  # the full stencil lies in the image
    z_centre = z[rows[todo], cols[todo]]
    abs_m, rel = np.float32(jump_abs_m), np.float32(jump_rel)
    for s in dict.fromkeys((step_px, 1)):
        if todo.size == 0:
            break
        r, c = rows[todo], cols[todo]
        z_ahead = z[r + s, c] if axis == 0 else z[r, c + s]
        z_behind = z[r - s, c] if axis == 0 else z[r, c - s]
        smooth_ahead = np.abs(z_ahead - z_centre) <= np.float32(s) * (abs_m + rel * np.minimum(z_ahead, z_centre))
        smooth_behind = np.abs(z_centre - z_behind) <= np.float32(s) * (abs_m + rel * np.minimum(z_behind, z_centre))
        options = (((z_ahead > 0) & (z_behind > 0), -s, s),
                   ((z_ahead > 0) & smooth_ahead, 0, s),
                   ((z_behind > 0) & smooth_behind, -s, 0))
        left = np.ones(todo.size, bool)
        for usable, back, fore in options:
            take = usable & left
            behind_off[todo[take]], ahead_off[todo[take]] = back, fore
            found[todo[take]] = True
            left &= ~take
        todo, z_centre = todo[left], z_centre[left]
    return behind_off, ahead_off, found


def normals_at(points_cam: np.ndarray, rows: np.ndarray, cols: np.ndarray, step_px: int,
               jump_abs_m: float, jump_rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals toward the camera at the given pixels of an organised point image (z = 0: hole).

    ``(down - up) x (right - left)`` faces the camera in the optical frame (x right, y down); each
    difference falls back from central to one-sided, then to one pixel, when its stencil meets a hole
    (see :func:`_axis_pairs`). Returns ``(normals (N, 3) float32, ok (N,) bool)``; ``ok`` is False
    where an axis has no usable difference or a stencil would leave the image.
    """
    z = points_cam[..., 2]
    u_behind, u_ahead, ok_u = _axis_pairs(z, rows, cols, 1, step_px, jump_abs_m, jump_rel)
    v_behind, v_ahead, ok_v = _axis_pairs(z, rows, cols, 0, step_px, jump_abs_m, jump_rel)
    w = points_cam.shape[1]
    flat = np.ascontiguousarray(points_cam).reshape(-1, 3)
    at = rows * w + cols
    du = flat[at + u_ahead] - flat[at + u_behind]  # right - left
    dv = flat[at + v_ahead * w] - flat[at + v_behind * w]  # down - up
    n = np.cross(dv, du)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    ok = ok_u & ok_v & (length > 0)
    return (n / np.where(length > 0, length, 1.0)[:, None]).astype(np.float32), ok


def depth_normals(points_cam: np.ndarray, step_px: int, jump_abs_m: float = 0.002,
                  jump_rel: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a whole organised camera-frame point image (H, W, 3), as :func:`normals_at`.

    Returns ``(normals (H, W, 3) float32 toward the camera, ok (H, W) bool)``; ``ok`` is False at
    holes (z = 0), within ``step_px`` of the image border and where no difference is usable.
    """
    h, w = points_cam.shape[:2]
    normals = np.zeros((h, w, 3), np.float32)
    ok = np.zeros((h, w), bool)
    rows, cols = np.nonzero(points_cam[..., 2] > 0)
    n, good = normals_at(points_cam, rows, cols, step_px, jump_abs_m, jump_rel)
    normals[rows, cols] = n
    ok[rows, cols] = good
    return normals, ok


__all__ = ["BAND_FRACTION", "HOLE_SEARCH_PX", "depth_normals", "edge_free_mask", "edge_holes", "normals_at"]
