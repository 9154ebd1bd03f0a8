"""The parametric D4 depth model on synthetic exact depth images (no rendering): statistics and artefacts."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import TwinError
from darp.twin.camera.depth_model import (
    DepthModel,
    DepthNoiseSettings,
    depth_to_z16,
    occluded_from_right_depth,
    occluded_from_right_scanline,
)

FX = 383.5
B = 0.050
H, W = 480, 640
SUBPIXEL = 0.08
Q_SIGMA_M = 0.001 / np.sqrt(12.0)


def plane(z: float) -> np.ndarray:
    return np.full((H, W), z, np.float32)


def fg_box_scene(
    z_fg: float, z_bg: float, cols: tuple[int, int], rows: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Left and right exact depth of a fronto-parallel box in front of a wall (rectified pair)."""
    left = plane(z_bg)
    left[rows[0] : rows[1], cols[0] : cols[1]] = z_fg
    right = plane(z_bg)
    shift = FX * B / z_fg  # the box sits this many pixels further left in the right image
    c0, c1 = round(cols[0] - shift), round(cols[1] - shift)
    right[rows[0] : rows[1], max(c0, 0) : max(c1, 0)] = z_fg
    return left, right


def plane_residual(depth_m: np.ndarray, roi: tuple[slice, slice]) -> np.ndarray:
    """Residuals of valid depth in ``roi`` after a least-squares plane fit z = a u + b v + c."""
    z = depth_m[roi]
    v, u = np.mgrid[roi[0], roi[1]]
    ok = z > 0
    A = np.column_stack([u[ok], v[ok], np.ones(ok.sum())])
    coef, *_ = np.linalg.lstsq(A, z[ok].astype(np.float64), rcond=None)
    res = np.zeros(z.shape)
    res[ok] = z[ok] - A @ coef
    return res


ROI = (slice(140, 340), slice(260, 460))


@pytest.mark.parametrize("z", [0.30, 0.45, 0.60])
def test_noise_rms_follows_intel_formula(z: float) -> None:
    model = DepthModel(DepthNoiseSettings.realistic(), FX, B)
    rng = np.random.default_rng(7)
    rms = []
    for _ in range(4):
        measured = depth_to_z16(model.apply(plane(z), rng)) * 0.001
        rms.append(np.std(plane_residual(measured, ROI)[measured[ROI] > 0]))
    predicted = np.hypot(z * z * SUBPIXEL / (FX * B), Q_SIGMA_M)
    assert np.mean(rms) == pytest.approx(predicted, rel=0.30)


def test_noise_is_spatially_correlated_and_unbiased() -> None:
    model = DepthModel(DepthNoiseSettings.realistic().with_(pixel_locking_px=0.0), FX, B)
    d = model.apply(plane(0.6), np.random.default_rng(3)) - 0.6
    patch = d[ROI]
    horizontal = np.corrcoef(patch[:, :-1].ravel(), patch[:, 1:].ravel())[0, 1]
    vertical = np.corrcoef(patch[:-1].ravel(), patch[1:].ravel())[0, 1]
    far = np.corrcoef(patch[:, :-10].ravel(), patch[:, 10:].ravel())[0, 1]
    assert horizontal > 0.5 and vertical > 0.5
    assert abs(far) < 0.1  # correlation length of a few pixels, not a global offset
    assert abs(np.mean(patch)) < 0.2 * np.std(patch)


def test_white_noise_option_is_uncorrelated() -> None:
    model = DepthModel(DepthNoiseSettings.realistic().with_(noise_correlation_px=0.0), FX, B)
    patch = (model.apply(plane(0.6), np.random.default_rng(3)) - 0.6)[ROI]
    assert abs(np.corrcoef(patch[:, :-1].ravel(), patch[:, 1:].ravel())[0, 1]) < 0.1


def test_disparity_is_quantised_to_one_32nd_pixel() -> None:
    model = DepthModel(DepthNoiseSettings.realistic(), FX, B)
    z = model.apply(plane(0.45), np.random.default_rng(1))
    d32 = FX * B / z[z > 0] * 32.0
    assert np.max(np.abs(d32 - np.rint(d32))) < 1e-3
    assert len(np.unique(np.rint(d32))) > 5  # noise spans several steps


