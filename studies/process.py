#!/usr/bin/env python3
"""End-to-end processing speed and memory: ``darp process`` on twin surveys, next to real time.

Scenario: twin surveys of the mug (realistic profile), both cameras recording every stream (depth,
colour, IR left and right, IMU) at 640x480 and 30 fps, one arm at a time orbiting the object (two
rings of views, dwell 0.6 s). Two lengths (default about 30 s and 60 s of recording) are generated once
into a cache folder (the twin renders them slower than real time; this is not timed).

Each survey is then processed in its own subprocess, all five stages (poses, keyframes, fusion, mesh,
evaluation with ground truth and figures), with the true calibration. Reported: the wall and CPU time
of each stage, the survey's length, and the ratio survey seconds / processing seconds (the peer is the
real rig, which records in real time: a ratio above 1 means processing keeps up with acquisition),
plus the subprocess's peak resident memory (ru_maxrss) for both lengths: flat means streaming.

    .venv/bin/python studies/process.py [--cache DIR] [--lengths 30,60] [--fps 30] [--resolution 640x480]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")


def make_survey(folder: Path, seconds: float, fps: int, width: int, height: int) -> Path:
    """Record (once) a twin survey of about ``seconds``: waypoints are added until the plan is that long."""
    from darp.kinematics.rig import load_rig
    from darp.twin.objects.model import ObjectPlacement, make_object
    from darp.twin.record import expected_duration_s, record_survey
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import WaypointPlan, orbit_waypoints

    if (folder / "arm_poses.csv").is_file():
        return folder
    rig, obj = load_rig(), make_object("mug")
    placement = ObjectPlacement(0.0, 0.0, 0.3)
    centre = (0.0, 0.0, 0.5 * obj.height_m)
    settings = TwinSettings.from_profile("realistic", seed=5).with_camera(fps=fps, width=width, height=height)
    views = {arm: [w for elevation in (35.0, 60.0) for w in orbit_waypoints(
        rig, arm, centre, 0.36, azimuths_deg=(-45, -22.5, 0, 22.5, 45), elevation_deg=elevation, dwell_s=0.6)]
        for arm in ("arm110", "arm111")}
    park = {arm: rig.arms[arm].park_q_rad for arm in views}
    count = 1
    while True:
        plan = WaypointPlan({arm: tuple(v[:count]) for arm, v in views.items()}, ("arm110", "arm111"))
        if expected_duration_s(plan, park, settings) >= seconds or count >= min(len(v) for v in views.values()):
            break
        count += 1
    t0 = time.perf_counter()
    result = record_survey(folder, plan, obj, placement, settings=settings, camera_workers=True)
    print(f"  recorded {folder.name}: {result.duration_s:.1f} s of survey, {result.frames} depth frames, "
          f"{time.perf_counter() - t0:.0f} s to render (not timed below)", flush=True)
    return folder


class MemorySampler:
    """Peak anonymous and file-backed resident memory of this process, sampled every 20 ms.

    ``ru_maxrss`` counts the pages of memory-mapped recordings that a pass over the file touched (page
    cache, shared and reclaimable); the anonymous part is the memory the process itself allocated.
    """

    def __init__(self) -> None:
        import threading

        self.peak = {"RssAnon": 0, "RssFile": 0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                key = line.split(":")[0]
                if key in self.peak:
                    self.peak[key] = max(self.peak[key], int(line.split()[1]) // 1024)

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self._sample()

    def __enter__(self):  # returns self
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


def child(survey: str, out: str) -> None:
    """Process one survey (run in a subprocess) and print a JSON line with the timings."""
    from darp.formats.survey import open_survey
    from darp.processing.job import SurveyJob
    from darp.processing.runner import process_survey
    from darp.processing.stages import PROCESS_STAGES
    from darp.twin.truth import read_truth

    truth = read_truth(survey)
    cpu: dict[str, float] = {}
    stages = []
    for stage in PROCESS_STAGES:
        def timed(job, run=stage.run, name=stage.name):
            c0 = time.process_time()
            try:
                return run(job)
            finally:
                cpu[name] = time.process_time() - c0
        stages.append(type(stage)(stage.name, timed, stage.outputs, stage.settings_groups))
    job = SurveyJob(open_survey(survey), Path(out), truth.calibration, None)
    t0, c0 = time.perf_counter(), time.process_time()
    with MemorySampler() as memory:
        report = process_survey(job, stages)
    wall, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    results = json.loads((Path(out) / "results.json").read_text())
    print(json.dumps({
        "wall_s": wall, "cpu_s": total_cpu, "stages": {k: v["seconds"] for k, v in report.items()}, "stage_cpu_s": cpu,
        "duration_s": results["composition"]["duration_s"], "depth_frames": results["composition"]["depth_frames"],
        "keyframes": results["keyframes"]["total"], "fused_points": results["clouds"].get("fused"),
        "heldout": results["heldout"]["aggregate"], "accuracy": results["truth"]["cloud"]["accuracy"],
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "peak_anon_mb": memory.peak["RssAnon"], "peak_file_mb": memory.peak["RssFile"]}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/darp-bench-process"))
    parser.add_argument("--lengths", default="30,60", help="survey lengths to generate, seconds")
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--resolution", default="640x480")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    width, height = (int(v) for v in args.resolution.split("x"))
    cores = len(os.sched_getaffinity(0))
    print(f"darp process on twin surveys ({args.resolution}, {args.fps} fps, every stream), {cores} cores, "
          f"load average {os.getloadavg()[0]:.1f}")
    rows = []
    for seconds in (float(s) for s in args.lengths.split(",")):
        survey = make_survey(args.cache / f"mug_{int(seconds)}s_{args.fps}fps_{width}x{height}", seconds,
                             args.fps, width, height)
        out = args.cache / "out" / survey.name
        proc = subprocess.run([sys.executable, __file__, "--child", str(survey), str(out)], capture_output=True,
                              text=True, check=False)
        if proc.returncode != 0:
            sys.exit(f"processing {survey} failed:\n{proc.stderr}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    print(f"\n{'survey [s]':>10} {'frames':>12} {'keyframes':>9} {'process wall [s]':>16} {'CPU [s]':>8} "
          f"{'ratio (real time / wall)':>24} {'peak RSS [MB]':>13} {'anon [MB]':>9} {'file-backed [MB]':>16}")
    for r in rows:
        frames = "+".join(str(v) for v in r["depth_frames"].values())
        print(f"{r['duration_s']:10.1f} {frames:>12} {r['keyframes']:9d} {r['wall_s']:16.1f} {r['cpu_s']:8.1f} "
              f"{r['duration_s'] / r['wall_s']:24.2f} {r['max_rss_mb']:13.0f} {r['peak_anon_mb']:9.0f} "
              f"{r['peak_file_mb']:16.0f}")
    print("\nper stage, wall s (CPU s):")
    for r in rows:
        parts = ", ".join(f"{k} {v:.1f} ({r['stage_cpu_s'].get(k, float('nan')):.1f})" for k, v in r["stages"].items())
        print(f"  {r['duration_s']:.0f} s survey: {parts}")
    print("\nquality (true calibration):")
    for r in rows:
        h, a = r["heldout"], r["accuracy"]
        print(f"  {r['duration_s']:.0f} s survey: held-out median {h['median_mm']:.2f} mm, RMSE {h['rmse_mm']:.2f} mm, "
              f"{h['within_10mm_pct']:.2f} % within 10 mm ({h['count']:,} points); fused accuracy vs truth median "
              f"{a['median_mm']:.3f} mm ({r['fused_points']:,} points)")
    if len(rows) > 1:
        length = rows[-1]["duration_s"] / rows[0]["duration_s"]
        for key, label in (("max_rss_mb", "peak RSS"), ("peak_anon_mb", "peak anonymous memory")):
            print(f"\n{label} x{rows[-1][key] / rows[0][key]:.2f} for a x{length:.2f} longer survey (flat: ~1); "
                  f"target < 4096 MB")


if __name__ == "__main__":
    main()
