#!/usr/bin/env python3
"""Real-time factor of a twin recording: both cameras, every stream, next to the real rig (factor 1).

Scenario: the default rig with the mug on the table; the joint log runs, both cameras record depth,
colour, both infrared images and the IMU, while arm110 swings between two views of the mug (arm111
parked). The real-time factor (RTF) is simulated seconds per wall-clock second of the recording loop;
the peer is the real rig, which records in real time (factor 1); the target is 0.5 on 2 cores.

The machine this runs on is shared, so the wall RTF moves with other processes' load (printed next
to it). The stable numbers are CPU times: per camera frame and per simulated second, all processes
and threads (llvmpipe's render threads included), split by stage from the camera's own counters
(``TwinCamera.stage_cpu_s``, the workers report theirs): render (every MuJoCo render and read-back),
IR (projector pattern, shadows, sensor noise), depth noise (the D4 model), colour (conversion and
noise), Z16 (depth units), write (bag messages and LZ4), IMU (main process) and the rest (scene
updates, kinematics, joint log, pipes). On N free cores the RTF cannot exceed N x simulated seconds
/ CPU seconds: that is the "2 free cores" estimate. Memory: the resident-set high-water marks of a
short and a long recording (flat means the recording streams to disk).

    .venv/bin/python studies/twin.py [--seconds 2] [--long 6] [--repeats 2] [--resolution 640x480]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

TARGET_RTF = 0.5
STAGES = ("render", "ir", "depth_noise", "colour", "z16", "write", "imu", "other")
MODES = {False: "one process", True: "2 camera workers"}


def measure(seconds: float, width: int, height: int, fps: int, profile: str, workers: bool,
            compression: str | None = None) -> dict:
    """One recording of ``seconds`` simulated seconds in this process; its times, CPU and memory."""
    import numpy as np

    from darp.twin.objects.model import ObjectPlacement, make_object
    from darp.twin.rig_backend import TwinRig
    from darp.twin.settings import TwinSettings

    settings = TwinSettings.from_profile(profile, seed=1).with_camera(width=width, height=height, fps=fps)
    if compression is not None:
        settings = settings.with_camera(compression=compression)
    load_start = os.getloadavg()[0]
    t_build = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, TwinRig(settings, obj=make_object("mug"), camera_workers=workers,
                                                       placement=ObjectPlacement(0.0, 0.0, 0.3)) as twin:
        build_s = time.perf_counter() - t_build
        park = twin.park_q("arm110")
        views = [park + np.array([0.25, 0.3, 0.0, -0.3, 0.1, 0.0]), park + np.array([-0.25, 0.3, 0.0, -0.3, -0.1, 0.0])]
        twin.start_joint_log(Path(tmp) / "arm_poses.csv")
        twin.clock.sleep(0.2)
        start_sim = twin.clock.elapsed_ns
        cpu0, t0 = time.process_time(), time.perf_counter()
        for cam in twin.cameras.values():
            cam.start_recording(Path(tmp) / f"cam{cam.serial}.bag")
        k = 0
        while (twin.clock.elapsed_ns - start_sim) / 1e9 < seconds:
            if not twin.arms["arm110"].is_moving():
                twin.arms["arm110"].move_to(views[k % 2])
                k += 1
            twin.clock.sleep(0.1)
        for cam in twin.cameras.values():
            cam.stop_recording()
        wall = time.perf_counter() - t0
        cpu_main = time.process_time() - cpu0
        sim = (twin.clock.elapsed_ns - start_sim) / 1e9
        twin.clock.sleep(0.2)
        twin.stop_joint_log()
        size = sum(p.stat().st_size for p in Path(tmp).iterdir())
        cams = list(twin.cameras.values())
        frames = sum(c.frames_recorded for c in cams)
        stages = dict.fromkeys(STAGES, 0.0)
        for c in cams:
            for key, value in c.stage_cpu_s.items():
                stages[key] += value
        cpu_workers = sum(c.worker.recording_cpu_s for c in cams if c.worker is not None)
        worker_rss = max((c.worker.peak_rss_mb for c in cams if c.worker is not None), default=0.0)
    cpu_total = cpu_main + cpu_workers
    stages["other"] = cpu_total - sum(stages.values())
    return {"seconds": sim, "wall_s": wall, "rtf": sim / wall, "build_s": build_s, "frames": frames,
            "cpu_main_s": cpu_main, "cpu_workers_s": cpu_workers, "cpu_s": cpu_total, "stages_cpu_s": stages,
            "workers": workers, "bytes": size, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "worker_rss_mb": worker_rss, "load": max(load_start, os.getloadavg()[0])}


def run_child(seconds: float, workers: bool, args: argparse.Namespace) -> dict:
    """:func:`measure` in a fresh interpreter (clean memory high-water marks)."""
    cmd = [sys.executable, __file__, "--child", str(seconds), "--resolution", args.resolution, "--fps",
           str(args.fps), "--profile", args.profile] + (["--workers"] if workers else []) \
        + (["--compression", args.compression] if args.compression else [])
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def median_run(runs: list[dict]) -> dict:
    """The run with the median CPU per frame (CPU is what other processes disturb least)."""
    ordered = sorted(runs, key=lambda r: r["cpu_s"] / max(r["frames"], 1))
    return ordered[len(ordered) // 2]


def print_stage_table(best: dict[bool, dict]) -> None:
    modes = list(best)
    print(f"\n  {'CPU ms per camera frame':28s}" + "".join(f"{MODES[m]:>18s}" for m in modes))
    for stage in STAGES:
        cells = "".join(f"{1e3 * best[m]['stages_cpu_s'][stage] / max(best[m]['frames'], 1):18.1f}" for m in modes)
        print(f"  {stage:28s}{cells}")
    total = "".join(f"{1e3 * best[m]['cpu_s'] / max(best[m]['frames'], 1):18.1f}" for m in modes)
    print(f"  {'total (all processes)':28s}{total}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated seconds of the short survey")
    parser.add_argument("--long", type=float, default=6.0, help="simulated seconds of the long survey")
    parser.add_argument("--resolution", default="640x480")
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--profile", default="realistic", choices=("ideal", "realistic"))
    parser.add_argument("--repeats", type=int, default=2, help="long runs per mode (CPU: median run; RTF: best)")
    parser.add_argument("--compression", choices=("lz4", "none"), default=None,
                        help="bag chunk compression (default: the twin's setting)")
    parser.add_argument("--workers", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child", type=float, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    if args.child is not None:
        print(json.dumps(measure(args.child, width, height, args.fps, args.profile, args.workers, args.compression)))
        return

    print(f"twin recording, {args.profile} profile, {width}x{height} at {args.fps} fps, both cameras, all streams "
          f"+ IMU, {os.cpu_count()} CPU cores, 1-min load average {os.getloadavg()[0]:.1f} at start")
    median: dict[bool, dict] = {}
    fastest: dict[bool, dict] = {}
    short: dict[bool, dict] = {}
    for workers in (False, True):
        runs = [run_child(args.long, workers, args) for _ in range(max(1, args.repeats))]
        median[workers], fastest[workers] = median_run(runs), max(runs, key=lambda r: r["rtf"])
        short[workers] = run_child(args.seconds, workers, args)
        for r in runs:
            n = r["frames"]
            print(f"  {MODES[workers]}: {r['seconds']:.1f} s simulated in {r['wall_s']:.1f} s wall, RTF {r['rtf']:.3f} "
                  f"at load average {r['load']:.1f}; {n} camera frames, {r['bytes'] / 1e6:.0f} MB; "
                  f"CPU {1e3 * r['cpu_s'] / n:.1f} ms per frame")
    print_stage_table(median)
    print()
    for workers, r in median.items():
        cpu_per_sim = r["cpu_s"] / r["seconds"]
        f = fastest[workers]
        print(f"{MODES[workers]}: CPU {cpu_per_sim:.2f} s per simulated second, "
              f"{1e3 * r['cpu_s'] / r['frames']:.1f} ms per camera frame -> estimated RTF on 2 free cores "
              f"{2.0 / cpu_per_sim:.2f}")
        print(f"  real-time factor: darp twin {f['rtf']:.3f} (load average {f['load']:.1f}), real rig 1.000, "
              f"ratio {f['rtf']:.3f}; target {TARGET_RTF}: wall {'met' if f['rtf'] >= TARGET_RTF else 'missed'}, "
              f"2-free-core estimate {'met' if 2.0 / cpu_per_sim >= TARGET_RTF else 'missed'}")
    print()
    for workers in (False, True):
        s, lg = short[workers], median[workers]
        print(f"memory ({MODES[workers]}): peak RSS of the main process {s['maxrss_mb']:.0f} MB ({s['seconds']:.0f} s) "
              f"vs {lg['maxrss_mb']:.0f} MB ({lg['seconds']:.0f} s): {lg['maxrss_mb'] - s['maxrss_mb']:+.0f} MB")
        if workers:
            print(f"  per camera worker: {s['worker_rss_mb']:.0f} MB vs {lg['worker_rss_mb']:.0f} MB: "
                  f"{lg['worker_rss_mb'] - s['worker_rss_mb']:+.0f} MB")


if __name__ == "__main__":
    main()
