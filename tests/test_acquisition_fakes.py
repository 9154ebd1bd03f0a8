"""The acquisition tests' analytic rig (helpers.acquisition_fakes) held to Open3D's ray caster, and its clock
and arms to their specification."""

from __future__ import annotations

import numpy as np
import pytest

from darp.kinematics.rig import load_rig
from helpers.acquisition_fakes import INTRINSICS, Cylinder, FakeArm, FakeClock, render_depth


def test_analytic_depth_matches_open3d_ray_casting() -> None:
    o3d = pytest.importorskip("open3d")
    rig = load_rig()
    cyl = Cylinder(0.03, -0.02, 0.05, 0.1)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [-0.6, 0.0, -0.8], [0.8, 0.0, -0.6]]).T  # looks down 53 deg along +x
    T[:3, 3] = [-0.35, -0.02, 0.45]
    exact = render_depth(T, INTRINSICS, [cyl], rig)
    mesh = o3d.geometry.TriangleMesh.create_cylinder(cyl.radius_m, cyl.height_m, resolution=256, split=1)
    mesh.translate([cyl.x_m, cyl.y_m, cyl.height_m / 2])
    table = o3d.geometry.TriangleMesh.create_box(1.8, 0.9, 0.01)
    table.translate([-0.9, -0.45, -0.01])
    scene = o3d.t.geometry.RaycastingScene()
    for m in (mesh, table):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    v, u = np.mgrid[0:120, 0:160].astype(float)
    d_cam = np.stack([(u - INTRINSICS.ppx) / INTRINSICS.fx, (v - INTRINSICS.ppy) / INTRINSICS.fy, np.ones_like(u)], -1)
    d = d_cam @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], axis=-1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    both = (exact > 0) & np.isfinite(t_hit)
    assert np.mean((exact > 0) == np.isfinite(t_hit)) > 0.99  # the same pixels see a surface
    assert both.mean() > 0.5
    on_object = both & (np.abs(exact - t_hit) < 0.05) & (exact < np.percentile(exact[exact > 0], 30))
    assert on_object.sum() > 300
    assert np.median(np.abs(exact[both] - t_hit[both])) < 2e-4
    assert np.mean(np.abs(exact[both] - t_hit[both]) < 1e-3) > 0.97  # all but silhouette pixels agree


def test_fake_clock_runs_processes_in_time_order() -> None:
    clock = FakeClock(0.0)
    seen: list[tuple[str, float]] = []
    clock.every(0.5, lambda t: seen.append(("a", t)))
    clock.every(0.3, lambda t: seen.append(("b", t)))
    clock.sleep(1.0)
    times = [t for _, t in seen]
    assert times == sorted(times)
    assert [n for n, _ in seen].count("a") == 3 and [n for n, _ in seen].count("b") == 4
    assert clock.now() == pytest.approx(1.0)


def test_fake_arm_moves_linearly_and_reports_bias() -> None:
    clock = FakeClock(0.0)
    arm = FakeArm("arm110", clock, np.zeros(6), speed_rad_s=0.5, reported_bias_rad=np.r_[0.1, np.zeros(5)])
    arm.move_to(np.r_[1.0, np.zeros(5)])
    clock.sleep(1.0)
    assert arm.is_moving()
    np.testing.assert_allclose(arm.true_q()[0], 0.5)
    np.testing.assert_allclose(arm.read_state().q_rad[0], 0.6)
    clock.sleep(1.5)
    assert not arm.is_moving() and arm.true_q()[0] == pytest.approx(1.0)
