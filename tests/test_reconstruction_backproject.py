"""Back-projection: pixel-centre convention, depth scale, distortion (pyrealsense2 as oracle), edge
rejection, normals, incidence, colour, and the envelope window."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import ReconstructionError
from darp.formats.realsense.types import Intrinsics
from darp.reconstruction.backproject import (
    DepthFilterSettings,
    PosedDepth,
    backproject,
    camera_points,
    depth_to_metres,
    pixel_rays,
)
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.depth_edges import HOLE_SEARCH_PX, depth_normals, edge_holes
from darp.twin.camera.depth_model import DepthModel, DepthNoiseSettings
from darp.twin.camera.noise import correlated_normal
from helpers.synthetic_depth import Scene, look_at, small_intrinsics, sphere, table, to_z16

INTR = Intrinsics(64, 48, 380.0, 384.0, 31.2, 22.7)  # a D435-like pixel footprint on a small image


def rot_x(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def plane_depth(intr: Intrinsics, normal: np.ndarray, offset: float) -> np.ndarray:
    """Exact depth of the camera-frame plane n . p = offset along every pixel ray."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones(u.shape)], axis=-1)
    return offset / (rays @ normal)


def frame(depth_raw: np.ndarray, intr: Intrinsics = INTR, T: np.ndarray | None = None, scale: float = 0.001,
          colour: np.ndarray | None = None) -> PosedDepth:
    return PosedDepth("arm110", 0, depth_raw, scale, intr, np.eye(4) if T is None else T, colour)


NO_EDGES = DepthFilterSettings(edge_margin_px=0, max_incidence_deg=90.0)


def test_frontal_plane_follows_the_pixel_centre_convention() -> None:
    depth = np.full((INTR.height, INTR.width), 500, np.uint16)  # 0.5 m
    cloud = backproject(frame(depth), NO_EDGES)
    v, u = np.divmod(cloud.pixels, INTR.width)
    expected = np.column_stack([(u - INTR.ppx) * 0.5 / INTR.fx, (v - INTR.ppy) * 0.5 / INTR.fy,
                                np.full(u.size, 0.5)])
    # every pixel except the one-pixel image border (the normal stencil needs neighbours)
    assert len(cloud) == (INTR.width - 2 * NO_EDGES.normal_step_px) * (INTR.height - 2 * NO_EDGES.normal_step_px)
    np.testing.assert_allclose(cloud.points, expected, atol=1e-6)
    np.testing.assert_allclose(cloud.normals, np.tile([0.0, 0.0, -1.0], (len(cloud), 1)), atol=1e-5)


def test_depth_scale_is_honoured_and_pose_applied() -> None:
    depth = np.full((INTR.height, INTR.width), 1000, np.uint16)
    T = np.eye(4)
    T[:3, :3] = rot_x(np.pi)  # camera looks down -z from 0.8 m: the plane lands at world z = 0.3
    T[:3, 3] = [0.1, -0.2, 0.8]
    cloud = backproject(frame(depth, T=T, scale=0.0005), NO_EDGES)
    np.testing.assert_allclose(cloud.points[:, 2], 0.3, atol=1e-6)
    np.testing.assert_allclose(cloud.normals, np.tile([0.0, 0.0, 1.0], (len(cloud), 1)), atol=1e-5)
    np.testing.assert_allclose(cloud.camera_centre, [0.1, -0.2, 0.8])
    assert depth_to_metres(depth, 0.0005).max() == pytest.approx(0.5)


def test_tilted_plane_is_kept_whole_and_exact() -> None:
    normal = np.array([0.0, np.sin(0.6), -np.cos(0.6)])  # 34 deg from frontal, facing the camera
    depth_m = plane_depth(INTR, normal, -0.45)
    settings = DepthFilterSettings()
    cloud = backproject(frame(depth_m.astype(np.float32), scale=1.0), settings)
    m = settings.edge_margin_px
    assert len(cloud) == (INTR.width - 2 * m) * (INTR.height - 2 * m)  # a smooth surface loses only the border
    np.testing.assert_allclose(cloud.points @ normal, -0.45, atol=2e-6)
    np.testing.assert_allclose(cloud.normals, np.tile(normal, (len(cloud), 1)), atol=1e-4)


