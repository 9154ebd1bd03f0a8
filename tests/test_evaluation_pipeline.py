"""The measured-surface chain end to end on noisy synthetic keyframes of two arms: fusion, meshing,
held-out, cross-arm and ground-truth metrics must meet the twin's accuracy targets."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from darp.evaluation.cross_arm import cross_arm_consistency
from darp.evaluation.heldout import evaluate_heldout, heldout_mask
from darp.evaluation.point_to_mesh import MeshDistance
from darp.evaluation.truth_metrics import sample_surface, truth_metrics, visible_in_frames
from darp.reconstruction.backproject import PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.fusion import FusionSettings, fuse
from darp.reconstruction.mesh import ball_pivoting_mesh, boundary_edges, mesh_arrays
from helpers.synthetic_depth import Scene, add_depth_noise, box, orbit_poses, small_intrinsics, table, to_z16

INTR = small_intrinsics(320, 240, 380.0)  # the D435's pixel footprint, a smaller field of view
CENTRE = (0.01, 0.0, 0.04)


@pytest.fixture(scope="module")
def chain():
    cylinder = o3d.geometry.TriangleMesh.create_cylinder(0.03, 0.08, 100, 16)
    cylinder.translate((0.0, 0.0, 0.04))
    obj = cylinder + box((0.025, 0.025, 0.025), (0.025, -0.0125, 0.0))
    scene = Scene([obj, table()])
    rng = np.random.default_rng(7)
    fused_frames, held = [], []
    for arm, start in (("arm110", -80.0), ("arm111", 100.0)):
        poses = orbit_poses(CENTRE, 0.33, (20, 45, 70), np.linspace(start, start + 160.0, 8))
        is_held = heldout_mask(len(poses), every=6, offset=3)
        for i, T in enumerate(poses):
            depth = to_z16(add_depth_noise(scene.render(T, INTR)[0], rng, fx=INTR.fx))
            (held if is_held[i] else fused_frames).append(PosedDepth(arm, i, depth, 0.001, INTR, T))
    crop = EnvelopeCrop(CENTRE, 0.05, 0.08, table_z_m=0.0)
    result = fuse(fused_frames, FusionSettings(), crop)
    mesh = ball_pivoting_mesh(result.fused.points, result.fused.normals)
    return obj, crop, fused_frames, held, result, mesh


def test_fused_cloud_and_mesh_meet_the_accuracy_targets(chain) -> None:
    obj, _, fused_frames, _, result, mesh = chain
    v, t = mesh_arrays(obj)
    samples, normals = sample_surface(v, t, np.random.default_rng(0), spacing_m=0.001)
    seen = visible_in_frames(samples, fused_frames, normals=normals)
    m = truth_metrics(result.fused.points, v, t, samples, seen, mesh=mesh_arrays(mesh))
    assert m.cloud.accuracy.median_m < 0.0005
    assert m.cloud.accuracy.within_pct[0.002] > 99.0
    assert m.cloud.completeness_pct(0.005) > 97.0
    assert m.mesh.accuracy.median_m < 0.0005
    assert len(boundary_edges(np.asarray(mesh.triangles))) < 0.05 * len(mesh.triangles)  # few holes


def test_heldout_and_cross_arm_agree(chain) -> None:
    _, crop, _, held, result, mesh = chain
    heldout = evaluate_heldout(held, MeshDistance.from_open3d(mesh), object_name="cylinder+box", region=crop)
    stats = heldout.stats()
    assert heldout.n_frames == len(held) and stats.count > 10_000
    assert stats.median_m < 0.001 and stats.rmse_m < 0.002 and stats.within_pct[0.01] > 99.0
    a, b = result.per_arm["arm110"], result.per_arm["arm111"]
    cross = cross_arm_consistency(a.points, b.points, normals_a=a.normals, normals_b=b.normals)
    for direction in (cross.a_to_b, cross.b_to_a):
        assert direction.n_co_observed > 500
        assert direction.point_to_plane.median_m < 0.0005  # exact poses: the arms agree
