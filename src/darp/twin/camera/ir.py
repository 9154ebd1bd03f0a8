"""Left/right infrared (Y8) images of the twin: ambient scene light plus the projector's dot pattern.

The projector sits between the two imagers (``projector_x_m`` along +x of the left imager) and throws
a fixed pseudo-random dot pattern (one per unit, from a seed) over its field of projection. The dots
are placed through the geometry: each pixel's surface point (from the view's exact depth) is expressed
in the projector frame and looked up in the pattern, so a dot lands on the same surface point in both
imagers and moves with the surface, as on the real camera. Surface points the projector cannot see
(its shadow, computed along image rows as for stereo occlusion) get no dots.

Signal per pixel, in digital numbers (DN): ``ambient_gain * 255 * L + dot_peak_dn * pattern *
(reference_m / z)^2 * max(L, reflectance_floor)``, where ``L`` is the rendered luminance of the view
(the D4 imagers see visible light too). Sensor noise: shot noise with variance ``shot_noise_gain * S``
plus Gaussian read noise, then rounding and clipping to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from darp.errors import TwinError
from darp.formats.realsense.types import Intrinsics
from darp.twin.camera.depth_model import occluded_from_right_scanline
from darp.twin.camera.noise import NoiseBank


@dataclass(frozen=True)
class IrSettings:
    """Magnitudes of the IR image model (DN = 8-bit digital numbers)."""

    emitter_enabled: bool = True
    dot_count: int = 5000  # D435 projector: about 5000 spots (Intel projector white paper)
    field_h_deg: float = 86.0  # field of projection (FRAMOS D435e manual: H 86 +-3 deg, V 57 +-3 deg)
    field_v_deg: float = 57.0
    dot_sigma_rad: float = 0.0025  # angular dot radius (Gaussian sigma): about 1 px at 640x480
    dot_peak_dn: float = 150.0  # peak dot brightness on a white surface at reference_m
    reference_m: float = 0.5
    reflectance_floor: float = 0.1  # dots stay faintly visible on dark surfaces
    projector_shadows: bool = True
    ambient_gain: float = 0.6  # fraction of the rendered luminance that reaches the IR image
    shot_noise_gain: float = 0.05  # DN^2 of variance per DN of signal (about 20 electrons per DN)
    read_noise_dn: float = 1.0

    def __post_init__(self) -> None:
        if self.dot_count < 0 or self.dot_sigma_rad <= 0 or self.reference_m <= 0:
            raise TwinError("IR settings need dot_count >= 0, dot_sigma_rad > 0 and reference_m > 0")
        if not (0 < self.field_h_deg < 180 and 0 < self.field_v_deg < 180):
            raise TwinError("IR projector field of projection must be in (0, 180) degrees")
        if (
            min(
                self.dot_peak_dn,
                self.ambient_gain,
                self.shot_noise_gain,
                self.read_noise_dn,
                self.reflectance_floor,
            )
            < 0
        ):
            raise TwinError("IR brightness and noise settings must be >= 0")

    @classmethod
    def ideal(cls) -> IrSettings:
        """Same light, no sensor noise."""
        return cls(shot_noise_gain=0.0, read_noise_dn=0.0)


class DotPattern:
    """The projector's fixed dot pattern, rasterised on its tangent plane (x right, y down, z forward)."""

    def __init__(self, settings: IrSettings, seed: int | np.random.Generator) -> None:
        rng = np.random.default_rng(seed)
        self.settings = settings
        self.focal_px = 1.5 / settings.dot_sigma_rad  # raster pitch: dot sigma spans 1.5 raster pixels
        half_w = np.tan(np.deg2rad(settings.field_h_deg) / 2)
        half_h = np.tan(np.deg2rad(settings.field_v_deg) / 2)
        self.width = int(np.ceil(2 * half_w * self.focal_px)) + 1
        self.height = int(np.ceil(2 * half_h * self.focal_px)) + 1
        self.cx = (self.width - 1) / 2
        self.cy = (self.height - 1) / 2
        tx = rng.uniform(-half_w, half_w, settings.dot_count)
        ty = rng.uniform(-half_h, half_h, settings.dot_count)
        brightness = rng.uniform(0.7, 1.0, settings.dot_count)  # spots differ a little in power
        raster: NDArray[np.float32] = np.zeros((self.height, self.width), np.float32)
        x = tx * self.focal_px + self.cx
        y = ty * self.focal_px + self.cy
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        for dx, dy, wgt in (
            (0, 0, (1 - fx) * (1 - fy)),
            (1, 0, fx * (1 - fy)),
            (0, 1, (1 - fx) * fy),
            (1, 1, fx * fy),
        ):
            xi, yi = np.clip(x0 + dx, 0, self.width - 1), np.clip(y0 + dy, 0, self.height - 1)
            np.add.at(raster, (yi, xi), (brightness * wgt).astype(np.float32))
        sigma = settings.dot_sigma_rad * self.focal_px
        raster = cast("NDArray[np.float32]", cv2.GaussianBlur(raster, (0, 0), sigma))
        raster *= np.float32(2 * np.pi * sigma * sigma)  # an isolated unit dot peaks at 1
        self.raster = raster
        self._map_key: tuple[float, ...] | None = None
        self._map_x = self._map_y = np.zeros((0, 0), np.float32)

    def lookup(self, inv_depth: np.ndarray, intr: Intrinsics, projector_x_m: float) -> np.ndarray:
        """Pattern value at each pixel's surface point, from the inverse depth ``1 / z`` (0 = no surface).

        The projector shares the camera's orientation and sits at ``projector_x_m`` along its x axis, so
        a pixel's projector column is its own ray's column shifted by ``projector_x_m / z``. Pixels
        without a surface get a meaningless value: the caller's ``1 / z^2`` fall-off zeroes them.
        """
        base_x, map_y = self._maps(intr)
        map_x = cv2.scaleAdd(inv_depth, -float(projector_x_m) * self.focal_px, base_x)
        return cv2.remap(
            self.raster, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0
        )

    def _maps(self, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """Pattern coordinates of each pixel's ray seen from the camera centre (cached per intrinsics)."""
        key = (intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy)
        if self._map_key != key:
            u = (np.arange(intr.width, dtype=np.float64) - intr.ppx) / intr.fx * self.focal_px + self.cx
            v = (np.arange(intr.height, dtype=np.float64) - intr.ppy) / intr.fy * self.focal_px + self.cy
            self._map_x = np.ascontiguousarray(
                np.broadcast_to(u[None, :], (intr.height, intr.width)), np.float32
            )
            self._map_y = np.ascontiguousarray(
                np.broadcast_to(v[:, None], (intr.height, intr.width)), np.float32
            )
            self._map_key = key
        return self._map_x, self._map_y


class IrModel:
    """Makes the IR pair of one camera from rendered views (colour + exact depth) of its two imagers."""

    def __init__(
        self,
        settings: IrSettings,
        intr: Intrinsics,
        baseline_m: float,
        projector_x_m: float,
        seed: int | list[int] = 0,
    ) -> None:
        """``seed`` fixes the unit's dot pattern and the pre-drawn sensor noise bank."""
        self.settings = settings
        self.intr = intr
        self.baseline_m = float(baseline_m)
        self.projector_x_m = float(projector_x_m)
        seq = [*np.atleast_1d(seed).tolist()]
        self.pattern = DotPattern(settings, np.random.default_rng([*seq, 1]))
        self._noise = (
            NoiseBank((intr.height, intr.width), np.random.default_rng([*seq, 2]))
            if settings.shot_noise_gain > 0 or settings.read_noise_dn > 0
            else None
        )

    def image(
        self, rgb: np.ndarray, depth_m: np.ndarray, projector_x_m: float, rng: np.random.Generator
    ) -> np.ndarray:
        """One Y8 image for a view whose projector is at ``projector_x_m`` along its x axis."""
        s = self.settings
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
        signal = grey.astype(np.float32)
        if s.emitter_enabled and s.dot_count > 0 and s.dot_peak_dn > 0:
            inv_z = np.zeros(depth_m.shape, np.float32)
            np.reciprocal(depth_m, out=inv_z, where=depth_m > 0)
            dots = self.pattern.lookup(inv_z, self.intr, projector_x_m)
            if s.projector_shadows:  # no dots where the projector cannot see: multiply by "lit" (0 or 1)
                np.multiply(dots, ~self._projector_shadow(inv_z, projector_x_m), out=dots)
            # reflectance proxy; OpenCV takes a Python number as a scalar, its stubs accept only arrays
            weight = cv2.max(signal, float(np.float32(255.0 * s.reflectance_floor)))  # type: ignore[call-overload]
            weight *= inv_z
            weight *= inv_z  # irradiance falls off as 1 / z^2; zero where there is no surface
            dots *= weight
            signal *= np.float32(s.ambient_gain)
            signal += dots * np.float32(s.dot_peak_dn * s.reference_m**2 / 255.0)
        else:
            signal *= np.float32(s.ambient_gain)
        if self._noise is not None:
            std = signal * np.float32(s.shot_noise_gain)
            std += np.float32(s.read_noise_dn**2)
            np.sqrt(std, out=std)
            std *= self._noise.draw(rng)
            signal += std
        # round and saturate to 8 bits; OpenCV takes a Python number as a scalar, its stubs accept only arrays
        y8: np.ndarray = cv2.add(signal, 0.0, dtype=cv2.CV_8U)  # type: ignore[call-overload]
        return y8

    def _projector_shadow(self, inv_depth: np.ndarray, projector_x_m: float) -> np.ndarray:
        """Surface points hidden from the projector: stereo occlusion with the projector as second view."""
        d = inv_depth * np.float32(self.intr.fx * abs(projector_x_m))
        return occluded_from_right_scanline(d, mirrored=projector_x_m < 0)  # projector on the left: mirrored

    def pair(
        self,
        left_rgb: np.ndarray,
        left_depth_m: np.ndarray,
        right_rgb: np.ndarray,
        right_depth_m: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(ir1, ir2) from the left and right imagers' rendered colour and depth."""
        ir1 = self.image(left_rgb, left_depth_m, self.projector_x_m, rng)
        ir2 = self.image(right_rgb, right_depth_m, self.projector_x_m - self.baseline_m, rng)
        return ir1, ir2