def test_step_edge_and_flying_pixels_are_removed() -> None:
    depth = np.full((INTR.height, INTR.width), 400, np.uint16)
    depth[:, 32:] = 600
    depth[:, 31] = 500  # a column of flying pixels between foreground and background
    settings = DepthFilterSettings(edge_margin_px=2)
    cloud = backproject(frame(depth), settings)
    _, u = np.divmod(cloud.pixels, INTR.width)
    assert not np.any((u >= 31 - 2) & (u <= 32 + 2)), "points survived next to the discontinuity"
    z = cloud.points[:, 2]
    assert np.all((np.abs(z - 0.4) < 1e-6) | (np.abs(z - 0.6) < 1e-6)), "a flying pixel survived"
    # away from the edge both sides are kept whole
    assert np.count_nonzero(u == 20) == INTR.height - 4 and np.count_nonzero(u == 45) == INTR.height - 4


def test_surface_holes_cost_only_the_hole_margin() -> None:
    depth = np.full((INTR.height, INTR.width), 450, np.uint16)
    depth[20, 30] = 0  # a one-pixel dropout inside a frontal plane
    border = DepthFilterSettings().normal_step_px
    whole = (INTR.width - 2 * border) * (INTR.height - 2 * border)
    # by default only the hole itself is lost: its neighbours' normals fall back to one-sided differences
    default = backproject(frame(depth), DepthFilterSettings(edge_margin_px=1))
    assert len(default) == whole - 1
    np.testing.assert_allclose(default.normals, np.tile([0.0, 0.0, -1.0], (len(default), 1)), atol=1e-5)
    # hole_margin_px = 1 drops the 3x3 around it, and nothing else
    eroded = backproject(frame(depth), DepthFilterSettings(edge_margin_px=1, hole_margin_px=1))
    v, u = np.divmod(eroded.pixels, INTR.width)
    assert not np.any((np.abs(v - 20) <= 1) & (np.abs(u - 30) <= 1))
    assert len(eroded) == whole - 9


def test_grazing_surfaces_are_dropped_by_incidence() -> None:
    normal = np.array([0.0, np.sin(np.radians(70.0)), -np.cos(np.radians(70.0))])
    depth_m = plane_depth(INTR, normal, -0.15).astype(np.float32)
    loose = DepthFilterSettings(max_incidence_deg=90.0, discontinuity_rel=0.5, edge_margin_px=0)
    strict = DepthFilterSettings(max_incidence_deg=70.0, discontinuity_rel=0.5, edge_margin_px=0)

    def incidence_deg(points: np.ndarray) -> np.ndarray:
        rays = points / np.linalg.norm(points, axis=1, keepdims=True)
        return np.degrees(np.arccos(-(rays @ normal)))

    everything = backproject(frame(depth_m, scale=1.0), loose)
    kept = backproject(frame(depth_m, scale=1.0), strict)
    angles = incidence_deg(everything.points)
    assert angles.min() < 69.0 and angles.max() > 71.0  # the plane spans the threshold
    assert np.all(incidence_deg(kept.points) <= 70.0 + 0.05)
    assert abs(len(kept) - np.count_nonzero(angles <= 70.0)) <= INTR.width  # at most one row differs


def test_colour_is_taken_from_the_aligned_image() -> None:
    depth = np.full((INTR.height, INTR.width), 500, np.uint16)
    colour = np.zeros((INTR.height, INTR.width, 3), np.uint8)
    colour[..., 0] = np.arange(INTR.width)[None, :]
    colour[..., 1] = np.arange(INTR.height)[:, None]
    cloud = backproject(frame(depth, colour=colour), NO_EDGES)
    v, u = np.divmod(cloud.pixels, INTR.width)
    np.testing.assert_array_equal(cloud.colours[:, 0], u)
    np.testing.assert_array_equal(cloud.colours[:, 1], v)
    with pytest.raises(ReconstructionError, match="not aligned"):
        backproject(frame(depth, colour=colour[:10]), NO_EDGES)


@pytest.mark.parametrize("model", ["Brown Conrady", "Inverse Brown Conrady"])
def test_distorted_rays_match_librealsense(model: str) -> None:
    rs = pytest.importorskip("pyrealsense2")
    coeffs = (0.08, -0.04, 0.0015, -0.001, 0.01)
    intr = Intrinsics(64, 48, 50.0, 52.0, 31.2, 22.7, model, coeffs)
    rays = pixel_rays(intr)
    ri = rs.intrinsics()
    ri.width, ri.height, ri.fx, ri.fy, ri.ppx, ri.ppy = 64, 48, 50.0, 52.0, 31.2, 22.7
    ri.model = rs.distortion.brown_conrady if model == "Brown Conrady" else rs.distortion.inverse_brown_conrady
    ri.coeffs = list(coeffs)
    for u, v in [(0, 0), (63, 47), (10, 40), (31, 22), (50, 5)]:
        x, y, z = rs.rs2_deproject_pixel_to_point(ri, [float(u), float(v)], 1.0)
        assert rays[v, u] == pytest.approx([x / z, y / z], abs=2e-6)


