"""Back-projection: pixel-centre convention, depth scale, distortion (pyrealsense2 as oracle), edge
rejection, normals, incidence, colour, and the envelope window."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_depth import Scene, look_at, small_intrinsics, sphere, table, to_z16

from darp.errors import ReconstructionError
from darp.formats.recording_types import Intrinsics
from darp.reconstruction.backproject import (
    DepthFilterSettings,
    PosedDepth,
    backproject,
    camera_points,
    depth_to_metres,
    pixel_rays,
)
from darp.reconstruction.crop import EnvelopeCrop

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


def test_holes_erode_their_neighbours_only() -> None:
    depth = np.full((INTR.height, INTR.width), 450, np.uint16)
    depth[20, 30] = 0
    cloud = backproject(frame(depth), DepthFilterSettings(edge_margin_px=1))
    v, u = np.divmod(cloud.pixels, INTR.width)
    near = (np.abs(v - 20) <= 1) & (np.abs(u - 30) <= 1)
    assert not near.any()
    # the 3x3 around the hole, plus the four pixels whose normal stencil (+-2 px) reaches into it
    border = DepthFilterSettings().normal_step_px
    assert len(cloud) == (INTR.width - 2 * border) * (INTR.height - 2 * border) - 9 - 4


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
    assert camera_points(depth_to_metres(depth, 0.001), INTR).shape == (48, 64, 3)


def test_region_window_gives_the_same_points_as_cropping_afterwards() -> None:
    intr = small_intrinsics()
    scene = Scene([sphere(0.04, (0.02, 0.0, 0.04), 60), table()])
    crop = EnvelopeCrop((0.02, 0.0, 0.04), 0.04, 0.08, table_z_m=0.0)
    T = look_at((0.3, 0.15, 0.25), (0.02, 0.0, 0.04))
    depth, _ = scene.render(T, intr)
    f = frame(to_z16(depth), intr, T)
    full = backproject(f)
    cropped = backproject(f, region=crop)
    inside = crop.contains(full.points)
    assert 0 < len(cropped) < len(full)
    np.testing.assert_array_equal(np.sort(cropped.pixels), np.sort(full.pixels[inside]))
