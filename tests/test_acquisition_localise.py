"""Localisation on synthetic depth: the estimator, its rejections, the plane fit and the enclosing circle."""

from __future__ import annotations

import numpy as np
import pytest

from darp.acquisition.estimate import (
    LocaliseSettings,
    estimate_from_depth,
    fit_table_plane,
)
from darp.acquisition.localise import search_targets
from darp.geometry import min_enclosing_circle
from darp.kinematics import transforms as tf
from darp.kinematics.rig import load_rig
from helpers.acquisition_fakes import INTRINSICS, Cylinder, render_depth

RIG = load_rig()


def camera_looking_at(target: np.ndarray, distance: float, elevation_deg: float,
                      azimuth_deg: float = 180.0) -> np.ndarray:
    """T_world_cam of a camera ``distance`` from ``target`` at the given elevation and azimuth (world)."""
    e, a = np.radians(elevation_deg), np.radians(azimuth_deg)
    eye = target + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return tf.look_at(eye, target)


def frames_of(objects: list[Cylinder], T: np.ndarray, n: int = 2) -> list[tuple[np.ndarray, object, np.ndarray]]:
    depth = render_depth(T, INTRINSICS, objects, RIG)
    return [(depth, INTRINSICS, T)] * n


@pytest.mark.parametrize("azimuth, radius, height", [(180.0, 0.05, 0.10), (0.0, 0.07, 0.06), (140.0, 0.04, 0.15)])
def test_cylinder_estimate_centre_radius_height(azimuth: float, radius: float, height: float) -> None:
    cyl = Cylinder(0.06, -0.04, radius, height)
    T = camera_looking_at(np.array([cyl.x_m, cyl.y_m, height / 2]), 0.45, 45.0, azimuth)
    obs = estimate_from_depth(frames_of([cyl], T), RIG, "arm110")
    assert obs.ok, obs.detail
    est = obs.estimate
    # Seen from one side: half the side wall and the top cap; the enclosing circle recovers the axis.
    assert np.linalg.norm(est.centre_m[:2] - [cyl.x_m, cyl.y_m]) < 0.005
    assert est.radius_m == pytest.approx(radius, abs=0.005)
    assert est.height_m == pytest.approx(height, abs=0.003)
    assert est.centre_m[2] == pytest.approx(height / 2, abs=0.002)
    assert est.n_points > 200 and est.valid_fraction > 0.5


def test_empty_table_is_no_object() -> None:
    T = camera_looking_at(np.zeros(3), 0.55, 50.0)
    obs = estimate_from_depth(frames_of([], T), RIG, "arm110")
    assert not obs.ok and obs.reason == "no_object"


def test_object_outside_the_workspace_is_rejected_with_its_position() -> None:
    cyl = Cylinder(0.0, 0.36, 0.04, 0.1)  # workspace y is +-0.25
    T = camera_looking_at(np.array([0.0, 0.36, 0.05]), 0.45, 45.0)
    obs = estimate_from_depth(frames_of([cyl], T), RIG, "arm110")
    assert obs.reason == "outside_workspace"
    assert obs.candidate is not None and abs(obs.candidate.centre_m[1] - 0.36) < 0.01
    assert "outside the workspace" in obs.detail


def test_object_cut_by_the_image_border_is_truncated() -> None:
    cyl = Cylinder(0.0, 0.0, 0.05, 0.1)
    T = camera_looking_at(np.array([0.0, 0.0, 0.05]), 0.45, 45.0)
    T = T @ tf.make_transform(tf.rot_y(np.radians(33.0)))  # turn right: the object slides to the left edge
    obs = estimate_from_depth(frames_of([cyl], T), RIG, "arm110")
    assert obs.reason == "truncated"


