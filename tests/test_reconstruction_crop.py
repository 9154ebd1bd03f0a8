"""Envelope crop and the per-pixel object-support mask, on exact renders of an object on a table."""

from __future__ import annotations

import numpy as np
import pytest

from darp.errors import ReconstructionError
from darp.formats.envelope import Envelope
from darp.reconstruction.backproject import PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop, support_mask
from helpers.synthetic_depth import Scene, box, look_at, small_intrinsics, sphere, table, to_z16

CENTRE = (0.05, -0.02, 0.04)
RADIUS = 0.04


@pytest.fixture(scope="module")
def scene() -> Scene:
    # object (geometry 0), table (1), and a background box well outside the envelope (2)
    return Scene([sphere(RADIUS, CENTRE, 80), table(), box((0.05, 0.05, 0.1), (-0.25, 0.15, 0.0))])


def envelope() -> Envelope:
    return Envelope(object_name="ball", center_m=CENTRE, radius_m=RADIUS, height_m=2 * RADIUS)


def test_contains_follows_the_cylinder_table_and_margins() -> None:
    crop = EnvelopeCrop.from_envelope(envelope(), margin_m=0.01, table_margin_m=0.003)
    assert crop.table_z_m == pytest.approx(0.0)
    assert crop.z_range_m == pytest.approx((0.003, 0.09))
    cx, cy, _ = CENTRE
    pts = np.array([
        [cx, cy, 0.04],  # centre
        [cx + 0.049, cy, 0.04],  # inside the radial margin
        [cx + 0.051, cy, 0.04],  # outside it
        [cx, cy, 0.002],  # within the table margin: table, not object
        [cx, cy, 0.004],  # just above it
        [cx, cy, 0.089],  # below top + margin
        [cx, cy, 0.091],  # above it
    ])
    np.testing.assert_array_equal(crop.contains(pts), [True, True, False, False, True, True, False])
    lo, hi = crop.bounds_m
    assert lo == pytest.approx([cx - 0.05, cy - 0.05, 0.003]) and hi == pytest.approx([cx + 0.05, cy + 0.05, 0.09])


def test_explicit_table_height_and_missing_geometry() -> None:
    crop = EnvelopeCrop.from_envelope(envelope(), table_z_m=-0.01, table_margin_m=0.002)
    assert crop.z_range_m[0] == pytest.approx(-0.008)
    with pytest.raises(ReconstructionError, match="no centre/radius/height"):
        EnvelopeCrop.from_envelope(Envelope(object_name="x"))
    with pytest.raises(ReconstructionError, match="radius and height"):
        EnvelopeCrop((0, 0, 0), -1.0, 0.1, 0.0)


def test_crop_removes_table_and_background(scene: Scene) -> None:
    intr = small_intrinsics(200, 150, 120.0)
    crop = EnvelopeCrop.from_envelope(envelope())
    T = look_at((0.35, -0.25, 0.3), CENTRE)
    depth, geometry = scene.render(T, intr)
    assert {0, 1, 2} <= set(np.unique(geometry))  # the view sees object, table and background
    frame = PosedDepth("arm110", 0, to_z16(depth), 0.001, intr, T)
    everything = backproject(frame)
    cropped = backproject(frame, region=crop)
    hit = geometry.reshape(-1)[cropped.pixels]
    assert np.all(hit == 0), "table or background points survived the crop"
    assert np.all(cropped.points[:, 2] >= 0.003 - 1e-6)
    on_object = geometry.reshape(-1)[everything.pixels] == 0
    high = everything.points[:, 2] > 0.004
    # every filtered object point above the table margin is kept
    assert set(everything.pixels[on_object & high]) <= set(cropped.pixels)


def test_support_mask_is_conservative(scene: Scene) -> None:
    intr = small_intrinsics(200, 150, 120.0)
    T = look_at((-0.2, 0.3, 0.35), CENTRE)
    depth, geometry = scene.render(T, intr)
    raw = to_z16(depth)
    mask = support_mask(raw, intr, T, envelope(), depth_scale=0.001)
    # the object's pixels above the table margin are all in the mask ...
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.ppx) / intr.fx, (v - intr.ppy) / intr.fy, np.ones(u.shape)], -1)
    world_z = (rays * depth[..., None]) @ T[2, :3] + T[2, 3]
    object_px = (geometry == 0) & (world_z > 0.004)
    assert object_px.sum() > 200
    assert np.all(mask[object_px])
    # ... and nothing outside the cylinder: no background, no table beyond the radial margin
    assert not np.any(mask[geometry == 2])
    assert not np.any(mask[(geometry == 1) & (world_z < 0.002)])
    assert not np.any(mask[raw == 0])
    # metric depth and an EnvelopeCrop give the same mask; raw depth needs its scale
    crop = EnvelopeCrop.from_envelope(envelope())
    np.testing.assert_array_equal(support_mask(raw.astype(np.float32) * 0.001, intr, T, crop), mask)
    with pytest.raises(ReconstructionError, match="depth_scale"):
        support_mask(raw, intr, T, envelope())
