"""Fusion support counted over a voxel's neighbourhood (``support_neighbourhood``) and per-arm clouds that keep
what the fused cloud supports (``arm_support_from_fused``): scattered measurements of a real surface are kept,
isolated ghosts are still rejected, and per-arm clouds gain the co-observed band."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from darp.errors import ReconstructionError
from darp.reconstruction.backproject import FrameCloud, PosedDepth
from darp.reconstruction.crop import EnvelopeCrop
from darp.reconstruction.fusion import FusionSettings, VoxelFusion, neighbourhood_support, supported_voxels
from darp.reconstruction.voxel_stats import VoxelStats, pack_keys, popcount64
from helpers.synthetic_depth import Scene, orbit_poses, small_intrinsics, sphere, table


def stats_of(voxels: dict[tuple[int, int, int], tuple[int, list[int]]]) -> VoxelStats:
    """Voxel statistics with the given (frames, view bins) per voxel, sorted by key."""
    ijk = np.array(list(voxels), np.int64)
    keys = pack_keys(ijk)
    order = np.argsort(keys)
    frames = np.array([voxels[k][0] for k in voxels], np.int32)[order]
    masks = np.array([sum(1 << b for b in voxels[k][1]) for k in voxels], np.uint64)[order]
    m = len(voxels)
    return VoxelStats(keys[order], np.ones(m, np.int64), np.zeros((m, 3)), np.zeros((m, 3)), None, frames, masks,
                      np.ones(m, np.uint8))


def test_neighbourhood_support_is_an_exact_lower_bound() -> None:
    rng = np.random.default_rng(3)
    voxels = {tuple(int(v) for v in rng.integers(0, 6, 3)): (int(rng.integers(1, 5)), [int(rng.integers(0, 64))])
              for _ in range(120)}
    stats = stats_of(voxels)
    for radius in (0, 1, 2):
        frames, bins = neighbourhood_support(stats, radius)
        for n, key in enumerate(voxels_sorted := sorted(voxels, key=lambda k: int(pack_keys(np.array([k]))[0]))):
            near = [voxels[(key[0] + i, key[1] + j, key[2] + k)]
                    for i, j, k in itertools.product(range(-radius, radius + 1), repeat=3)
                    if (key[0] + i, key[1] + j, key[2] + k) in voxels]
            assert frames[n] == max(f for f, _ in near)
            assert int(bins[n]) == sum({1 << b for _, bs in near for b in bs})
        assert len(voxels_sorted) == len(stats)


def test_scattered_surface_is_kept_and_isolated_ghosts_are_not() -> None:
    voxels = {
        (0, 0, 0): (3, [1, 2]),  # well supported
        (1, 0, 0): (1, [1]),  # the same surface, one frame landed in the next voxel (noise, pixel footprint)
        (2, 0, 0): (1, [2]),  # two voxels away from the supported one
        (9, 9, 9): (2, [5]),  # a ghost: two frames, one direction, nothing around it
        (9, 9, 11): (1, [6]),
    }
    stats = stats_of(voxels)
    keys = {k: int(np.flatnonzero(stats.keys == pack_keys(np.array([k])))[0]) for k in voxels}

    def kept(**kw: int) -> set[tuple[int, int, int]]:
        mask = supported_voxels(stats, FusionSettings(adaptive_support=False, **kw))
        return {k for k, i in keys.items() if mask[i]}

    assert kept() == {(0, 0, 0)}
    assert kept(support_neighbourhood=1) == {(0, 0, 0), (1, 0, 0)}
    assert kept(support_neighbourhood=2) == {(0, 0, 0), (1, 0, 0), (2, 0, 0)}
    # the ghost pair: 3 frames' worth within 2 voxels but the most any of them saw is 2, and one bin each
    assert (9, 9, 9) not in kept(support_neighbourhood=2, min_frames=3)
    with pytest.raises(ReconstructionError):
        FusionSettings(support_neighbourhood=3)
    with pytest.raises(ReconstructionError):
        FusionSettings(arm_support_from_fused=-1)


def test_tangent_plane_neighbourhood_lends_support_along_the_surface_not_to_the_noise_layer() -> None:
    """A surface in z = 0 (normals +z): a neighbour beside the supported voxel borrows its support, the voxel
    above it (where noise along the normal lands) borrows it only from the whole cube; a voxel without a
    normal keeps its own support."""
    voxels = {
        (0, 0, 0): (3, [1, 2]),  # the supported surface voxel
        (1, 0, 0): (1, [1]),  # beside it, in the surface plane
        (0, 0, 1): (1, [2]),  # above it: the noise layer
        (1, 1, 1): (1, [2]),  # diagonal, one voxel off the plane
    }
    stats = stats_of(voxels)
    normals = np.zeros((len(stats), 3))
    normals[:, 2] = 1.0
    no_normal = int(np.flatnonzero(stats.keys == pack_keys(np.array([(1, 1, 1)])))[0])
    normals[no_normal] = 0.0
    stats = dataclasses.replace(stats, sum_normal=normals)
    keys = {k: int(np.flatnonzero(stats.keys == pack_keys(np.array([k])))[0]) for k in voxels}

    def kept(**kw: float) -> set[tuple[int, int, int]]:
        mask = supported_voxels(stats, FusionSettings(adaptive_support=False, support_neighbourhood=1, **kw))
        return {k for k, i in keys.items() if mask[i]}

    assert kept() == {(0, 0, 0), (1, 0, 0), (0, 0, 1), (1, 1, 1)}
    assert kept(neighbourhood_plane_voxels=0.5) == {(0, 0, 0), (1, 0, 0)}
    frames, _ = neighbourhood_support(stats, 1, plane_voxels=0.5)
    assert frames[keys[(0, 0, 1)]] == 1 and frames[keys[(1, 0, 0)]] == 3 and frames[keys[(1, 1, 1)]] == 1
    # a tilted surface: normal (1, 0, 1)/sqrt(2); (1, 0, -1) lies in its plane, (1, 0, 0) is 0.71 voxel off it
    tilted = dataclasses.replace(stats, sum_normal=np.tile([1.0, 0.0, 1.0], (len(stats), 1)))
    frames, _ = neighbourhood_support(tilted, 1, plane_voxels=0.5)
    assert frames[keys[(1, 0, 0)]] == 1
    with pytest.raises(ReconstructionError):
        FusionSettings(neighbourhood_plane_voxels=-1.0)


def test_holes_only_neighbourhood_fills_a_hole_but_not_a_second_layer() -> None:
    """A surface row in z = 0 (normals +z) with a thin voxel at x = 2 (a hole in the support) and, above its
    start, a second copy of the surface one voxel up (another view, offset by pose error): the cube lends
    support to both; ``neighbourhood_holes_only`` keeps the hole and drops the second layer."""
    voxels = {(x, 0, 0): (3, [1, 2]) for x in (0, 1, 3, 4)}
    voxels[(2, 0, 0)] = (1, [1])
    voxels[(0, 0, 1)] = (1, [2])
    voxels[(1, 0, 1)] = (2, [2])
    stats = stats_of(voxels)
    stats = dataclasses.replace(stats, sum_normal=np.tile([0.0, 0.0, 1.0], (len(stats), 1)))
    keys = {k: int(np.flatnonzero(stats.keys == pack_keys(np.array([k])))[0]) for k in voxels}

    def kept(**kw: float) -> set[tuple[int, int, int]]:
        mask = supported_voxels(stats, FusionSettings(adaptive_support=False, support_neighbourhood=1, **kw))
        return {k for k, i in keys.items() if mask[i]}

    surface = {(x, 0, 0) for x in range(5)}
    assert kept() == surface | {(0, 0, 1), (1, 0, 1)}
    counts: dict[str, int] = {}
    mask = supported_voxels(stats, FusionSettings(adaptive_support=False, support_neighbourhood=1,
                                                  neighbourhood_holes_only=2), counts=counts)
    assert {k for k, i in keys.items() if mask[i]} == surface
    assert counts["second_layer"] == 2
    with pytest.raises(ReconstructionError):
        FusionSettings(neighbourhood_holes_only=4)


def test_cell_support_counts_distinct_frames_whose_hits_scattered_over_a_cell() -> None:
    """Four frames hit one 2x2x2 cell, each only one of two voxels in it (hits scattered by noise and a pixel
    footprint the voxel's size): no voxel has 3 frames, the cell has 4, so both voxels are kept with
    ``support_cell_voxels: 2``; a cell only 2 frames hit stays out; counts are distinct frames, not hits."""
    from darp.reconstruction.voxel_stats import cell_stats, frame_stats, merge_stats

    voxel = 0.0015
    a, b = np.array([[0.25, 0.25, 0.25]]) * voxel, np.array([[1.25, 0.25, 0.25]]) * voxel  # one cell, two voxels
    ghost = np.array([[20.25, 20.25, 20.25]]) * voxel
    up = np.array([[0.0, 0.0, 1.0]])
    frames = []
    for pts, cam in [(a, (0.3, 0, 0.3)), (a, (-0.3, 0, 0.3)), (np.vstack([b, b]), (0, 0.3, 0.3)),
                     (b, (0, -0.3, 0.3)), (ghost, (0.3, 0, 0.3)), (ghost, (0.3, 0.01, 0.3))]:
        frames.append(frame_stats(pts, np.repeat(up, len(pts), axis=0), None, np.array(cam), voxel, 0))
    stats = merge_stats(frames)
    cells = merge_stats([cell_stats(f, 2) for f in frames])
    assert sorted(cells.n_frames.tolist()) == [2, 4]  # the scattered cell: 4 distinct frames (5 hits)
    settings = FusionSettings(adaptive_support=False, support_cell_voxels=2)
    assert not supported_voxels(stats, settings).any()  # without the cells: 2 frames at most per voxel
    kept = supported_voxels(stats, settings, cells=cells)
    assert kept.sum() == 2 and not kept[np.argmax(stats.keys)]  # the two voxels of the cell, not the ghost
    with pytest.raises(ReconstructionError):
        FusionSettings(support_cell_voxels=0)


R = 0.04
CENTRE = np.array([0.0, 0.0, R])
INTR = small_intrinsics(160, 120, 190.0)
CROP = EnvelopeCrop(tuple(CENTRE), R, 2 * R, table_z_m=0.0)


@pytest.fixture(scope="module")
def frames() -> list[PosedDepth]:
    """A sphere seen by each arm from one ring of 3 views on its own side, noisy depth (1 mm)."""
    scene = Scene([sphere(R, CENTRE, 150), table()])
    rng = np.random.default_rng(0)
    out = []
    for arm, azimuths in (("arm110", (-50, 0, 50)), ("arm111", (130, 180, 230))):
        for i, T in enumerate(orbit_poses(CENTRE, 0.3, [35], azimuths)):
            depth, _ = scene.render(T, INTR)
            noisy = np.where(depth > 0, depth + rng.normal(0.0, 0.001, depth.shape), 0.0).astype(np.float32)
            out.append(PosedDepth(arm, i, noisy, 1.0, INTR, T))
    return out


def fuse_with(frames: list[PosedDepth], ghost_clouds: list[tuple[str, FrameCloud]] = (), **kw: int) -> object:
    fusion = VoxelFusion(FusionSettings(voxel_size_m=0.0015, **kw), CROP)
    for f in frames:
        fusion.add(f)
    for k, (arm, cloud) in enumerate(ghost_clouds):
        fusion.add_cloud(arm, 1000 + k, cloud)
    return fusion.result()


def test_noisy_sparse_views_keep_more_surface_without_losing_accuracy(frames: list[PosedDepth]) -> None:
    base = fuse_with(frames)
    wide = fuse_with(frames, support_neighbourhood=1)
    assert len(wide.fused) > 1.2 * len(base.fused)  # noise scatters each frame's hits over neighbouring voxels
    err_base = np.abs(np.linalg.norm(base.fused.points - CENTRE, axis=1) - R)
    err_wide = np.abs(np.linalg.norm(wide.fused.points - CENTRE, axis=1) - R)
    assert np.percentile(err_wide, 90) < 1.5 * np.percentile(err_base, 90) + 2e-4
    # what was kept before is kept now (the surface fit moves points, so within a voxel)
    from scipy.spatial import cKDTree

    assert np.mean(cKDTree(wide.fused.points).query(base.fused.points, k=1)[0] < 0.0015) > 0.98


def test_per_arm_clouds_keep_the_band_the_fused_cloud_supports(frames: list[PosedDepth]) -> None:
    ghost = np.array([0.03, 0.03, 0.076])  # in the air inside the envelope
    cam = frames[0].T_world_cam[:3, 3]
    normal = (cam - ghost) / np.linalg.norm(cam - ghost)
    cloud = FrameCloud(np.repeat(ghost[None], 4, 0).astype(np.float32),
                       np.repeat(normal[None], 4, 0).astype(np.float32), None, np.arange(4), cam)
    own = fuse_with(frames, [("arm110", cloud)])
    shared = fuse_with(frames, [("arm110", cloud)], arm_support_from_fused=1)

    def co_observed(result: object) -> int:
        from scipy.spatial import cKDTree

        a, b = result.per_arm["arm110"], result.per_arm["arm111"]  # type: ignore[attr-defined]
        return int(np.sum(cKDTree(b.points).query(a.points, k=1)[0] < 0.002))

    assert co_observed(shared) >= co_observed(own) + 10
    assert shared.stats["arm110"]["from_fused"] > 0
    for arm in ("arm110", "arm111"):  # an arm's cloud only gains voxels its own frames measured
        assert len(shared.per_arm[arm]) >= len(own.per_arm[arm])
    np.testing.assert_array_equal(shared.fused.points, own.fused.points)  # the fused cloud is unchanged
    for result in (own, shared):  # the single-frame ghost is in no cloud
        for c in (result.fused, result.per_arm["arm110"]):
            assert not np.any(np.linalg.norm(c.points - ghost, axis=1) < 0.003)
    assert dataclasses.asdict(shared.settings)["arm_support_from_fused"] == 1
    assert popcount64(np.array([3], np.uint64))[0] == 2


def test_neighbourhood_support_only_for_voxels_seen_by_enough_frames_themselves() -> None:
    # a well-supported voxel (4 frames, 2 bins), beside it one that 2 frames hit and one that 1 frame hit
    stats = stats_of({(0, 0, 0): (4, [0, 1]), (1, 0, 0): (2, [0]), (0, 1, 0): (1, [1])})
    order = {k: n for n, k in enumerate(sorted([(0, 0, 0), (1, 0, 0), (0, 1, 0)],
                                               key=lambda k: int(pack_keys(np.array([k]))[0])))}
    every = supported_voxels(stats, FusionSettings(support_neighbourhood=1, adaptive_support=False))
    own2 = supported_voxels(stats, FusionSettings(support_neighbourhood=1, neighbourhood_own_frames=2,
                                                  adaptive_support=False))
    assert every.all()  # the neighbourhood lends its support to both
    assert own2[order[(0, 0, 0)]] and own2[order[(1, 0, 0)]]
    assert not own2[order[(0, 1, 0)]]  # a voxel one frame hit keeps its own count
    with pytest.raises(ReconstructionError, match="neighbourhood_own_frames"):
        FusionSettings(neighbourhood_own_frames=0)
