"""Voxel fusion: exact reconstruction of a sphere, voxel and view support, per-arm clouds, streaming,
determinism, outlier removal (Open3D as oracle) and the surface fit."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from darp.errors import ReconstructionError
from darp.reconstruction.backproject import FrameCloud, PosedDepth
from darp.reconstruction.cloud_io import read_ply
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.fusion import (
    FusionSettings,
    VoxelFusion,
    fit_to_local_surface,
    fuse,
    statistical_outliers,
    write_voxel_cloud,
)
from darp.reconstruction.voxel_stats import (
    VIEW_DIRECTIONS,
    fibonacci_directions,
    frame_stats,
    merge_stats,
    pack_keys,
    popcount64,
    unpack_keys,
    view_bins,
)
from helpers.synthetic_depth import Scene, orbit_poses, small_intrinsics, sphere, table

R = 0.04
CENTRE = np.array([0.0, 0.0, R])
INTR = small_intrinsics(160, 120, 190.0)
CROP = EnvelopeCrop(tuple(CENTRE), R, 2 * R, table_z_m=0.0)
SETTINGS = FusionSettings(voxel_size_m=0.002)


def render_frames() -> list[PosedDepth]:
    scene = Scene([sphere(R, CENTRE, 150), table()])
    frames = []
    for arm, azimuths in (("arm110", range(-60, 61, 30)), ("arm111", range(120, 241, 30))):
        for i, T in enumerate(orbit_poses(CENTRE, 0.3, [25, 55], azimuths)):
            depth, _ = scene.render(T, INTR)
            frames.append(PosedDepth(arm, i, depth, 1.0, INTR, T))  # exact metric depth
    return frames


@pytest.fixture(scope="module")
def frames() -> list[PosedDepth]:
    return render_frames()


@pytest.fixture(scope="module")
def result(frames: list[PosedDepth]):
    return fuse(frames, SETTINGS, CROP)


def radial_error(points: np.ndarray) -> np.ndarray:
    return np.abs(np.linalg.norm(points - CENTRE, axis=1) - R)


def test_noiseless_views_reproduce_the_sphere(result) -> None:
    fused = result.fused
    assert len(fused) > 1500
    assert radial_error(fused.points).max() < SETTINGS.voxel_size_m / 2
    assert np.median(radial_error(fused.points)) < 1e-4
    outward = (fused.points - CENTRE) / np.linalg.norm(fused.points - CENTRE, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", fused.normals, outward) > 0.9)  # normals face the cameras
    assert np.all(fused.n_frames >= SETTINGS.min_frames) and np.all(fused.n_views >= SETTINGS.min_view_bins)
    assert fused.points[:, 2].min() >= CROP.z_range_m[0] - 1e-6


def test_per_arm_clouds_cover_their_own_sides(result) -> None:
    a, b = result.per_arm["arm110"], result.per_arm["arm111"]
    # arm110 looked from +x (azimuths -60..60 deg), arm111 from -x; views at +-60 deg legitimately see up to
    # 150 deg round, and visibility-adapted support keeps those grazing voxels (0.90 of arm110's points on +x)
    assert np.mean(a.points[:, 0] > CENTRE[0]) > 0.85
    assert np.mean(b.points[:, 0] < CENTRE[0]) > 0.85
    both = result.fused.seen_by("arm110") & result.fused.seen_by("arm111")
    assert 0 < both.sum() < 0.5 * len(result.fused)  # a co-observed band around the top
    assert result.fused.arms == ("arm110", "arm111")
    assert len(result.fused) > max(len(a), len(b))
    assert result.stats["fused"]["frames"] == 20


def test_streaming_merges_and_determinism(frames: list[PosedDepth], result) -> None:
    again = fuse(frames, SETTINGS, CROP)
    np.testing.assert_array_equal(again.fused.points, result.fused.points)
    tiny_batches = fuse(frames, FusionSettings(voxel_size_m=0.002, merge_rows=500), CROP)
    np.testing.assert_array_equal(tiny_batches.fused.voxel_ijk, result.fused.voxel_ijk)
    np.testing.assert_allclose(tiny_batches.fused.points, result.fused.points, atol=1e-7)


def test_memory_stays_bounded_for_repeated_views(frames: list[PosedDepth]) -> None:
    fusion = VoxelFusion(FusionSettings(voxel_size_m=0.002, merge_rows=5000), CROP)
    rows = []
    for repeat in range(4):
        for f in frames[:10]:
            fusion.add(PosedDepth(f.arm, f.frame_id + 100 * repeat, f.depth, f.depth_scale, f.intrinsics,
                                  f.T_world_cam))
        fusion._merge()  # measure the merged state
        rows.append(fusion.rows)
    assert rows[-1] == rows[0], "the state grew although the same surface was seen again"
    assert fusion.peak_rows < rows[0] + 5000 + 3000


def spurious_cloud(point: np.ndarray, camera: np.ndarray, n: int = 4) -> FrameCloud:
    pts = np.repeat(point[None, :], n, axis=0).astype(np.float32)
    normal = (camera - point) / np.linalg.norm(camera - point)
    return FrameCloud(pts, np.repeat(normal[None, :], n, 0).astype(np.float32), None,
                      np.arange(n), camera.astype(np.float64))


def test_voxel_and_view_support_reject_weak_measurements(frames: list[PosedDepth]) -> None:
    ghost = np.array([0.035, 0.035, 0.075])  # inside the envelope, in the air 2 cm from the sphere
    cam = frames[0].T_world_cam[:3, 3]

    def fused_with(clouds: list[FrameCloud], **overrides) -> np.ndarray:
        fusion = VoxelFusion(FusionSettings(voxel_size_m=0.002, sor_neighbours=0, **overrides), CROP)
        for f in frames:
            fusion.add(f)
        for k, cloud in enumerate(clouds):
            fusion.add_cloud("arm110", 1000 + k, cloud)
        return fusion.result().fused.points

    def has_ghost(points: np.ndarray) -> bool:
        return bool(np.any(np.linalg.norm(points - ghost, axis=1) < 0.002))

    assert not has_ghost(fused_with([spurious_cloud(ghost, cam)]))  # one frame only
    same_view = [spurious_cloud(ghost, cam) for _ in range(4)]
    assert not has_ghost(fused_with(same_view))  # four frames, one viewing direction
    assert has_ghost(fused_with(same_view, min_view_bins=1))
    other_side = frames[-1].T_world_cam[:3, 3]
    two_views = same_view[:2] + [spurious_cloud(ghost, other_side) for _ in range(2)]
    assert has_ghost(fused_with(two_views))  # supported, so only the outlier removal could drop it


def test_statistical_outlier_removal_matches_open3d() -> None:
    rng = np.random.default_rng(3)
    pts = np.vstack([rng.normal(size=(2000, 3)) * 0.01, rng.uniform(-0.2, 0.2, size=(30, 3))])
    ours = statistical_outliers(pts, 20, 2.0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, kept = cloud.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    expected = np.zeros(len(pts), bool)
    expected[np.asarray(kept)] = True
    assert np.count_nonzero(ours != expected) <= 2  # ties at the threshold aside
    assert not ours[2000:].any()  # the scattered points go


def test_surface_fit_flattens_a_noisy_plane() -> None:
    rng = np.random.default_rng(0)
    xy = np.stack(np.meshgrid(np.arange(40), np.arange(40)), -1).reshape(-1, 2) * 0.0015
    pts = np.column_stack([xy, rng.normal(size=len(xy)) * 0.0004]).astype(np.float32)
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1)).astype(np.float32)
    fitted = fit_to_local_surface(pts, normals, np.ones(len(pts)), 0.003, 16)
    assert np.std(fitted[:, 2]) < 0.4 * np.std(pts[:, 2])
    np.testing.assert_array_equal(fitted[:, :2], pts[:, :2])  # points only move along their normals


def test_voxel_keys_masks_and_merges() -> None:
    ijk = np.array([[0, 0, 0], [-1, 5, -7], [1000, -1000, 3]], np.int64)
    np.testing.assert_array_equal(unpack_keys(pack_keys(ijk)), ijk)
    with pytest.raises(ReconstructionError, match="too far"):
        pack_keys(np.array([[1 << 21, 0, 0]]))
    masks = np.array([0, 1, 0xFFFF_FFFF_FFFF_FFFF, 0b1011], np.uint64)
    np.testing.assert_array_equal(popcount64(masks), [0, 1, 64, 3])
    dirs = fibonacci_directions()
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(view_bins(3.0 * VIEW_DIRECTIONS), np.arange(64))  # any length
    random_dirs = np.random.default_rng(0).normal(size=(20000, 3))
    exact = np.argmax(random_dirs @ VIEW_DIRECTIONS.T, axis=1)
    assert np.mean(view_bins(random_dirs) == exact) > 0.95  # the table errs only at bin borders
    pts = np.array([[0.0005, 0.0005, 0.0005], [0.0015, 0.0005, 0.0005]], np.float32)
    nrm = np.tile([0.0, 0.0, 1.0], (2, 1)).astype(np.float32)
    s1 = frame_stats(pts, nrm, None, np.array([0.0, 0.0, 1.0]), 0.001, 0)
    s2 = frame_stats(pts[:1], nrm[:1], None, np.array([1.0, 0.0, 0.0]), 0.001, 1)
    merged = merge_stats([s1, s2])
    assert len(merged) == 2
    first = np.flatnonzero(merged.keys == s2.keys[0])[0]
    assert merged.n_frames[first] == 2 and merged.n_points[first] == 2
    assert popcount64(merged.view_mask[first:first + 1])[0] == 2 and merged.arm_mask[first] == 0b11


def test_errors_and_ply_output(tmp_path, result, frames: list[PosedDepth]) -> None:
    fusion = VoxelFusion(SETTINGS, CROP)
    fusion.add(frames[0])
    with pytest.raises(ReconstructionError, match="already fused"):
        fusion.add(frames[0])
    far = EnvelopeCrop((5.0, 5.0, 0.1), 0.05, 0.1, 0.0)
    with pytest.raises(ReconstructionError, match="nothing to fuse"):
        fuse(frames[:2], SETTINGS, far)
    with pytest.raises(ReconstructionError, match="voxel_size_m"):
        FusionSettings(voxel_size_m=0.0)
    path = write_voxel_cloud(tmp_path / "fused.ply", result.fused)
    ply = read_ply(path)
    np.testing.assert_allclose(ply.points, result.fused.points, atol=1e-7)
    np.testing.assert_array_equal(ply.vertex["n_frames"], result.fused.n_frames)
    np.testing.assert_array_equal(ply.vertex["arm_mask"], result.fused.arm_mask)
    assert "arms arm110 arm111" in ply.comments