def test_sparse_depth_is_unreliable() -> None:
    cyl = Cylinder(0.0, 0.0, 0.05, 0.1)
    T = camera_looking_at(np.array([0.0, 0.0, 0.05]), 0.45, 45.0)
    depth = render_depth(T, INTRINSICS, [cyl], RIG)
    holes = np.random.default_rng(0).random(depth.shape) < 0.9
    obs = estimate_from_depth([(np.where(holes, 0.0, depth), INTRINSICS, T)], RIG, "arm110")
    assert obs.reason == "low_valid_fraction"
    few = estimate_from_depth([(depth, INTRINSICS, T)], RIG, "arm110", LocaliseSettings(min_points=5000))
    assert few.reason == "few_points"


def test_calibration_error_is_absorbed_by_the_fitted_table_plane() -> None:
    cyl = Cylinder(0.02, 0.03, 0.05, 0.08)
    T_true = camera_looking_at(np.array([cyl.x_m, cyl.y_m, 0.04]), 0.45, 45.0)
    depth = render_depth(T_true, INTRINSICS, [cyl], RIG)
    # The pose believed by a miscalibrated rig: 1 deg tilt and 8 mm too low.
    T_believed = tf.make_transform(tf.rot_x(np.radians(1.0)), [0.0, 0.0, -0.008]) @ T_true
    obs = estimate_from_depth([(depth, INTRINSICS, T_believed)] * 2, RIG, "arm110")
    assert obs.ok
    assert obs.estimate.height_m == pytest.approx(0.08, abs=0.004)  # measured from the plane it sees
    assert abs(obs.estimate.plane["c"] + 0.008) < 0.01
    nominal = estimate_from_depth([(depth, INTRINSICS, T_believed)] * 2, RIG, "arm110",
                                  LocaliseSettings(plane_band_m=1e-4))  # no plane found: the nominal table
    assert nominal.ok and abs(nominal.estimate.height_m - 0.08) > abs(obs.estimate.height_m - 0.08)


def test_plane_fit_recovers_a_tilted_plane_despite_an_object() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.3, 0.3, (4000, 2))
    z = 0.01 * xy[:, 0] - 0.02 * xy[:, 1] + 0.004 + rng.normal(0, 0.0005, 4000)
    obj = np.column_stack([rng.uniform(-0.03, 0.03, (800, 2)), rng.uniform(0.01, 0.03, 800)])
    coef, n = fit_table_plane(np.vstack([np.column_stack([xy, z]), obj]), 0.0, 0.04)
    np.testing.assert_allclose(coef, [0.01, -0.02, 0.004], atol=5e-4)
    assert 3500 < n <= 4200
    assert fit_table_plane(obj[:50], 0.0, 0.04) is None


def test_min_enclosing_circle_matches_opencv() -> None:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(2)
    for _ in range(20):
        pts = rng.normal(size=(int(rng.integers(3, 400)), 2)) * rng.uniform(0.01, 0.2, 2)
        centre, radius = min_enclosing_circle(pts)
        (cx, cy), r_cv = cv2.minEnclosingCircle(pts.astype(np.float32))
        dist = np.linalg.norm(pts - centre, axis=1)
        assert np.all(dist <= radius + 1e-9)  # encloses every point
        # OpenCV's circle (float32, padded slightly) is never smaller and its centre is the same.
        assert r_cv * (1 - 1e-3) <= radius <= r_cv + 1e-9
        assert np.linalg.norm(centre - [cx, cy]) < 1e-3 * radius
        # Optimal: the boundary points are not all within a half circle (centre in their convex hull).
        rim = pts[dist > radius - 1e-9] - centre
        angles = np.sort(np.arctan2(rim[:, 1], rim[:, 0]))
        gaps = np.diff(np.r_[angles, angles[0] + 2 * np.pi])
        assert len(rim) >= 2 and gaps.max() <= np.pi + 1e-6
    # A half circle's enclosing circle is the full circle: the far side need not be seen.
    a = np.linspace(0, np.pi, 50)
    centre, radius = min_enclosing_circle(np.column_stack([0.3 + 0.05 * np.cos(a), -0.1 + 0.05 * np.sin(a)]))
    np.testing.assert_allclose(centre, [0.3, -0.1], atol=1e-9)
    assert radius == pytest.approx(0.05)


