#!/usr/bin/env python3
"""Measured-surface fusion and point-to-mesh evaluation speed, next to their peers, in one run.

Scene: a cylinder (r 35 mm, h 100 mm) with a box beside it on a table, seen by 100 synthetic 640x480
D435-like depth keyframes (two arms, 50 orbit poses each at 0.35 m, Z16 with D4-like noise), rendered
exactly with Open3D's RaycastingScene before any timing.

1. Fusion keyframes/s: darp (back-projection + edge/incidence filters + envelope crop + voxel
   accumulation; the final support/outlier/fit step timed separately) against Open3D's
   ``t.geometry.VoxelBlockGrid`` TSDF integration (CPU) of the same keyframes at the same voxel size,
   once on the raw depth and once on depth masked to the envelope by ``darp.support_mask`` (mask time
   included: the same pixels darp keeps, the same crop work).
2. Memory: the accumulator's rows and the process's traced memory while the keyframes stream by
   three times (300 distinct frames): flat once the surface has been seen.
3. Point-to-mesh points/s: darp's MeshDistance (Open3D RaycastingScene, exact) on held-out points,
   against libigl's exact ``point_mesh_squared_distance`` (``pip install libigl``, the bench extra).
4. Accuracy of both fusions against the true surface (for context).

    .venv/bin/python benchmarks/fusion.py [--frames 100] [--voxel 0.0015]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Self

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # for the tests' helpers package

from darp.evaluation.point_to_mesh import MeshDistance, distance_stats
from darp.reconstruction.backproject import PosedDepth, backproject
from darp.reconstruction.crop import EnvelopeCrop, support_mask
from darp.reconstruction.fusion import FusionSettings, VoxelFusion
from darp.reconstruction.mesh import ball_pivoting_mesh, mesh_arrays
from helpers.synthetic_depth import D435_INTRINSICS, Scene, add_depth_noise, box, orbit_poses, table, to_z16
from results import Row, Target, row

FUSION_TARGET = Target("ratio", ">=", 2.0, "issue 7")  # fusion keyframes/s at least 2x Open3D's TSDF
POINT_TO_MESH_TARGET = Target("darp", ">=", 1.0, "issue 7")  # point-to-mesh at least 1 M points/s

CENTRE = np.array([0.01, 0.0, 0.05])


def make_object() -> o3d.geometry.TriangleMesh:
    cylinder = o3d.geometry.TriangleMesh.create_cylinder(0.035, 0.10, 160, 20)
    cylinder.translate((0.0, 0.0, 0.05))
    return cylinder + box((0.03, 0.03, 0.03), (0.03, -0.015, 0.0))


def render_keyframes(n_frames: int, seed: int = 0) -> tuple[list[PosedDepth], o3d.geometry.TriangleMesh]:
    obj = make_object()
    scene = Scene([obj, table()])
    per_arm = n_frames // 2
    elevations = (15, 35, 55, 75)
    n_az = int(np.ceil(per_arm / len(elevations)))
    rng = np.random.default_rng(seed)
    frames = []
    for arm, start in (("arm110", -90.0), ("arm111", 90.0)):
        poses = orbit_poses(CENTRE, 0.35, elevations, np.linspace(start, start + 180.0, n_az))[:per_arm]
        for i, T in enumerate(poses):
            depth, _ = scene.render(T, D435_INTRINSICS)
            frames.append(PosedDepth(arm, i, to_z16(add_depth_noise(depth, rng)), 0.001, D435_INTRINSICS, T))
    return frames, obj


class Clock:
    """Wall time and this process's CPU time (all threads) of a block: the machine may be shared."""

    def __enter__(self) -> Self:
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def time_darp(frames: list[PosedDepth], settings: FusionSettings, crop: EnvelopeCrop) -> tuple[Clock, Clock, object]:
    fusion = VoxelFusion(settings, crop)
    with Clock() as stream:
        for f in frames:
            fusion.add(f)
    with Clock() as final:
        result = fusion.result()
    return stream, final, result


