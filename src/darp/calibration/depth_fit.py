"""Per-camera depth correction from board captures (issue 16, item 3).

Each capture with a depth image gives, for every valid depth pixel inside the detected ChArUco corners'
convex hull (shrunk by ``margin_px``), a measured depth ``z`` and a predicted one: the board plane's pose in
the depth frame is known from its corners (PnP in the capture's stream, ``T_depth_stream @ T_stream_board``),
so the predicted depth is where the pixel's ray meets that plane. The fit is

    z_pred = scale * z + offset_m + quad_per_m * z^2

with a robust (Huber) loss: the board's printed texture causes D4 depth artefacts on marker edges, and a
few pixels see past the board. Pixels of one capture share that capture's PnP pose error, so the
standard errors come from a bootstrap over captures, not from the pixel count.

**Is the distance term identifiable?** Over the range of distances the captures span, ``z^2`` is almost
a linear combination of ``z`` and 1. The full model is fitted; the quadratic term is kept only when the
captures span at least ``min_span_m`` and its bootstrap standard error is at most ``max_quad_std_per_m``
(default 2 mm/m^2, half the paper profile's 4 mm/m^2 spread); otherwise it is fixed at 0 and the
two-parameter fit is stored, with the reason in ``notes``.

**What the fit measures.** The predicted depth comes from PnP with the stream's *written* intrinsics:
a focal length off by ``e`` (relative) puts the board ``e`` further away, so the fitted scale absorbs
``e`` (the paper profile draws focal_std_pct 0.3 %, i.e. 1.5 mm at 0.5 m). The correction then makes depth
agree with the board geometry the hand-eye calibration saw through the same intrinsics (docs/accuracy.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from darp.calibration.captures import CaptureSet
from darp.calibration.detect import Detection
from darp.calibration.geometry import undistort_pixels
from darp.errors import CalibrationError
from darp.formats.calibration import DepthCorrection
from darp.formats.realsense.types import Intrinsics


@dataclass(frozen=True)
class DepthFitSettings:
    """How the depth correction is fitted."""

    margin_px: int = 4  # shrink the corners' hull by this much (board edges, corner blur)
    max_pixels_per_capture: int = 3000  # random subsample per capture (deterministic)
    min_pixels_per_capture: int = 200
    min_captures: int = 4
    max_abs_residual_m: float = 0.03  # pixels further than this from the plane are not the board
    huber_k: float = 1.5  # Huber threshold in robust standard deviations
    bootstrap: int = 200
    min_span_m: float = 0.15  # the distance term needs captures over at least this range of depth
    max_quad_std_per_m: float = 0.002  # ... and a bootstrap std at most this (m per m^2)
    seed: int = 0


@dataclass(frozen=True)
class BoardDepthSamples:
    """Measured and predicted depth (metres) of one capture's board pixels."""

    capture_id: str
    measured_m: np.ndarray
    predicted_m: np.ndarray


