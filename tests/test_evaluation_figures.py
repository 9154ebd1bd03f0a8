"""Figures are written, non-trivial and in the paper's colours (arm110 red, arm111 blue)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from darp.errors import EvaluationError
from darp.evaluation.figures import cross_arm_figure, heldout_histogram, partial_fused_figure


def clouds() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = 0.04 * d + [0.0, 0.0, 0.04]
    return pts[pts[:, 0] > -0.01], pts[pts[:, 0] < 0.01]


def colour_pixels(path) -> tuple[int, int]:
    img = imread(path)[..., :3]
    red = (img[..., 0] > 0.6) & (img[..., 1] < 0.45) & (img[..., 2] < 0.45)
    blue = (img[..., 2] > 0.6) & (img[..., 0] < 0.45) & (img[..., 1] < 0.6)
    return int(red.sum()), int(blue.sum())


def test_cross_arm_figure_shows_both_arms(tmp_path) -> None:
    a, b = clouds()
    path = cross_arm_figure({"arm110": a, "arm111": b}, tmp_path / "cross.png", title="test")
    red, blue = colour_pixels(path)
    assert red > 500 and blue > 500
    assert imread(path).shape[1] > 1000  # three panels side by side
    only_red = cross_arm_figure({"arm110": a, "arm111": b[:0]}, tmp_path / "red.png")
    assert colour_pixels(only_red)[1] < 50
    assert not list(tmp_path.glob("*.partial"))


def test_partial_fused_figure_and_pdf_output(tmp_path) -> None:
    a, b = clouds()
    fused = np.vstack([a, b])
    colours = np.tile([20, 200, 20], (len(fused), 1)).astype(np.uint8)
    path = partial_fused_figure(a, b, fused, tmp_path / "partial.png", fused_colours=colours)
    img = imread(path)[..., :3]
    red, blue = colour_pixels(path)
    green = ((img[..., 1] > 0.6) & (img[..., 0] < 0.3) & (img[..., 2] < 0.3)).sum()
    assert red > 300 and blue > 300 and green > 300
    pdf = partial_fused_figure(a, b, fused, tmp_path / "partial.pdf")
    assert pdf.read_bytes().startswith(b"%PDF")


def test_heldout_histogram(tmp_path) -> None:
    rng = np.random.default_rng(0)
    distances = {"arm110": np.abs(rng.normal(size=5000)) * 0.002, "arm111": np.abs(rng.normal(size=4000)) * 0.003}
    path = heldout_histogram(distances, tmp_path / "hist.png")
    red, blue = colour_pixels(path)
    assert red > 50 and blue > 50
    with pytest.raises(EvaluationError, match="no held-out"):
        heldout_histogram({"arm110": np.empty(0)}, tmp_path / "empty.png")
    with pytest.raises(EvaluationError, match="every cloud is empty"):
        cross_arm_figure({"arm110": np.empty((0, 3))}, tmp_path / "none.png")
