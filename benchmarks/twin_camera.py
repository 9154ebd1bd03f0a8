#!/usr/bin/env python3
"""Time per stage of the twin's D435 camera at 640x480, next to its peers and the 30 fps budget.

Scene: a table with a box, a sphere, a dark cylinder and a ChArUco board, seen from 0.45 m. Stages:
colour render, left render (light + exact depth), segmentation, right render, D4 noise model, IR pair,
SGBM; then whole captures (ideal, realistic, the rig's settings with and without dropout geoms, ...)
with the real-time factor of a two-camera rig at 30 fps (wall, and CPU-bound on 2 free cores), and the
CPU split by stage. Peers: MuJoCo's CPU ray caster (mj_multiRay) for exact depth, the facts'
reference timings (MuJoCo RGB 5-9 ms, depth 4-7 ms; numpy D4 model 17 ms; SGBM 26 ms), and the
33.3 ms frame period.

Single-threaded by default (llvmpipe and OpenCV), as in a camera worker on a 2-core machine, so that
CPU and wall times agree and each stage's CPU is its own; ``--threads 2`` measures the threaded mode.

    .venv/bin/python benchmarks/twin_camera.py [--repeats 30] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np

from darp.formats.calibration import CharucoBoardSpec
from darp.twin.camera.depth_model import DepthModel, DepthNoiseSettings
from darp.twin.camera.ir import IrModel, IrSettings
from darp.twin.camera.render import SceneRenderer, geom_image_region, mujoco
from darp.twin.camera.sensor import TwinCamera, TwinCameraSettings
from darp.twin.camera.spec import make_camera_spec
from darp.twin.camera.stereo import StereoMatcher, StereoSettings
from darp.twin.objects.board import add_charuco_board
from results import Row, row

FRAME_BUDGET_MS = 1000.0 / 30.0


def build_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = mujoco.MjSpec()
    spec.worldbody.add_light(pos=[0.3, 0.2, 1.5], dir=[0, 0, -1], diffuse=[0.6, 0.6, 0.6], castshadow=False)
    geom = mujoco.mjtGeom
    spec.worldbody.add_geom(
        type=geom.mjGEOM_BOX, size=[0.6, 0.4, 0.01], pos=[0, 0, -0.01], rgba=[0.6, 0.5, 0.4, 1]
    )
    spec.worldbody.add_geom(
        type=geom.mjGEOM_BOX, size=[0.05] * 3, pos=[0.1, 0.1, 0.05], rgba=[0.2, 0.6, 0.9, 1]
    )
    spec.worldbody.add_geom(
        type=geom.mjGEOM_SPHERE, size=[0.04, 0, 0], pos=[-0.1, 0.05, 0.04], rgba=[0.9, 0.2, 0.2, 1]
    )
    spec.worldbody.add_geom(
        name="dark_cylinder",
        type=geom.mjGEOM_CYLINDER,
        size=[0.03, 0.06, 0],
        pos=[0, -0.12, 0.06],
        rgba=[0.1, 0.1, 0.1, 1],
    )
    T_board = np.diag([1.0, -1.0, -1.0, 1.0])
    T_board[:3, 3] = [-0.2, -0.05, 0.001]
    board = CharucoBoardSpec(squares_x=7, squares_y=5, square_length_m=0.03, marker_length_m=0.022,
                             dictionary="DICT_5X5_100")
    add_charuco_board(spec, board, T_parent_board=T_board)  # default texture: 128 px per square, 32 px margin
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def camera_pose(distance_m: float = 0.45) -> np.ndarray:
    c, s = np.cos(np.deg2rad(200)), np.sin(np.deg2rad(200))
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    T[:3, 3] = -T[:3, 2] * distance_m
    return T


def timed_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """Median wall time, its 10th percentile, and median CPU time (all threads) of ``fn``, in ms.

    On a shared machine the wall time grows with other processes' load; the 10th percentile and the
    CPU time show the speed when the cores are free (CPU time counts llvmpipe's render threads too).
    """
    for _ in range(3):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.percentile(wall, 10)), 1e3 * float(np.median(cpu))


def measure(n: int, threads: int) -> dict[str, tuple[float, str, float]]:
    """Print the stage and whole-camera tables (``n`` repeats each); returns darp's median ms, the peer's name and
    the peer's ms of every line that has a peer."""
    os.environ.setdefault("LP_NUM_THREADS", "0" if threads <= 1 else str(threads))  # before any GL
    cv2.setNumThreads(0 if threads <= 1 else threads)
    compared: dict[str, tuple[float, str, float]] = {}

    model, data = build_scene()
    spec = make_camera_spec()
    T = camera_pose()
    T_color = T @ spec.T_depth_stream("color")
    T_right = T @ spec.T_depth_stream("ir2")
    renderer = SceneRenderer(model, 640, 480)
    renderer.update_scene(data)
    dark = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "dark_cylinder")]
    left = renderer.render_view(T, spec.depth)
    right = renderer.render_view(T_right, spec.depth)
    depth_model = DepthModel(DepthNoiseSettings.realistic(), spec.depth.fx, spec.baseline_m, bank_seed=0)
    ir_model = IrModel(IrSettings(), spec.depth, spec.baseline_m, spec.projector_x_m, seed=0)
    rng = np.random.default_rng(0)
    ir1, ir2 = ir_model.pair(left.rgb, left.depth_m, right.rgb, right.depth_m, rng)
    sgbm = StereoMatcher(StereoSettings(), spec.depth.fx, spec.baseline_m)
    sgbm96 = StereoMatcher(StereoSettings(num_disparities=96), spec.depth.fx, spec.baseline_m)

    # Peer for exact depth: MuJoCo's CPU ray caster, one ray per pixel.
    v, u = np.mgrid[0:480, 0:640]
    rays = (
        np.stack(
            [(u - spec.depth.ppx) / spec.depth.fx, (v - spec.depth.ppy) / spec.depth.fy, np.ones(u.shape)], -1
        ).reshape(-1, 3)
        @ T[:3, :3].T
    )
    rays_flat = rays.reshape(-1).copy()
    dist, geom = np.zeros(rays.shape[0]), np.zeros(rays.shape[0], np.int32)

    def ray_cast() -> None:
        mujoco.mj_multiRay(
            model, data, T[:3, 3].copy(), rays_flat, None, 1, -1, geom, dist, None, rays.shape[0], 100.0
        )

    stages = [
        ("update scene", lambda: renderer.update_scene(data), "", None),
        (
            "render colour (colour imager)",
            lambda: renderer.render_view(T_color, spec.color, depth=False),
            "facts: MuJoCo RGB",
            7.0,
        ),
        (
            "render left (light + depth)",
            lambda: renderer.render_view(T, spec.depth),
            "facts: RGB + depth",
            12.0,
        ),
        (
            "render depth only",
            lambda: renderer.render_view(T, spec.depth, rgb=False),
            "mj_multiRay",
            timed_ms(ray_cast, max(3, n // 10))[0],
        ),
        ("render segmentation", lambda: renderer.render_segmentation(T, spec.depth), "", None),
        (
            "render ids, dark cylinder's region",
            lambda: renderer.render_segmentation(
                T, spec.depth, region=geom_image_region(model, data, dark, T, spec.depth)
            ),
            "full-frame id pass",
            timed_ms(lambda: renderer.render_segmentation(T, spec.depth), max(3, n // 3))[0],
        ),
        (
            "render ids + depth (flat pass)",
            lambda: renderer.render_segmentation_and_depth(T, spec.depth),
            "",
            None,
        ),
        ("render right (light + depth)", lambda: renderer.render_view(T_right, spec.depth), "", None),
        (
            "D4 noise model",
            lambda: depth_model.apply(left.depth_m, rng, depth_right_m=right.depth_m),
            "facts: numpy model",
            17.0,
        ),
        ("IR pair", lambda: ir_model.pair(left.rgb, left.depth_m, right.rgb, right.depth_m, rng), "", None),
        ("SGBM 128 disparities", lambda: sgbm.depth(ir1, ir2), "facts: SGBM 96", 26.0),
        ("SGBM 96 disparities", lambda: sgbm96.depth(ir1, ir2), "facts: SGBM 96", 26.0),
    ]
    load = os.getloadavg()[0]
    print(
        f"{os.cpu_count()} CPUs, 1-min load average {load:.2f} at start (timings scale with contention), "
        f"{threads} thread(s) for llvmpipe and OpenCV"
    )
    header = f"{'darp ms':>8s} {'p10 ms':>7s} {'cpu ms':>7s}   {'peer':22s} {'peer ms':>8s} {'ratio':>6s}"
    print(f"{'stage (640x480)':34s} {header}")
    for name, fn, peer, peer_ms in stages:
        ms, p10, cpu = timed_ms(fn, n)
        line = f"{name:34s} {ms:8.2f} {p10:7.2f} {cpu:7.2f}"
        print(line if peer_ms is None else f"{line}   {peer:22s} {peer_ms:8.2f} {peer_ms / ms:5.2f}x")
        if peer_ms is not None:
            compared[name] = (ms, peer, peer_ms)
    renderer.close()

    print()
    rig = TwinCameraSettings.from_profile("realistic", segmentation=False)  # what TwinRig records
    profiles = [
        ("capture ideal", TwinCameraSettings.from_profile("ideal"), None),
        ("capture realistic", TwinCameraSettings.from_profile("realistic"), None),
        ("realistic, no segmentation", rig, None),
        ("realistic, no seg., dark dropouts", rig, {dark[0]: 0.7}),
        ("realistic, no IR", TwinCameraSettings.from_profile("realistic", render_ir=False), None),
        (
            "realistic, no IR, no segmentation",
            TwinCameraSettings.from_profile("realistic", render_ir=False, segmentation=False),
            None,
        ),
        (
            "SGBM mode",
            TwinCameraSettings.from_profile("realistic", depth_mode="sgbm", segmentation=False),
            None,
        ),
    ]
    print(
        f"{'whole camera (no bag writing)':34s} {header}  2-cam RTF @30 fps: median, p10, 2 free cores (CPU)"
    )
    split = {}
    for name, settings, dropouts in profiles:
        with TwinCamera(model, spec, settings, seed=1, dropout_geoms=dropouts) as cam:
            ms, p10, cpu = timed_ms(lambda cam=cam: cam.capture(data, T), max(5, n // 2))
            if dropouts:
                split = {k: 1e3 * v / cam.frame_index for k, v in cam.stage_cpu_s.items()}
        print(
            f"{name:34s} {ms:8.2f} {p10:7.2f} {cpu:7.2f}   {'30 fps frame period':22s} {FRAME_BUDGET_MS:8.2f} "
            f"{FRAME_BUDGET_MS / ms:5.2f}x  {FRAME_BUDGET_MS / (2 * ms):.2f}, {FRAME_BUDGET_MS / (2 * p10):.2f}, "
            f"{FRAME_BUDGET_MS / cpu:.2f}"
        )
        if settings is rig and not dropouts:
            compared[f"whole camera, {name} (as TwinRig records)"] = (ms, "30 fps frame period", FRAME_BUDGET_MS)
    print(
        "CPU ms per capture by stage (realistic, no seg., dark dropouts): "
        + ", ".join(f"{k} {v:.2f}" for k, v in split.items())
    )
    return compared


def rows(repeats: int = 10, threads: int = 1) -> list[Row]:
    """The results table's rows: each stage that has a peer (MuJoCo's CPU ray caster, the facts' reference
    timings) and the whole camera as the twin's rig records against the 30 fps frame period; no target stated."""
    return [row("twin_camera", f"{name}, 640x480, median", "ms", ms, peer_ms, peer)
            for name, (ms, peer, peer_ms) in measure(repeats, threads).items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument(
        "--threads",
        type=int,
        default=1,
        help="llvmpipe and OpenCV threads (1: as in a camera worker on 2 cores)",
    )
    args = parser.parse_args()
    measure(args.repeats, args.threads)


if __name__ == "__main__":
    main()
