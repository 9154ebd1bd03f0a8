"""The parametric D4 depth model: turns exact rendered depth into D435-like depth, in the disparity domain.

Stereo depth is ``z = fx * B / d``; the D4 estimates the disparity ``d`` (pixels) and everything that
goes wrong happens there, which is why the model works on ``d``:

1. spatially correlated sub-pixel noise (the matcher window makes neighbours err together), optional
   pixel-locking ripple with a period of one disparity, optional offset;
2. edge fattening (the foreground grows into the background) and flying pixels (values between the
   foreground and the background) at disparity discontinuities;
3. invalid pixels: the left band whose match falls outside the right image (width ``fx * B / z``),
   occlusion holes (surface hidden from the right imager), disparities beyond the search range (closer
   than the minimum depth ``fx * B / 126``), beyond the maximum range, dark/specular material dropouts;
4. quantisation to 1/32 px, conversion back to depth (optional scale error), then the 1 mm depth unit
   when written as Z16.

Every magnitude is a named field of :class:`DepthNoiseSettings`; the defaults and their sources are
listed in docs/twin-camera.md. All randomness comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from scipy.special import ndtri

from darp.errors import TwinError
from darp.twin.camera.noise import NoiseBank, correlated_normal

__all__ = [
    "DepthModel",
    "DepthNoiseSettings",
    "correlated_normal",
    "depth_to_z16",
    "occluded_from_right_depth",
    "occluded_from_right_scanline",
]


@dataclass(frozen=True)
class DepthNoiseSettings:
    """Magnitudes of the D4 corruption model (pixels are depth-image pixels at the current resolution)."""

    subpixel_rms_px: float = 0.08  # disparity noise RMS (Intel's RMS formula, subpixel ~0.08 px)
    noise_correlation_px: float = 1.0  # Gaussian sigma of the noise's spatial correlation
    disparity_step_px: float = 1.0 / 32.0  # D4 sub-pixel disparity resolution (0 = no quantisation)
    pixel_locking_px: float = 0.02  # amplitude of the one-disparity-period ripple
    disparity_offset_px: float = 0.0  # constant disparity error (a calibration drift)
    depth_scale_error: float = 0.0  # relative depth scale bias (one D435 read 980.7 mm at 1 m: -0.019)
    max_disparity_px: float = 126.0  # D4 search range: sets the minimum depth
    max_depth_m: float = 10.0  # farther surfaces are reported invalid
    left_band: bool = True  # invalidate pixels whose match lies left of the right image
    occlusion: bool = True  # invalidate pixels hidden from the right imager
    occlusion_tolerance: float = 0.01  # relative depth difference that counts as hidden
    edge_jump_px: float = 1.5  # disparity step that counts as a depth discontinuity
    edge_fattening_px: int = 1  # foreground growth into the background, pixels
    flying_pixel_band_px: int = 2  # half-width of the band where flying pixels can appear
    flying_pixel_prob: float = 0.3  # probability that a band pixel takes an intermediate value
    dropout_correlation_px: float = 2.0  # blob size of material dropouts (Gaussian sigma)
    random_dropout_prob: float = 0.0  # extra uncorrelated dropouts anywhere

    def __post_init__(self) -> None:
        nonneg = (
            "subpixel_rms_px",
            "noise_correlation_px",
            "disparity_step_px",
            "pixel_locking_px",
            "occlusion_tolerance",
            "edge_jump_px",
            "edge_fattening_px",
            "flying_pixel_band_px",
            "dropout_correlation_px",
        )
        for name in nonneg:
            if getattr(self, name) < 0:
                raise TwinError(f"depth noise setting {name} must be >= 0, got {getattr(self, name)}")
        for name in ("flying_pixel_prob", "random_dropout_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise TwinError(f"depth noise setting {name} must be in [0, 1], got {getattr(self, name)}")
        if self.max_disparity_px <= 0 or self.max_depth_m <= 0:
            raise TwinError("max_disparity_px and max_depth_m must be > 0")

    @classmethod
    def realistic(cls) -> DepthNoiseSettings:
        """D435-like noise and artefacts (the defaults)."""
        return cls()

    @classmethod
    def ideal(cls) -> DepthNoiseSettings:
        """No noise, no artefacts: exact depth (the 1 mm unit still applies when written as Z16)."""
        return cls(
            subpixel_rms_px=0.0,
            disparity_step_px=0.0,
            pixel_locking_px=0.0,
            left_band=False,
            occlusion=False,
            edge_fattening_px=0,
            flying_pixel_prob=0.0,
            max_disparity_px=1e9,
            max_depth_m=1e9,
        )

    def with_(self, **changes: Any) -> DepthNoiseSettings:
        """A copy with some settings changed (numbers and flags by field name; validated)."""
        return replace(self, **changes)


def _window_min(x: np.ndarray, span: int, *, leftward: bool = False) -> np.ndarray:
    """Per row, the minimum of ``x`` over the ``span`` columns right of each pixel (left if ``leftward``).

    Column ``i`` gets ``min x[:, i+1 : i+1+span]`` (``min x[:, i-span : i]``); columns beyond the image
    count as ``inf`` and NaN never wins. Doubling windows, ``log2(span)`` passes of ``np.fmin`` over one
    contiguous buffer whose rows are padded by ``span`` so that no window reaches the next row:
    ``np.minimum.accumulate`` along rows is a scalar loop, several times slower. Exact.
    """
    h, w = x.shape
    span = max(1, min(int(span), w))
    width = w + span
    buf = np.full((h, width), np.float32(np.inf), np.float32)
    if leftward:
        buf[:, span + 1 : span + w] = x[:, :-1]  # buf[:, span + i] = x[:, i - 1]
    else:
        buf[:, : w - 1] = x[:, 1:]  # buf[:, i] = x[:, i + 1]
    cur = buf.reshape(-1)
    other = np.empty_like(cur)

    def widen(step: int) -> None:  # other[i] = min(cur[i], cur[i +- step]): the window grows by step
        if leftward:
            np.fmin(cur[step:], cur[:-step], out=other[step:])
            other[:step] = cur[:step]
        else:
            np.fmin(cur[:-step], cur[step:], out=other[:-step])
            other[-step:] = cur[-step:]

    length = 1
    while 2 * length <= span:
        widen(length)
        cur, other = other, cur
        length *= 2
    if span > length:  # a second, overlapping window covers the rest
        widen(span - length)
        cur = other
    rows = cur.reshape(h, width)
    return rows[:, span : span + w] if leftward else rows[:, :w]


def occluded_from_right_scanline(disparity_px: np.ndarray, *, mirrored: bool = False) -> np.ndarray:
    """Pixels hidden from a camera displaced along +x, from the left disparity alone (0 = no surface).

    A left pixel ``u`` lands at ``u - d`` in the right image; it is hidden when a pixel to its right
    lands at or left of that column (the right-view ordering is broken by a nearer surface).
    ``mirrored``: the other camera is displaced along -x (the same rule on mirrored rows).

    A pixel ``j`` right of ``i`` hides it only if ``j - i <= d_j - d_i < max(d)``, so each pixel is
    compared with the windowed minimum over the next ``max(d) + 2`` columns: the same result as a
    scan of the whole row. Pixels without a surface (``d <= 0``) can never hide another one.
    """
    d = np.asarray(disparity_px, dtype=np.float32)
    h, w = d.shape
    surface = d > 0
    if w < 2 or not surface.any():
        return np.zeros((h, w), bool)
    cols = np.arange(w, dtype=np.float32)
    x_other = (cols[::-1] if mirrored else cols)[None, :] - d  # column in the other view (mirrored rows)
    d_max = float(np.fmax.reduce(d, axis=None))
    span = int(np.ceil(d_max)) + 2 if np.isfinite(d_max) else w  # inf: a surface at z ~ 0 hides all
    hidden: np.ndarray = np.greater_equal(x_other, _window_min(x_other, span, leftward=mirrored))  # at or left of it
    hidden &= surface
    return hidden


_ROW_MAPS: dict[tuple[int, int], np.ndarray] = {}


def _row_map(h: int, w: int) -> np.ndarray:
    """``map_y`` of a same-row remap (cached: it depends on the image size only)."""
    key = (h, w)
    if key not in _ROW_MAPS:
        _ROW_MAPS[key] = np.ascontiguousarray(
            np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
        )
    return _ROW_MAPS[key]


def occluded_from_right_depth(
    depth_m: np.ndarray, disparity_px: np.ndarray, depth_right_m: np.ndarray, tolerance: float
) -> np.ndarray:
    """Pixels whose surface point is hidden from the right imager, using the right view's rendered depth.

    The pair is rectified (same intrinsics, pure x baseline), so the point seen at left ``(u, v)`` with
    disparity ``d`` lies at right ``(u - d, v)`` with the same z; a clearly nearer right depth there
    hides it. Matches beyond the right image are left to the left-band rule.
    """
    h, w = depth_m.shape
    map_x = np.arange(w, dtype=np.float32)[None, :] - disparity_px
    z_right = cv2.remap(
        np.asarray(depth_right_m, np.float32),
        map_x,
        _row_map(h, w),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    )
    limit = np.multiply(depth_m, np.float32(1.0 - tolerance), dtype=np.float32)
    hidden: np.ndarray = np.less(z_right, limit)
    hidden &= z_right > 0
    hidden &= disparity_px > 0
    return hidden


class DepthModel:
    """Applies :class:`DepthNoiseSettings` to exact depth images of one depth stream (fixed fx, baseline)."""

    def __init__(
        self,
        settings: DepthNoiseSettings,
        fx_px: float,
        baseline_m: float,
        *,
        bank_seed: int | list[int] | None = None,
    ) -> None:
        """``bank_seed``: seed of the pre-drawn noise fields (see ``darp.twin.camera.noise``); without it the
        fields come from the generator of the first :meth:`apply` call."""
        if fx_px <= 0 or baseline_m <= 0:
            raise TwinError(f"depth model needs fx > 0 and baseline > 0, got {fx_px}, {baseline_m}")
        self.settings = settings
        self.fx_px = float(fx_px)
        self.baseline_m = float(baseline_m)
        self.fb = self.fx_px * self.baseline_m  # disparity (px) times depth (m)
        self._bank_seed = bank_seed
        self._banks: dict[tuple[tuple[int, int], float], NoiseBank] = {}

    def _field(self, shape: tuple[int, int], sigma_px: float, rng: np.random.Generator) -> np.ndarray:
        """A unit correlated field window from the bank for this shape and correlation."""
        key = (shape, float(sigma_px))
        bank = self._banks.get(key)
        if bank is None:
            seed_rng = (
                rng
                if self._bank_seed is None
                else np.random.default_rng([*np.atleast_1d(self._bank_seed).tolist(), len(self._banks)])
            )
            bank = self._banks[key] = NoiseBank(shape, seed_rng, correlation_px=sigma_px)
        return bank.draw(rng)

    def disparity(self, depth_m: np.ndarray) -> np.ndarray:
        """Disparity in pixels of exact depth (0 where there is no surface)."""
        with np.errstate(divide="ignore"):
            d = np.where(depth_m > 0, np.float32(self.fb) / depth_m, np.float32(0.0))
        return d.astype(np.float32, copy=False)

    def apply(
        self,
        depth_m: np.ndarray,
        rng: np.random.Generator,
        *,
        depth_right_m: np.ndarray | None = None,
        dropout_prob: np.ndarray | None = None,
    ) -> np.ndarray:
        """Measured depth in metres (float32, 0 = invalid) from exact left-imager depth ``depth_m``.

        ``depth_right_m``: exact depth rendered from the right imager (for occlusion; without it the
        left disparity's scanline order is used). ``dropout_prob``: per-pixel dropout probability
        (dark, glossy or transparent materials). Works in place on its own float32 buffers (a few
        whole-image passes, each about 0.05 ms at 640x480).
        """
        s = self.settings
        z = np.asarray(depth_m, dtype=np.float32)
        if z.ndim != 2:
            raise TwinError(f"depth image must be 2-D, got shape {z.shape}")
        h, w = z.shape
        surface = z > 0
        surface &= z < np.float32(np.inf)
        fb = np.float32(self.fb)
        d_true = np.zeros((h, w), np.float32)
        np.divide(fb, z, out=d_true, where=surface)  # disparity, 0 where there is no surface

        work = np.empty((h, w), np.float32)  # scratch buffer
        if s.subpixel_rms_px > 0:
            d = np.multiply(self._field((h, w), s.noise_correlation_px, rng), np.float32(s.subpixel_rms_px))
            d += d_true
        else:
            d = d_true.copy()
        if s.pixel_locking_px > 0:
            np.multiply(d_true, np.float32(2 * np.pi), out=work)
            np.sin(work, out=work)
            work *= np.float32(s.pixel_locking_px)
            d -= work
        if s.disparity_offset_px:
            d += np.float32(s.disparity_offset_px)

        valid = np.less_equal(z, s.max_depth_m)
        valid &= surface
        if s.occlusion:
            if depth_right_m is not None:
                hidden = occluded_from_right_depth(
                    z, d_true, np.asarray(depth_right_m, np.float32), s.occlusion_tolerance
                )
            else:
                hidden = occluded_from_right_scanline(d_true)
            valid &= ~hidden

        self._edge_effects(d_true, d, valid, rng)

        mask = np.empty((h, w), bool)
        if s.left_band:  # the match u - d must lie inside the right image
            np.subtract(np.arange(w, dtype=np.float32)[None, :], d, out=work)
            valid &= np.greater_equal(work, -0.5, out=mask)
        valid &= np.greater(d, 0, out=mask)
        valid &= np.less_equal(d, s.max_disparity_px, out=mask)
        if dropout_prob is not None:
            valid &= ~self._dropouts(np.asarray(dropout_prob, np.float32), rng)
        if s.random_dropout_prob > 0:
            valid &= rng.random((h, w), dtype=np.float32) >= s.random_dropout_prob

        if s.disparity_step_px > 0:
            step = np.float32(s.disparity_step_px)
            d /= step
            np.rint(d, out=d)
            d *= step
        valid &= np.greater(d, 0, out=mask)
        out = np.zeros((h, w), np.float32)
        np.divide(fb, d, out=out, where=valid)
        if s.depth_scale_error:
            out *= np.float32(1.0 + s.depth_scale_error)
        return out

    def _edge_effects(
        self, d_true: np.ndarray, d: np.ndarray, valid: np.ndarray, rng: np.random.Generator
    ) -> None:
        """Edge fattening (background pixels near a foreground take its disparity) and flying pixels.

        Updates ``d`` and ``valid`` in place. Finds the discontinuities with whole-image morphology,
        then works on the few pixels near them only (index arrays), so its cost follows the edges.
        """
        s = self.settings
        fatten = s.edge_fattening_px > 0
        fly = s.flying_pixel_prob > 0 and s.flying_pixel_band_px > 0
        if not (fatten or fly):
            return
        r = max(s.edge_fattening_px if fatten else 0, s.flying_pixel_band_px if fly else 0)
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        jump = np.float32(s.edge_jump_px)
        up_full = cv2.dilate(d_true, kernel)  # nearest disparity around, minus this pixel's
        up_full -= d_true
        void = cv2.threshold(d_true, 0.0, np.inf, cv2.THRESH_BINARY_INV)[1]  # inf where no surface
        down_full = cv2.erode(cv2.add(d_true, void), kernel)  # farthest surface around (void ignored)
        np.subtract(d_true, down_full, out=down_full)  # this pixel's disparity minus the farthest
        edge = up_full > jump
        edge |= down_full > jump
        idx = np.flatnonzero(edge)
        if idx.size == 0:
            return
        d_flat, valid_flat, true_flat = d.reshape(-1), valid.reshape(-1), d_true.reshape(-1)
        t_true = true_flat[idx]
        noise = d_flat[idx] - t_true  # keep each pixel's own noise sample
        fat = np.zeros(idx.size, bool)
        if fatten:
            k = 2 * s.edge_fattening_px + 1
            near_fat = cv2.dilate(d_true, np.ones((k, k), np.uint8)).reshape(-1)[idx]
            fat = (near_fat - t_true) > s.edge_jump_px
            d_flat[idx[fat]] = near_fat[fat] + noise[fat]
            valid_flat[idx[fat]] = True
        if fly:
            up = up_full.reshape(-1)[idx]
            down = down_full.reshape(-1)[idx]
            cand = ~fat & (t_true > 0) & valid_flat[idx]
            draw = rng.random((2, idx.size), dtype=np.float32)
            hit = cand & (draw[0] < s.flying_pixel_prob)
            step = np.where(up >= down, up, -down)
            d_flat[idx[hit]] = t_true[hit] + draw[1][hit] * step[hit] + noise[hit]

    def _dropouts(self, prob: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Blob-shaped dropouts: a correlated unit field below the normal quantile of the probability."""
        mask = prob > 0
        if not np.any(mask):
            return np.zeros(prob.shape, bool)
        field = self._field(prob.shape, self.settings.dropout_correlation_px, rng)
        out = np.zeros(prob.shape, bool)
        out[mask] = field[mask] < ndtri(np.clip(prob[mask], 0.0, 1.0))
        return out


def depth_to_z16(depth_m: np.ndarray, depth_unit_m: float = 0.001) -> np.ndarray:
    """Depth in metres -> Z16 depth units (uint16, 0 = invalid), rounded to the nearest unit.

    The division is done in float64 (what the 1 mm unit needs to round exactly), in one buffer.
    """
    units: np.ndarray = np.divide(np.asarray(depth_m), depth_unit_m, dtype=np.float64)
    np.rint(units, out=units)
    if not (units.min(initial=0.0) >= 0.0 and units.max(initial=0.0) <= 65535.0):  # NaN fails too
        np.clip(units, 0, 65535, out=units)
    return units.astype(np.uint16)