def time_tsdf(frames: list[PosedDepth], voxel_m: float, crop: EnvelopeCrop | None) -> tuple[Clock, object]:
    """Integrate every frame; with ``crop``, depth outside darp's support mask is zeroed first (timed)."""
    device = o3d.core.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32), ((1,), (1,)),
                                        voxel_m, 16, 60_000, device)
    intr = o3d.core.Tensor(D435_INTRINSICS.K, o3d.core.float64)
    with Clock() as clock:
        for f in frames:
            depth = f.depth if crop is None else np.where(
                support_mask(f.depth, f.intrinsics, f.T_world_cam, crop, depth_scale=f.depth_scale), f.depth, 0)
            image = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(depth, np.uint16))).to(device)
            extrinsic = o3d.core.Tensor(np.linalg.inv(f.T_world_cam), o3d.core.float64)
            blocks = vbg.compute_unique_block_coordinates(image, intr, extrinsic, 1000.0, 1.0, 8.0)
            vbg.integrate(blocks, image, intr, extrinsic, 1000.0, 1.0, 8.0)
    return clock, vbg


def memory_run(frames: list[PosedDepth], settings: FusionSettings, crop: EnvelopeCrop, repeats: int = 3) -> None:
    fusion = VoxelFusion(settings, crop)
    tracemalloc.start()
    print("  frames  rows(state+pending)  traced MB (current / peak)")
    for r in range(repeats):
        for f in frames:
            fusion.add(PosedDepth(f.arm, f.frame_id + 10_000 * r, f.depth, f.depth_scale, f.intrinsics, f.T_world_cam))
        fusion._merge()  # report the merged state
        current, peak = tracemalloc.get_traced_memory()
        print(f"  {len(frames) * (r + 1):6d}  {fusion.rows:19,d}  {current / 1e6:8.1f} / {peak / 1e6:.1f}")
    tracemalloc.stop()


def measure(n_frames: int, voxel_m: float) -> dict[str, float | None]:
    """Print the four parts of the report; returns the figures the results table compares."""
    t0 = time.perf_counter()
    frames, obj = render_keyframes(n_frames)
    print(f"rendered {len(frames)} keyframes 640x480 in {time.perf_counter() - t0:.1f} s (not timed below)")
    settings = FusionSettings(voxel_size_m=voxel_m)
    crop = EnvelopeCrop(tuple(CENTRE), 0.06, 0.10, table_z_m=0.0, margin_m=settings.envelope_margin_m,
                        table_margin_m=settings.table_margin_m)

    time_darp(frames[:5], settings, crop)  # warm caches (rays, imports)
    stream, final, result = time_darp(frames, settings, crop)
    tsdf_raw, _ = time_tsdf(frames, voxel_m, None)
    tsdf_masked, vbg_masked = time_tsdf(frames, voxel_m, crop)
    n = len(frames)
    print(f"\n1. fusion at {voxel_m * 1000:.1f} mm voxels, {n} keyframes "
          f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores: wall rates suffer when it is high)")
    print(f"   {'':52s} {'keyframes/s':>11s} {'per CPU-s':>10s}")
    rows = [("darp stream (backproject+filters+crop+accumulate)", n / stream.wall, n / stream.cpu),
            ("darp incl. final support+SOR+fit", n / (stream.wall + final.wall), n / (stream.cpu + final.cpu)),
            ("Open3D VoxelBlockGrid TSDF (CPU), raw depth", n / tsdf_raw.wall, n / tsdf_raw.cpu),
            ("Open3D VoxelBlockGrid TSDF (CPU), masked by darp", n / tsdf_masked.wall, n / tsdf_masked.cpu)]
    for label, wall, cpu in rows:
        print(f"   {label:52s} {wall:11.1f} {cpu:10.1f}")
    for label, peer in (("raw depth", tsdf_raw), ("darp-masked depth", tsdf_masked)):
        print(f"   darp stream / TSDF on {label}: {peer.wall / stream.wall:.1f}x wall, "
              f"{peer.cpu / stream.cpu:.1f}x CPU; incl. final step {peer.wall / (stream.wall + final.wall):.1f}x wall")

    print(f"\n2. memory while streaming the keyframes three times ({3 * n} distinct frames)")
    memory_run(frames, settings, crop)

    fused = result.fused
    t0 = time.perf_counter()
    mesh = ball_pivoting_mesh(fused.points, fused.normals)
    t_mesh = time.perf_counter() - t0
    held = np.concatenate([backproject(f, settings.depth, crop).points for f in frames[::2]])
    md = MeshDistance.from_open3d(mesh)
    md.distances(held[:1000])  # build the BVH outside the timing
    with Clock() as query:
        d = md.distances(held)
    m = len(held) / 1e6
    figures: dict[str, float | None] = {
        "darp_kf_s": n / stream.wall, "darp_kf_cpu": n / stream.cpu, "tsdf_raw_kf_s": n / tsdf_raw.wall,
        "tsdf_raw_kf_cpu": n / tsdf_raw.cpu, "tsdf_masked_kf_s": n / tsdf_masked.wall,
        "darp_mpts_s": m / query.wall, "darp_mpts_cpu": m / query.cpu, "libigl_mpts_s": None}
    print(f"\n3. point-to-mesh on {len(held):,} held-out-style points, mesh {len(mesh.triangles):,} triangles "
          f"(ball pivoting took {t_mesh:.1f} s)")
    print(f"   darp MeshDistance (Open3D RaycastingScene): {m / query.wall:.2f} M points/s, "
          f"{m / query.cpu:.2f} M points per CPU-s")
    try:
        import igl  # the peer: libigl's AABB-tree point_mesh_squared_distance (exact, C++)
    except ImportError:
        print("   libigl is not installed (pip install libigl, the bench extra): no peer number")
    else:
        v64, t64 = mesh_arrays(mesh)
        with Clock() as peer:
            sq, _, _ = igl.point_mesh_squared_distance(held.astype(np.float64), v64, t64)
        agree = float(np.max(np.abs(d - np.sqrt(sq))))
        print(f"   libigl point_mesh_squared_distance:         {m / peer.wall:.2f} M points/s, "
              f"{m / peer.cpu:.2f} M points per CPU-s")
        print(f"   ratio darp/libigl {peer.wall / query.wall:.1f}x wall, {peer.cpu / query.cpu:.1f}x CPU; "
              f"max disagreement {agree * 1e6:.2f} um")
        figures["libigl_mpts_s"] = m / peer.wall
    print(f"   held-out median {np.median(d) * 1e3:.3f} mm, within 5 mm {100 * np.mean(d <= 0.005):.2f} %")

    truth_v, truth_t = mesh_arrays(obj)
    truth = MeshDistance(truth_v, truth_t)
    acc = distance_stats(truth.distances(fused.points))
    tsdf_pts = vbg_masked.extract_point_cloud().point.positions.numpy()
    acc_tsdf = distance_stats(truth.distances(tsdf_pts)) if len(tsdf_pts) else None
    print("\n4. accuracy against the true surface (context)")
    print(f"   darp fused cloud: {len(fused):,} pts, median {acc.median_m * 1e3:.3f} mm, "
          f"RMSE {acc.rmse_m * 1e3:.3f} mm, p90 {acc.p90_m * 1e3:.3f} mm")
    if acc_tsdf is not None:
        print(f"   TSDF (masked) surface points: {len(tsdf_pts):,} pts, median {acc_tsdf.median_m * 1e3:.3f} mm, "
              f"RMSE {acc_tsdf.rmse_m * 1e3:.3f} mm, p90 {acc_tsdf.p90_m * 1e3:.3f} mm")
    figures["darp_median_mm"] = acc.median_m * 1e3
    figures["tsdf_median_mm"] = acc_tsdf.median_m * 1e3 if acc_tsdf is not None else None
    return figures