@pytest.mark.parametrize("z", [0.30, 0.55])
def test_left_band_width_is_f_b_over_z(z: float) -> None:
    model = DepthModel(DepthNoiseSettings.realistic(), FX, B)
    out = model.apply(plane(z), np.random.default_rng(2))
    first_valid = np.argmax(out[100:380] > 0, axis=1)
    assert np.median(first_valid) == pytest.approx(FX * B / z, abs=1.0)
    assert np.all(out[100:380, W // 2 :] > 0)


@pytest.mark.parametrize("use_right_view", [True, False])
def test_occlusion_hole_left_of_foreground(use_right_view: bool) -> None:
    z_fg, z_bg = 0.35, 0.60
    left, right = fg_box_scene(z_fg, z_bg, cols=(300, 420), rows=(180, 300))
    settings = DepthNoiseSettings.realistic().with_(edge_fattening_px=0, flying_pixel_prob=0.0)
    model = DepthModel(settings, FX, B)
    out = model.apply(left, np.random.default_rng(4), depth_right_m=right if use_right_view else None)
    predicted = FX * B * (1 / z_fg - 1 / z_bg)
    widths = [300 - np.flatnonzero(out[row, :300] > 0)[-1] - 1 for row in range(190, 290)]
    assert np.median(widths) == pytest.approx(predicted, abs=1.5)
    assert np.all(out[190:290, 310:410] > 0)  # the box itself is measured
    assert np.all(out[190:290, 430:600] > 0)  # no hole on the right side


def test_scanline_and_right_view_occlusion_agree() -> None:
    left, right = fg_box_scene(0.3, 0.5, cols=(250, 400), rows=(100, 400))
    d = FX * B / left
    a = occluded_from_right_scanline(d)
    b = occluded_from_right_depth(left, d, right, 0.01)
    assert a.sum() > 1000
    assert np.mean(a != b) < 0.002


def test_min_depth_is_invalid() -> None:
    model = DepthModel(DepthNoiseSettings.realistic(), FX, B)
    min_z = FX * B / 126.0
    assert np.all(model.apply(plane(0.9 * min_z), np.random.default_rng(0)) == 0)
    near = model.apply(plane(1.1 * min_z), np.random.default_rng(0))
    assert np.mean(near[:, W // 2 :] > 0) > 0.99


def test_edge_fattening_and_flying_pixels() -> None:
    z_fg, z_bg = 0.35, 0.60
    left, right = fg_box_scene(z_fg, z_bg, cols=(300, 420), rows=(180, 300))
    quiet = DepthNoiseSettings.realistic().with_(
        subpixel_rms_px=0.0, pixel_locking_px=0.0, disparity_step_px=0.0
    )
    plain = DepthModel(quiet.with_(edge_fattening_px=0, flying_pixel_prob=0.0), FX, B)
    fat = DepthModel(quiet.with_(edge_fattening_px=2, flying_pixel_prob=0.0), FX, B)
    flying = DepthModel(
        quiet.with_(edge_fattening_px=0, flying_pixel_prob=1.0, flying_pixel_band_px=2), FX, B
    )
    rng = np.random.default_rng(5)
    base = plain.apply(left, rng, depth_right_m=right)
    grown = fat.apply(left, rng, depth_right_m=right)
    # Foreground grows by 2 px into the background on the right edge and below the box.
    assert np.allclose(grown[200:280, 420:422], z_fg, atol=1e-4)
    assert np.allclose(base[200:280, 420:422], z_bg, atol=1e-4)
    assert np.allclose(grown[300:302, 320:400], z_fg, atol=1e-4)
    fly = flying.apply(left, rng, depth_right_m=right)
    between = (fly > z_fg + 0.002) & (fly < z_bg - 0.002)
    assert between[180:300, 418:424].mean() > 0.3  # intermediate depths at the edge
    assert not between[:, :250].any() and not between[:, 480:].any()  # and nowhere else


def test_material_dropouts_follow_probability_map() -> None:
    model = DepthModel(DepthNoiseSettings.realistic(), FX, B)
    prob = np.zeros((H, W), np.float32)
    prob[:, 320:] = 0.6
    out = model.apply(plane(0.5), np.random.default_rng(8), dropout_prob=prob)
    assert np.mean(out[:, 400:] == 0) == pytest.approx(0.6, abs=0.15)
    assert np.mean(out[:, 100:300] == 0) == 0.0
    holes = (out[:, 400:] == 0).astype(float)
    assert np.corrcoef(holes[:, :-1].ravel(), holes[:, 1:].ravel())[0, 1] > 0.5  # blobs, not salt


def test_ideal_settings_pass_exact_depth_through() -> None:
    z = np.linspace(0.05, 3.0, H * W, dtype=np.float32).reshape(H, W)
    z[:10] = 0.0
    out = DepthModel(DepthNoiseSettings.ideal(), FX, B).apply(z, np.random.default_rng(0))
    assert np.allclose(out, z, rtol=1e-6, atol=0)
    assert np.array_equal(
        depth_to_z16(np.array([0.0, 0.1234, 0.12351, 70.0])), np.array([0, 123, 124, 65535], np.uint16)
    )


def test_scale_error_and_offset() -> None:
    base = DepthNoiseSettings.ideal()
    scaled = DepthModel(base.with_(depth_scale_error=-0.0193), FX, B).apply(
        plane(1.0), np.random.default_rng(0)
    )
    assert np.allclose(scaled, 0.9807, atol=1e-6)
    shifted = DepthModel(base.with_(disparity_offset_px=0.2), FX, B).apply(
        plane(1.0), np.random.default_rng(0)
    )
    assert np.allclose(shifted, FX * B / (FX * B / 1.0 + 0.2), atol=1e-6)


def test_same_generator_state_gives_same_output() -> None:
    left, right = fg_box_scene(0.35, 0.6, cols=(300, 420), rows=(180, 300))
    a = DepthModel(DepthNoiseSettings(), FX, B, bank_seed=1).apply(
        left, np.random.default_rng(3), depth_right_m=right
    )
    b = DepthModel(DepthNoiseSettings(), FX, B, bank_seed=1).apply(
        left, np.random.default_rng(3), depth_right_m=right
    )
    c = DepthModel(DepthNoiseSettings(), FX, B, bank_seed=2).apply(
        left, np.random.default_rng(4), depth_right_m=right
    )
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_bad_settings_are_rejected() -> None:
    with pytest.raises(TwinError, match="subpixel_rms_px"):
        DepthNoiseSettings(subpixel_rms_px=-1.0)
    with pytest.raises(TwinError, match="flying_pixel_prob"):
        DepthNoiseSettings(flying_pixel_prob=1.5)
    with pytest.raises(TwinError, match="baseline"):
        DepthModel(DepthNoiseSettings(), FX, 0.0)
    with pytest.raises(TwinError, match="2-D"):
        DepthModel(DepthNoiseSettings(), FX, B).apply(np.zeros(5, np.float32), np.random.default_rng(0))