def test_zero_coefficients_are_pinhole_and_unknown_distortion_is_refused() -> None:
    pinhole = pixel_rays(Intrinsics(8, 6, 5.0, 5.0, 3.5, 2.5, "Modified Brown Conrady"))
    assert pinhole[2, 7] == pytest.approx([(7 - 3.5) / 5.0, (2 - 2.5) / 5.0])
    with pytest.raises(ReconstructionError, match="Kannala Brandt4"):
        pixel_rays(Intrinsics(8, 6, 5.0, 5.0, 3.5, 2.5, "Kannala Brandt4", (0.1, 0, 0, 0, 0)))


def test_bad_inputs_are_refused() -> None:
    depth = np.full((INTR.height, INTR.width), 500, np.uint16)
    with pytest.raises(ReconstructionError, match="intrinsics are 64x48"):
        backproject(frame(depth[:, :10]))
    with pytest.raises(ReconstructionError, match="NaN"):
        backproject(frame(depth, T=np.full((4, 4), np.nan)))
    with pytest.raises(ReconstructionError, match="not a rigid"):
        backproject(frame(depth, T=np.diag([2.0, 1.0, 1.0, 1.0])))
    with pytest.raises(ReconstructionError, match="depth scale"):
        backproject(frame(depth, scale=0.0))
    with pytest.raises(ReconstructionError, match="depth range"):
        DepthFilterSettings(min_depth_m=1.0, max_depth_m=0.5)
    with pytest.raises(ReconstructionError, match="hole_margin_px"):
        DepthFilterSettings(hole_margin_px=-1)
    with pytest.raises(ReconstructionError, match="stereo_baseline_m"):
        DepthFilterSettings(stereo_baseline_m=-0.05)
    with pytest.raises(ReconstructionError, match="stereo_baseline_m"):
        DepthFilterSettings(stereo_baseline_m=0.0)
    assert camera_points(depth_to_metres(depth, 0.001), INTR).shape == (48, 64, 3)


@pytest.mark.parametrize("holes", [False, True])
def test_region_window_gives_the_same_points_as_cropping_afterwards(holes: bool) -> None:
    """Working in the envelope's pixel window only changes the cost: with and without dropouts."""
    intr = small_intrinsics(160, 120, 190.0)  # a D435-like pixel footprint at this size
    scene = Scene([sphere(0.05, (0.0, 0.0, 0.05), 60), table()])
    crop = EnvelopeCrop((0.0, 0.0, 0.05), 0.05, 0.1, table_z_m=0.0)
    T = look_at((0.3, 0.1, 0.25), (0.0, 0.0, 0.05))
    depth, _ = scene.render(T, intr)
    if holes:  # blob dropouts everywhere (sphere and table), some reaching the silhouette
        depth = np.where(correlated_normal(depth.shape, 2.0, np.random.default_rng(4)) < -0.5, 0.0, depth)
    f = frame(to_z16(depth), intr, T)
    full = backproject(f)
    cropped = backproject(f, region=crop)
    inside = crop.contains(full.points)
    assert 0 < len(cropped) < len(full)
    np.testing.assert_array_equal(np.sort(cropped.pixels), np.sort(full.pixels[inside]))


# -- holes inside surfaces vs holes at edges -------------------------------------------------------
D4 = Intrinsics(160, 120, 380.0, 380.0, 79.5, 59.5)  # D435 pixel footprint (fx 380 px at 640x480)


def blob_holes(shape: tuple[int, int], seed: int, fraction: float, keep_border_px: int) -> np.ndarray:
    """Blob-shaped dropouts (a correlated field below its quantile) away from the image border."""
    field = correlated_normal(shape, 1.5, np.random.default_rng(seed))
    holes = field < np.quantile(field, fraction)
    b = keep_border_px
    holes[:b], holes[-b:], holes[:, :b], holes[:, -b:] = False, False, False, False
    return holes


