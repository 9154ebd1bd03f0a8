"""Random fields for the simulated camera: correlated Gaussian noise and a reusable noise bank.

Drawing 300k-900k Gaussian samples costs 3-9 ms per image on the twin's 2-core CPU, more than the
rest of the noise model. A :class:`NoiseBank` draws a field four times the image size once (from a
seeded generator) and each frame takes a window at a random offset: per frame the cost is two random
integers, the samples of one frame are independent, and two frames share no sample position unless
their offsets coincide (probability about 1/(H*W)).
"""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray


def correlated_normal(shape: tuple[int, int], sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-variance Gaussian field with Gaussian spatial correlation of ``sigma_px`` (float32).

    For ``sigma_px >= 0.5`` the white input is uniform rather than normal (five times cheaper to draw);
    the blur sums many samples, so the field is close to Gaussian (central limit theorem).
    """
    if sigma_px < 0.5:
        white = rng.standard_normal(shape, dtype=np.float32)
        if sigma_px <= 0.0:
            return white
    else:
        white = rng.random(shape, dtype=np.float32)
        white -= np.float32(0.5)
        white *= np.float32(np.sqrt(12.0))
    ksize = 2 * int(np.ceil(3.0 * sigma_px)) + 1
    g = cv2.getGaussianKernel(ksize, sigma_px, cv2.CV_64F).ravel()
    field = cast("NDArray[np.float32]", cv2.sepFilter2D(white, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT))
    field *= np.float32(1.0 / float(np.sum(g * g)))  # separable: std scales by sum(g^2)
    return field


class NoiseBank:
    """A pre-drawn unit-variance field (optionally spatially correlated) sampled by random windows."""

    def __init__(
        self,
        shape: tuple[int, ...],
        rng: np.random.Generator,
        *,
        correlation_px: float = 0.0,
        scale: float = 1.0,
        dtype: type = np.float32,
    ) -> None:
        h, w = shape[:2]
        channels = shape[2:]
        self.shape = tuple(shape)
        big = (2 * h, 2 * w)
        if channels:
            planes = [correlated_normal(big, correlation_px, rng) for _ in range(channels[0])]
            field = np.stack(planes, axis=-1)
        else:
            field = correlated_normal(big, correlation_px, rng)
        field *= np.float32(scale)
        self._field = (
            np.rint(field).astype(dtype) if np.issubdtype(dtype, np.integer) else field.astype(dtype)
        )

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """A window of the bank (a view, do not modify) of the bank's image shape."""
        h, w = self.shape[:2]
        oy = int(rng.integers(0, h + 1))
        ox = int(rng.integers(0, w + 1))
        return self._field[oy : oy + h, ox : ox + w]