def test_search_targets_start_at_the_workspace_centre_and_cover_it() -> None:
    targets = search_targets(RIG, "arm110")
    np.testing.assert_allclose(targets[0], [0.0, 0.0, 0.0], atol=1e-12)
    ws = RIG.workspace
    assert len(targets) == 9 and len({tuple(np.round(t, 6)) for t in targets}) == 9
    assert np.isclose(targets[:, 0].min(), ws.x_range_m[0]) and np.isclose(targets[:, 0].max(), ws.x_range_m[1])
    assert np.isclose(targets[:, 1].min(), ws.y_range_m[0]) and np.isclose(targets[:, 1].max(), ws.y_range_m[1])
    # The far row (from arm110 at -x) comes before the near row.
    assert targets[3, 0] > targets[6, 0]


def wavy_depth(depth: np.ndarray, field_px: float, seed: int, noise_px: float = 0.08) -> np.ndarray:
    """Depth with a stereo camera's disparity errors: a smooth field (std ``field_px`` on a 4 x 5 grid,
    cubic-interpolated, as the twin's D400 "breathing") plus per-pixel noise; depth error z^2 e / (f B)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    h, w = depth.shape
    nodes = rng.normal(0.0, field_px, (4, 5))
    field = ndimage.zoom(nodes, (h / 4, w / 5), order=3, mode="nearest")[:h, :w]
    e = field + rng.normal(0.0, noise_px, depth.shape)
    return np.where(depth > 0, depth + depth ** 2 * e / (INTRINSICS.fx * 0.05), 0.0)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_wavy_noisy_table_is_not_taken_for_the_object(seed: int) -> None:
    # Issue 12: at 2x the paper profile (424x240) the far table rose above the fixed 6 mm margin as one
    # wide flat blob that outweighed the object, which was then "found" at y ~ -0.3 m (outside the
    # workspace) or not at all. The margin now follows the view's own table noise at each range.
    cyl = Cylinder(-0.06, 0.07, 0.04, 0.10)
    T = camera_looking_at(np.zeros(3), 0.55, 50.0)
    clean = render_depth(T, INTRINSICS, [cyl], RIG)
    frames = [(wavy_depth(clean, 0.2, 10 * seed + k), INTRINSICS, T) for k in range(2)]
    obs = estimate_from_depth(frames, RIG, "arm110")
    assert obs.ok, obs.detail
    assert np.linalg.norm(obs.estimate.centre_m[:2] - [cyl.x_m, cyl.y_m]) < 0.015
    assert obs.estimate.radius_m < 0.06
    assert obs.stats["table_margin_mm"][1] > 10.0  # the far table's margin grew with its noise
    # The fixed margin alone (noise_floor_k = 0) takes the table for the object: the bug this fixes.
    fixed = estimate_from_depth(frames, RIG, "arm110", LocaliseSettings(noise_floor_k=0.0))
    est = fixed.estimate or fixed.candidate
    assert est is not None and (np.linalg.norm(est.centre_m[:2] - [cyl.x_m, cyl.y_m]) > 0.05 or est.radius_m > 0.1)


def test_a_clean_table_keeps_the_fixed_margin() -> None:
    cyl = Cylinder(0.0, 0.0, 0.05, 0.02)  # a low object: 2 cm, just above a 6 mm margin's worth of noise
    T = camera_looking_at(np.array([0.0, 0.0, 0.01]), 0.45, 45.0)
    obs = estimate_from_depth(frames_of([cyl], T), RIG, "arm110")
    assert obs.ok and obs.stats["table_margin_mm"] == [6.0, 6.0]
    assert obs.estimate.height_m == pytest.approx(0.02, abs=0.003)