def longest_run(mask: np.ndarray) -> int:
    """The longest run of set pixels along any row."""
    padded = np.zeros((mask.shape[0], mask.shape[1] + 2), np.int8)
    padded[:, 1:-1] = mask
    change = np.diff(padded, axis=1)
    starts, ends = np.nonzero(change == 1), np.nonzero(change == -1)
    return int((ends[1] - starts[1]).max(initial=0))


@pytest.mark.parametrize("tilt_deg", [0.0, 35.0, 65.0])
def test_plane_with_dropout_blobs_keeps_every_valid_pixel(tilt_deg: float) -> None:
    t = np.radians(tilt_deg)
    normal = np.array([np.sin(t) * 0.6, np.sin(t) * 0.8, -np.cos(t)])  # tilted along a diagonal
    depth_m = plane_depth(D4, normal, -0.40 * np.cos(t)).astype(np.float32)
    holes = blob_holes(depth_m.shape, 7, 0.3, keep_border_px=30)
    assert holes[30:-30, 30:-30].mean() > 0.2
    assert longest_run(holes) <= HOLE_SEARCH_PX and longest_run(holes.T) <= HOLE_SEARCH_PX  # else an edge
    depth_m[holes] = 0.0
    settings = DepthFilterSettings()
    cloud = backproject(frame(depth_m, D4, scale=1.0), settings)
    assert not edge_holes(depth_m, depth_m > 0, settings, D4.fx, D4.fy).any()
    # judged around the blobs (farther out, the steepest plane's far corner reaches 0.8 m, where its
    # diagonal neighbours differ by more than the discontinuity threshold: not this test's business)
    area = np.zeros(depth_m.shape, bool)
    area[25:-25, 25:-25] = True
    v, u = np.divmod(cloud.pixels, D4.width)
    kept = np.zeros(depth_m.shape, bool)
    kept[v, u] = True
    valid = area & ~holes
    assert not np.any(kept & holes)
    # nearly every valid pixel survives; the losses are pixels with a hole on both sides of both steps
    assert np.count_nonzero(kept & valid) >= 0.995 * np.count_nonzero(valid)
    np.testing.assert_allclose(cloud.points @ normal, -0.40 * np.cos(t), atol=2e-6)
    np.testing.assert_allclose(cloud.normals, np.tile(normal, (len(cloud), 1)), atol=2e-4)
    # the old rule (every hole is an edge) loses a large part of them
    old = backproject(frame(depth_m, D4, scale=1.0), DepthFilterSettings(hole_margin_px=2))
    kept_old = np.zeros(depth_m.shape, bool)
    kept_old[np.divmod(old.pixels, D4.width)] = True
    assert np.count_nonzero(kept_old & valid) < 0.7 * np.count_nonzero(valid)


def box_scene() -> tuple[np.ndarray, np.ndarray]:
    """A frontal foreground box (0.40 m) in front of a background plane (0.50 m), as D4 depth:
    ``(measured depth, exact depth)``. The occlusion band on the box's left is as wide as the
    disparity difference; the box is fattened by 2 px in every direction (eating into the band), and a
    few fattened pixels carry flying values between foreground and background."""
    z_fg, z_bg = 0.40, 0.50
    exact = np.full((D4.height, D4.width), z_bg, np.float32)
    r0, r1, c0, c1 = 30, 90, 60, 110
    exact[r0:r1, c0:c1] = z_fg
    measured = exact.copy()
    band = round(D4.fx * 0.05 * (1 / z_fg - 1 / z_bg))  # 9.5 -> 10 px
    measured[r0:r1, c0 - band:c0] = 0.0
    measured[r0 - 2:r1 + 2, c0 - 2:c1 + 2] = z_fg  # edge fattening (foreground depth at background positions)
    measured[40:45, c0 - 1] = 0.45  # flying pixels between foreground and background, next to the band
    measured[60:63, c1 + 1] = 0.46
    return measured, exact


def test_occlusion_band_fattening_and_flying_pixels_are_still_removed() -> None:
    measured, exact = box_scene()
    settings = DepthFilterSettings()
    cloud = backproject(frame(measured, D4, scale=1.0), settings)
    v, u = np.divmod(cloud.pixels, D4.width)
    # every kept point is where it should be: no fattened foreground at background positions, no flying pixel
    np.testing.assert_allclose(cloud.points[:, 2], exact[v, u], atol=1e-6)
    # the band is an edge hole; the box's interior and the background away from it are kept
    holes = measured == 0
    assert edge_holes(measured, ~holes, settings, D4.fx, D4.fy)[holes].all()
    kept = np.zeros(measured.shape, bool)
    kept[v, u] = True
    assert kept[33:87, 63:107].all()
    assert kept[5:25, 5:150].all() and kept[95:115, 5:150].all()