def _rays(u: np.ndarray, v: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Unit-z rays (N, 3) of depth pixels (distortion removed when the stream has any)."""
    uv = np.stack([u, v], axis=1).astype(np.float64)
    if intr.model != "None" and np.any(np.asarray(intr.coeffs)):
        uv = undistort_pixels(uv, intr)
    x = (uv[:, 0] - intr.ppx) / intr.fx
    y = (uv[:, 1] - intr.ppy) / intr.fy
    return np.stack([x, y, np.ones_like(x)], axis=1)


def board_depth_samples(depth_m: np.ndarray, depth_intr: Intrinsics, T_depth_board: np.ndarray,
                        corners_board_m: np.ndarray, *, capture_id: str = "", margin_px: int = 4,
                        max_pixels: int | None = None, rng: np.random.Generator | None = None,
                        max_abs_residual_m: float = 0.03) -> BoardDepthSamples:
    """Measured vs predicted depth of the pixels inside the board corners' hull (seen in the depth image).

    ``corners_board_m`` (N, 3): the detected corners in the board frame; their hull, projected into the
    depth image with the depth intrinsics and shrunk by ``margin_px``, is the region used.
    """
    T = np.asarray(T_depth_board, np.float64)
    P = corners_board_m @ T[:3, :3].T + T[:3, 3]
    if np.any(P[:, 2] <= 0):
        return BoardDepthSamples(capture_id, np.zeros(0), np.zeros(0))
    K = depth_intr.K
    dist = np.asarray(depth_intr.coeffs, np.float64) if depth_intr.model != "None" else np.zeros(5)
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    hull = cv2.convexHull(uv.reshape(-1, 2).astype(np.float32))
    h, w = depth_m.shape
    mask: np.ndarray = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull.reshape(-1, 2)).astype(np.int32), 1)
    if margin_px > 0:
        mask = cv2.erode(mask, np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8))
    v, u = np.nonzero((mask > 0) & (depth_m > 0))
    if max_pixels is not None and u.size > max_pixels:
        pick = (rng or np.random.default_rng(0)).choice(u.size, max_pixels, replace=False)
        u, v = u[pick], v[pick]
    n = T[:3, 2]
    rays = _rays(u.astype(np.float64), v.astype(np.float64), depth_intr)
    denom = rays @ n
    predicted = np.where(np.abs(denom) > 1e-9, float(n @ T[:3, 3]) / np.where(denom == 0, 1.0, denom), np.nan)
    measured = depth_m[v, u].astype(np.float64)
    keep = np.isfinite(predicted) & (predicted > 0) & (np.abs(measured - predicted) <= max_abs_residual_m)
    return BoardDepthSamples(capture_id, measured[keep], predicted[keep])


def _design(z: np.ndarray, quad: bool) -> np.ndarray:
    cols = [z, np.ones_like(z)] + ([z * z] if quad else [])
    return np.stack(cols, axis=1)


def _uncentre(p_u: np.ndarray, zc: float) -> np.ndarray:
    """Parameters in ``u = z - zc`` back to ``z``: ``s u + c + d u^2 = (s - 2 d zc) z + (c - s zc + d zc^2) + d z^2``.
    """
    if p_u.size == 3:
        s, c, d = p_u
        return np.array([s - 2 * d * zc, c - s * zc + d * zc * zc, d])
    s, c = p_u
    return np.array([s, c - s * zc])


def _irls(z: np.ndarray, target: np.ndarray, quad: bool, zc: float, huber_k: float,
          iterations: int = 30) -> tuple[np.ndarray, np.ndarray, float]:
    """Huber IRLS in centred coordinates: (parameters in u = z - zc, final weights, robust residual scale)."""
    Au = _design(z - zc, quad)
    w = np.ones(z.size)
    p_u = np.zeros(Au.shape[1])
    scale = 1e-3
    for _ in range(iterations):
        sw = np.sqrt(w)
        p_new, *_ = np.linalg.lstsq(Au * sw[:, None], target * sw, rcond=None)
        r = target - Au @ p_new
        scale = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-5)
        a = np.abs(r) / (huber_k * scale)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
        done = np.allclose(p_new, p_u, rtol=0, atol=1e-10)
        p_u = p_new
        if done:
            break
    return p_u, w, scale


def _fit_with_bootstrap(used: Sequence[BoardDepthSamples], quad: bool, s: DepthFitSettings
                        ) -> tuple[np.ndarray, np.ndarray, float]:
    """(parameters, bootstrap std over captures, robust residual scale). The bootstrap keeps the full fit's
    Huber weights and resamples whole captures (their pixels share one PnP pose error)."""
    z = np.concatenate([c.measured_m for c in used])
    t = np.concatenate([c.predicted_m for c in used])
    zc = float(np.median(z))
    p_u, w, scale = _irls(z, t, quad, zc, s.huber_k)
    bounds = np.cumsum([0] + [c.measured_m.size for c in used])
    normal = []
    for k in range(len(used)):
        sl = slice(bounds[k], bounds[k + 1])
        A = _design(z[sl] - zc, quad) * np.sqrt(w[sl])[:, None]
        normal.append((A.T @ A, A.T @ (t[sl] * np.sqrt(w[sl]))))
    M = np.array([m for m, _ in normal])
    b = np.array([v for _, v in normal])
    rng = np.random.default_rng(s.seed)
    boots = []
    for _ in range(s.bootstrap):
        pick = rng.integers(0, len(used), len(used))
        Ms, bs = M[pick].sum(axis=0), b[pick].sum(axis=0)
        if np.linalg.cond(Ms) > 1e12:
            continue
        boots.append(_uncentre(np.linalg.solve(Ms, bs), zc))
    std = np.std(np.array(boots), axis=0, ddof=1) if len(boots) > 1 else np.full(p_u.size, np.inf)
    return _uncentre(p_u, zc), std, scale


def fit_depth_correction(samples: Sequence[BoardDepthSamples],
                         settings: DepthFitSettings | None = None) -> DepthCorrection:
    """The robust depth correction of one camera from its captures' board samples (bootstrap std)."""
    s = settings or DepthFitSettings()
    used = [c for c in samples if c.measured_m.size >= s.min_pixels_per_capture]
    if len(used) < s.min_captures:
        raise CalibrationError(f"depth correction: only {len(used)} captures with {s.min_pixels_per_capture}+ board "
                               f"depth pixels (need {s.min_captures})")
    z = np.concatenate([c.measured_m for c in used])
    per_capture_z = np.array([float(np.median(c.measured_m)) for c in used])
    span = float(per_capture_z.max() - per_capture_z.min())
    p_full, std_full, mad_full = _fit_with_bootstrap(used, True, s)
    quad_std = float(std_full[2])
    quad_ok = span >= s.min_span_m and quad_std <= s.max_quad_std_per_m
    if quad_ok:
        p, stds, mad = p_full, std_full, mad_full
        notes = (f"distance term identifiable: captures span {span:.3f} m, its std {1e3 * quad_std:.2f} mm/m^2 "
                 f"<= {1e3 * s.max_quad_std_per_m:g}")
    else:
        p2, std2, mad = _fit_with_bootstrap(used, False, s)
        p, stds = np.array([p2[0], p2[1], 0.0]), np.array([std2[0], std2[1], 0.0])
        why = (f"captures span only {span:.3f} m (< {s.min_span_m:g})" if span < s.min_span_m else
               f"its bootstrap std {1e3 * quad_std:.2f} mm/m^2 > {1e3 * s.max_quad_std_per_m:g} over a "
               f"{span:.3f} m span")
        notes = (f"distance term not identifiable ({why}; full-model estimate {1e3 * p_full[2]:.2f} mm/m^2): "
                 "fixed at 0")
    return DepthCorrection(
        scale=float(p[0]), offset_m=float(p[1]), quad_per_m=float(p[2]),
        scale_std=float(stds[0]), offset_std_m=float(stds[1]), quad_std_per_m=float(stds[2]) if quad_ok else None,
        quad_identifiable=bool(quad_ok), range_m=(float(np.percentile(z, 1)), float(np.percentile(z, 99))),
        n_captures=len(used), n_pixels=int(z.size), residual_mad_m=float(mad), notes=notes)


def capture_depth_samples(captures: CaptureSet, detections: Sequence[Detection],
                          settings: DepthFitSettings | None = None) -> dict[str, list[BoardDepthSamples]]:
    """Board samples per arm, from every accepted detection whose capture has a depth image."""
    from darp.calibration.board import corners_board_m

    s = settings or DepthFitSettings()
    corners = corners_board_m(captures.board)
    out: dict[str, list[BoardDepthSamples]] = {}
    for det in detections:
        rec = det.record
        T = det.T_depth_board
        if not det.ok or T is None or not rec.has_depth:
            continue
        assert rec.depth_intrinsics is not None
        rng = np.random.default_rng([s.seed, sum(map(ord, rec.capture_id))])
        samples = board_depth_samples(captures.load_depth(rec), rec.depth_intrinsics, T, corners[det.ids],
                                      capture_id=rec.capture_id, margin_px=s.margin_px,
                                      max_pixels=s.max_pixels_per_capture, rng=rng,
                                      max_abs_residual_m=s.max_abs_residual_m)
        out.setdefault(rec.arm, []).append(samples)
    return out


def estimate_depth_corrections(captures: CaptureSet, detections: Sequence[Detection],
                               settings: DepthFitSettings | None = None) -> tuple[dict[str, DepthCorrection],
                                                                                 dict[str, str]]:
    """Per arm: its depth correction, or (second dict) why none was estimated. Folders without depth: ({}, {})."""
    corrections: dict[str, DepthCorrection] = {}
    skipped: dict[str, str] = {}
    for arm, samples in capture_depth_samples(captures, detections, settings).items():
        try:
            corrections[arm] = fit_depth_correction(samples, settings)
        except CalibrationError as err:
            skipped[arm] = err.message
    return corrections, skipped


__all__ = ["BoardDepthSamples", "DepthFitSettings", "board_depth_samples", "capture_depth_samples",
           "estimate_depth_corrections", "fit_depth_correction"]