def rows(frames: int = 60, voxel_m: float = 0.0015) -> list[Row]:
    """The results table's rows: fusion against Open3D's TSDF (raw and darp-masked depth), point-to-mesh
    against libigl, and both fusions' accuracy against the true surface."""
    f = measure(frames, voxel_m)
    scene = f"{frames} keyframes 640x480, {voxel_m * 1000:g} mm voxels"
    cpu = f"per CPU-s: darp {f['darp_kf_cpu']:.1f}, TSDF {f['tsdf_raw_kf_cpu']:.1f}"  # steadier on a shared machine
    return [row("fusion", f"fusion stream, {scene}", "keyframes/s", f["darp_kf_s"], f["tsdf_raw_kf_s"],
                "Open3D VoxelBlockGrid TSDF, raw depth", FUSION_TARGET, note=cpu),
            row("fusion", f"fusion stream, {scene}", "keyframes/s", f["darp_kf_s"], f["tsdf_masked_kf_s"],
                "Open3D TSDF, depth masked by darp"),
            row("fusion", "point-to-mesh, held-out points against the fused mesh", "M points/s", f["darp_mpts_s"],
                f["libigl_mpts_s"], "libigl point_mesh_squared_distance", POINT_TO_MESH_TARGET,
                note=f"darp {f['darp_mpts_cpu']:.2f} M points per CPU-s"),
            row("fusion", "fused surface against the true mesh, median", "mm", f["darp_median_mm"],
                f["tsdf_median_mm"], "Open3D TSDF (masked) surface points")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--voxel", type=float, default=0.0015)
    args = parser.parse_args()
    measure(args.frames, args.voxel)


if __name__ == "__main__":
    main()
