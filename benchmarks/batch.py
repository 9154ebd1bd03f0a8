#!/usr/bin/env python3
"""Batches on Ray: executor overhead against a plain loop, and 1 -> 2 worker scaling, on the same surveys.

1. ``--surveys`` twin surveys are made with ``darp twin generate``'s draws (cube / mug / ketchup; by
   default tiny: 424x240 at 6 fps, 2 views per arm; ``--resolution``, ``--fps`` and ``--views`` make them
   closer to real surveys, whose processing dwarfs a fresh worker's start-up), in a plain loop in this
   process: CPU-seconds and bytes per survey made.
2. The same surveys are processed (``darp process --truth-poses``'s stages) four ways: a plain loop
   in this process; Ray with one worker (``num_cpus=1``) and with two workers, each task in a fresh
   process forked from the worker's preloaded forkserver (darp's default, ``isolation="fork"``); and
   Ray with one worker and a fresh worker per task (``isolation="worker"``, ``max_calls=1``: what darp
   did before; ``--no-compare`` skips it). Each Ray run starts its own local Ray instance; its start-up
   (``ray.init``, then one warm-up task per worker that starts the worker's forkserver and imports darp
   there) is timed apart from the batch, as the loop's start-up (importing darp in this process) is.
   Before each run the surveys' files are read once, so every run finds them in the page cache.
3. After the one-worker batch, tasks that do nothing measure the fixed cost per task (the fork, the
   Ray round trip).

Printed: per-survey CPU-seconds and bytes (raw survey, processed output), the overhead of Ray with one
worker against the loop (target <= 5 %; also with both start-ups counted), the scaling efficiency from 1 to 2 workers
(``T1 / (2 * T2)``, target >= 90 %), and the load average before and after each run: this 2-core machine
is shared, so wall-clock ratios move with what else runs.

    .venv/bin/python benchmarks/batch.py [--surveys 4] [--seed 0] [--resolution 424x240] [--fps 6] [--views 2]
        [--work DIR] [--json results.json] [--no-compare]

The idle-machine reference run (docs/scaling.md) is
``benchmarks/batch.py --resolution 640x480 --fps 15 --views 3 --work /tmp/darp-batch`` (a second run
with the same ``--work`` skips making the surveys).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("RAY_worker_niceness", "0")  # as darp's own local Ray: workers at the loop's priority
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

_t0 = time.perf_counter()
from darp.batch.executor import Executor, run_tasks  # noqa: E402
from darp.batch.fresh import idle  # noqa: E402
from darp.batch.generate import plan_surveys, record_generated  # noqa: E402
from darp.batch.tasks import process_one  # noqa: E402
from darp.processing.settings import ProcessSettings  # noqa: E402

IMPORT_S = time.perf_counter() - _t0  # the loop's start-up: darp's processing stack imported here


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (user + system)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def load() -> float:
    return round(os.getloadavg()[0], 2)


def fixed_cost(n: int, isolation: str) -> dict[str, float]:
    """Wall seconds per task of ``n`` tasks that do nothing, one batch on one Ray worker (one at a time)."""
    t0 = time.perf_counter()
    run_tasks(idle, [()] * n, Executor("ray"), isolation=isolation)
    return {"per_task_s": round((time.perf_counter() - t0) / n, 3)}


def warm_page_cache(surveys: list[Path]) -> float:
    """Read every file of the surveys once (seconds taken), so that no run pays for a cold page cache and
    the loop, which runs first, is not the only one that reads from disk."""
    t0 = time.perf_counter()
    for survey in surveys:
        for path in sorted(survey.rglob("*")):
            if path.is_file():
                with open(path, "rb") as f:
                    while f.read(16 << 20):
                        pass
    return time.perf_counter() - t0


def process_all(surveys: list[Path], out: Path, executor: Executor, workers: int,
                isolation: str = "fork") -> dict[str, Any]:
    shutil.rmtree(out, ignore_errors=True)
    cache_s = warm_page_cache(surveys)
    settings = ProcessSettings().to_dict()
    calls = [(str(s), str(out / s.name), None, True, settings, False) for s in surveys]
    before = load()
    init_s = warm_s = 0.0
    fixed = None
    if executor.kind == "ray":
        import ray

        t0 = time.perf_counter()
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
        init_s = time.perf_counter() - t0
        if isolation == "fork":  # every worker starts its forkserver (darp imported there) before the batch
            t0 = time.perf_counter()
            forkservers = run_tasks(idle, [(1.0,)] * workers, executor)
            warm_s = time.perf_counter() - t0 - 1.0
            if len(set(forkservers)) != workers:
                print(f"warning: the warm-up reached {len(set(forkservers))} of {workers} workers", file=sys.stderr)
    cpu0, t0 = cpu_s(), time.perf_counter()
    try:
        run_tasks(process_one, calls, executor, isolation=isolation)
        wall = time.perf_counter() - t0
        if executor.kind == "ray" and workers == 1:
            fixed = fixed_cost(len(surveys), isolation)
    finally:
        if executor.kind == "ray":
            import ray

            ray.shutdown()
    return {"executor": str(executor), "workers": workers, "isolation": isolation if executor.kind == "ray" else None,
            "wall_s": round(wall, 2), "ray_init_s": round(init_s, 2), "warm_up_s": round(warm_s, 2),
            "driver_cpu_s": round(cpu_s() - cpu0, 2), "load_before": before, "load_after": load(),
            "fixed_cost": fixed, "page_cache_warm_s": round(cache_s, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--surveys", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", default="424x240", help="camera resolution WxH of the surveys")
    parser.add_argument("--fps", type=int, default=6)
    parser.add_argument("--views", type=int, default=2, help="orbit views per arm")
    parser.add_argument("--work", type=Path, default=None, help="keep the surveys here (default: a temp folder)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--no-compare", action="store_true", help="skip the fresh-worker-per-task run")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="darp-batch-"))
    gen = work / "surveys"
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    specs = plan_surveys(args.surveys, args.seed, ["cube", "mug", "ketchup"], views=args.views, fps=args.fps,
                         width=width, height=height)
    make = []
    for spec in specs:
        cpu0, t0 = cpu_s(), time.perf_counter()
        made = record_generated(spec, str(gen))
        make.append({"name": spec.name, "skipped": made["skipped"], "cpu_s": round(cpu_s() - cpu0, 2),
                     "wall_s": round(time.perf_counter() - t0, 2), "bytes": folder_bytes(gen / spec.name)})
    surveys = [gen / s.name for s in specs]

    loop_cpu0 = cpu_s()
    loop = process_all(surveys, work / "loop", Executor(), 1, "worker")
    loop["cpu_s"] = round(cpu_s() - loop_cpu0, 2)
    processed_bytes = [folder_bytes(work / "loop" / s.name) for s in surveys]
    ray1 = process_all(surveys, work / "ray1", Executor("ray"), 1)
    ray2 = process_all(surveys, work / "ray2", Executor("ray"), 2)
    fresh1 = None if args.no_compare else process_all(surveys, work / "ray1w", Executor("ray"), 1, "worker")

    def pct(ratio: float) -> float:
        return round(100 * (ratio - 1.0), 1)

    loop_start = IMPORT_S
    ray_start = ray1["ray_init_s"] + ray1["warm_up_s"]
    made = [m for m in make if not m["skipped"]]
    result = {
        "surveys": args.surveys, "cpu_count": os.cpu_count(), "make": make,
        "make_cpu_s_per_survey": round(sum(m["cpu_s"] for m in made) / len(made), 2) if made else None,
        "survey_bytes_mean": int(sum(m["bytes"] for m in make) / len(make)),
        "processed_bytes_mean": int(sum(processed_bytes) / len(processed_bytes)),
        "process_cpu_s_per_survey": round(loop["cpu_s"] / args.surveys, 2),
        "loop_import_s": round(loop_start, 2),
        "loop": loop, "ray_1_worker": ray1, "ray_2_workers": ray2, "ray_1_fresh_worker_per_task": fresh1,
        "ray_overhead_pct": pct(ray1["wall_s"] / loop["wall_s"]),
        "ray_overhead_with_startup_pct": pct((ray1["wall_s"] + ray_start) / (loop["wall_s"] + loop_start)),
        "fresh_worker_overhead_pct": None if fresh1 is None else pct(fresh1["wall_s"] / loop["wall_s"]),
        "scaling_efficiency_pct": round(100 * ray1["wall_s"] / (2.0 * ray2["wall_s"]), 1),
    }
    print(f"surveys: {args.surveys} ({args.resolution}, {args.fps} fps, {args.views} views per arm), "
          f"{os.cpu_count()} CPUs; shared machine: load averages are printed with each run")
    print(f"make a survey: {result['make_cpu_s_per_survey']} CPU-s, {result['survey_bytes_mean'] / 1e6:.1f} MB; "
          f"process it: {result['process_cpu_s_per_survey']} CPU-s, {result['processed_bytes_mean'] / 1e6:.1f} MB")
    print(f"loop start-up (import darp here): {loop_start:.2f} s")
    for name in ("loop", "ray_1_worker", "ray_2_workers", "ray_1_fresh_worker_per_task"):
        r = result[name]
        if r is not None:
            print(f"{name:<28} wall {r['wall_s']:7.2f} s  (ray.init {r['ray_init_s']:.2f} s, warm-up "
                  f"{r['warm_up_s']:.2f} s, page cache {r['page_cache_warm_s']:.1f} s)  "
                  f"load {r['load_before']} -> {r['load_after']}")
    print(f"Ray overhead vs plain loop (1 worker, fork per task): {result['ray_overhead_pct']} % (target <= 5 %); "
          f"with both start-ups: {result['ray_overhead_with_startup_pct']} %")
    if fresh1 is not None:
        print(f"  a fresh Ray worker per task instead (max_calls=1): {result['fresh_worker_overhead_pct']} %")
    print(f"scaling 1 -> 2 workers: efficiency {result['scaling_efficiency_pct']} % (target >= 90 %)")
    per_survey = loop["wall_s"] / args.surveys
    for name, r in (("fork", ray1), ("fresh worker", fresh1)):
        if r is not None and r["fixed_cost"]:
            cost = r["fixed_cost"]["per_task_s"]
            print(f"fixed cost of a Ray task ({name}): {cost} s per task against {per_survey:.2f} s per survey "
                  f"in the loop ({100 * cost / per_survey:.1f} %)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