def test_d4_model_with_a_dark_box_keeps_only_true_depth() -> None:
    """The twin's D4 model (noise, occlusion band, fattening, flying pixels, blob dropouts on the box):
    the kept points are within the noise of the exact depth, and far more of the box survives than
    with a margin around every hole."""
    _, exact = box_scene()
    model = DepthModel(DepthNoiseSettings(), D4.fx, 0.05)
    dark = np.zeros(exact.shape, np.float32)
    dark[exact < 0.45] = 0.6  # the box is dark: 60 % dropout in ~2 px blobs
    kept_new = kept_old = 0
    for seed in range(4):
        measured = model.apply(exact, np.random.default_rng(seed), dropout_prob=dark)
        for settings in (DepthFilterSettings(), DepthFilterSettings(hole_margin_px=2)):
            cloud = backproject(frame(measured, D4, scale=1.0), settings)
            v, u = np.divmod(cloud.pixels, D4.width)
            error = np.abs(cloud.points[:, 2] - exact[v, u])
            assert error.max() < 0.004, f"seed {seed}: a point {error.max() * 1000:.1f} mm off the true surface"
            on_box = np.count_nonzero(exact[v, u] < 0.45)
            if settings.hole_margin_px == 0:
                kept_new += on_box
            else:
                kept_old += on_box
    assert kept_new > 2 * kept_old


def test_hole_at_a_silhouette_is_an_edge() -> None:
    exact = np.full((D4.height, D4.width), 0.50, np.float32)
    exact[30:90, 60:110] = 0.40
    measured = exact.copy()
    measured[50:58, 104:116] = 0.0  # a dropout straddling the box's right silhouette
    measured[20:35, 80:86] = 0.0  # ... and one straddling its top silhouette
    measured[65:70, 80:84] = 0.0  # a dropout inside the box
    settings = DepthFilterSettings()
    valid = measured > 0
    edges = edge_holes(measured, valid, settings, D4.fx, D4.fy)
    assert edges[50:58, 104:116].all() and edges[20:35, 80:86].all()
    assert not edges[65:70, 80:84].any()
    cloud = backproject(frame(measured, D4, scale=1.0), settings)
    kept = np.zeros(measured.shape, bool)
    kept[np.divmod(cloud.pixels, D4.width)] = True
    assert not kept[50:58, 102:104].any()  # the two box pixels left of the silhouette hole
    assert not kept[35:37, 80:86].any()  # ... and below the top one
    assert kept[63:72, 78:86][valid[63:72, 78:86]].all()  # the surface hole costs nothing
    # against nothing (background beyond the depth range) the same holds
    far = measured.copy()
    far[exact > 0.45] = 3.0
    cloud = backproject(frame(far, D4, scale=1.0), settings)
    kept[:] = False
    kept[np.divmod(cloud.pixels, D4.width)] = True
    assert not kept[50:58, 102:104].any() and not kept[30:32, 60:110].any()
    assert kept[63:72, 78:86][valid[63:72, 78:86]].all()


def test_normals_fall_back_to_one_sided_differences_but_not_across_a_jump() -> None:
    normal = np.array([0.3, -0.2, -0.93])
    normal /= np.linalg.norm(normal)
    depth_m = plane_depth(INTR, normal, -0.4).astype(np.float32)
    depth_m[10, 22:24] = 0.0  # right of (10, 21): both steps are holes -> centre - left
    depth_m[30, 19:21] = 0.0  # left of (30, 21): right - centre
    depth_m[20, 21:23] = 0.0  # right of (20, 20) ...
    depth_m[20, 18:20] += 0.03  # ... and a step on its left: no usable difference
    points = camera_points(depth_m, INTR)
    normals, ok = depth_normals(points, 2)
    assert ok[10, 21] and ok[30, 21]
    np.testing.assert_allclose(normals[10, 21], normal, atol=1e-4)
    np.testing.assert_allclose(normals[30, 21], normal, atol=1e-4)
    assert not ok[20, 20]
    assert not ok[0:2].any() and not ok[:, -2:].any()  # the stencil would leave the image
    assert ok[15, 30] and np.dot(normals[15, 30], points[15, 30]) < 0  # toward the camera
