#!/usr/bin/env python3
"""Batches on Ray: executor overhead against a plain loop, and 1 -> 2 worker scaling, on the same surveys.

1. ``--surveys`` twin surveys are made with ``darp twin generate``'s draws (cube / mug / ketchup; by
   default tiny: 424x240 at 6 fps, 2 views per arm; ``--resolution``, ``--fps`` and ``--views`` make them
   closer to real surveys, whose processing dwarfs a fresh worker's start-up), in a plain loop in this
   process: CPU-seconds and bytes per survey made.
2. The same surveys are processed (``darp process --truth-poses``'s stages) three ways: a plain loop
   in this process; Ray with one worker (``num_cpus=1``); Ray with two workers. Each Ray run starts
   its own local Ray instance; its start-up is timed apart from the batch.

Printed: per-survey CPU-seconds and bytes (raw survey, processed output), the overhead of Ray with one
worker against the loop (target <= 5 %), the scaling efficiency from 1 to 2 workers
(``T1 / (2 * T2)``, target >= 90 %), and the load average before and after each run: this 2-core machine
is shared, so wall-clock ratios move with what else runs.

    .venv/bin/python benchmarks/batch.py [--surveys 4] [--seed 0] [--resolution 424x240] [--fps 6] [--views 2]
        [--work DIR] [--json results.json]
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
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from darp.batch.executor import Executor, run_tasks
from darp.batch.generate import plan_surveys, record_generated
from darp.batch.tasks import process_one
from darp.processing.settings import ProcessSettings


def cpu_s() -> float:
    """CPU seconds of this process and its finished children (user + system)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def load() -> float:
    return round(os.getloadavg()[0], 2)


def import_only() -> float:
    """What a fresh worker pays before its survey: importing darp's processing (numpy, Open3D, OpenCV...)."""
    t0 = time.perf_counter()
    import darp.batch.tasks  # noqa: F401

    return time.perf_counter() - t0


def fixed_cost(n: int) -> dict[str, float]:
    """Wall seconds per task of ``n`` tasks that only import darp, one at a time on one Ray worker."""
    t0 = time.perf_counter()
    imports = run_tasks(import_only, [()] * n, Executor("ray"))
    return {"per_task_s": round((time.perf_counter() - t0) / n, 2),
            "import_s": round(sum(imports) / n, 2)}


def process_all(surveys: list[Path], out: Path, executor: Executor, workers: int) -> dict[str, Any]:
    shutil.rmtree(out, ignore_errors=True)
    settings = ProcessSettings().to_dict()
    calls = [(str(s), str(out / s.name), None, True, settings, False) for s in surveys]
    before = load()
    init_s = 0.0
    if executor.kind == "ray":
        import ray

        t0 = time.perf_counter()
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
        init_s = time.perf_counter() - t0
    fixed = fixed_cost(len(surveys)) if executor.kind == "ray" and workers == 1 else None
    cpu0, t0 = cpu_s(), time.perf_counter()
    try:
        run_tasks(process_one, calls, executor)
        wall = time.perf_counter() - t0
    finally:
        if executor.kind == "ray":
            import ray

            ray.shutdown()
    return {"executor": str(executor), "workers": workers, "wall_s": round(wall, 2), "ray_init_s": round(init_s, 2),
            "driver_cpu_s": round(cpu_s() - cpu0, 2), "load_before": before, "load_after": load(),
            "fixed_cost": fixed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--surveys", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", default="424x240", help="camera resolution WxH of the surveys")
    parser.add_argument("--fps", type=int, default=6)
    parser.add_argument("--views", type=int, default=2, help="orbit views per arm")
    parser.add_argument("--work", type=Path, default=None, help="keep the surveys here (default: a temp folder)")
    parser.add_argument("--json", type=Path, default=None)
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
    loop = process_all(surveys, work / "loop", Executor(), 1)
    loop["cpu_s"] = round(cpu_s() - loop_cpu0, 2)
    processed_bytes = [folder_bytes(work / "loop" / s.name) for s in surveys]
    ray1 = process_all(surveys, work / "ray1", Executor("ray"), 1)
    ray2 = process_all(surveys, work / "ray2", Executor("ray"), 2)

    overhead = ray1["wall_s"] / loop["wall_s"] - 1.0
    overhead_with_init = (ray1["wall_s"] + ray1["ray_init_s"]) / loop["wall_s"] - 1.0
    efficiency = ray1["wall_s"] / (2.0 * ray2["wall_s"])
    made = [m for m in make if not m["skipped"]]
    result = {
        "surveys": args.surveys, "cpu_count": os.cpu_count(), "make": make,
        "make_cpu_s_per_survey": round(sum(m["cpu_s"] for m in made) / len(made), 2) if made else None,
        "survey_bytes_mean": int(sum(m["bytes"] for m in make) / len(make)),
        "processed_bytes_mean": int(sum(processed_bytes) / len(processed_bytes)),
        "process_cpu_s_per_survey": round(loop["cpu_s"] / args.surveys, 2),
        "loop": loop, "ray_1_worker": ray1, "ray_2_workers": ray2,
        "ray_overhead_pct": round(100 * overhead, 1), "ray_overhead_with_init_pct": round(100 * overhead_with_init, 1),
        "scaling_efficiency_pct": round(100 * efficiency, 1),
    }
    print(f"surveys: {args.surveys} ({args.resolution}, {args.fps} fps, {args.views} views per arm), "
          f"{os.cpu_count()} CPUs; shared machine: "
          f"load averages are printed with each run")
    print(f"make a survey: {result['make_cpu_s_per_survey']} CPU-s, {result['survey_bytes_mean'] / 1e6:.1f} MB; "
          f"process it: {result['process_cpu_s_per_survey']} CPU-s, {result['processed_bytes_mean'] / 1e6:.1f} MB")
    for name in ("loop", "ray_1_worker", "ray_2_workers"):
        r = result[name]
        print(f"{name:<14} wall {r['wall_s']:7.2f} s  (ray start {r['ray_init_s']:.2f} s)  "
              f"load {r['load_before']} -> {r['load_after']}")
    print(f"Ray overhead vs plain loop (1 worker): {result['ray_overhead_pct']} % (target <= 5 %); "
          f"with Ray's start-up: {result['ray_overhead_with_init_pct']} %")
    print(f"scaling 1 -> 2 workers: efficiency {result['scaling_efficiency_pct']} % (target >= 90 %)")
    fixed = ray1["fixed_cost"]
    per_survey = loop["wall_s"] / args.surveys
    print(f"fixed cost of a Ray task (fresh worker, import darp): {fixed['per_task_s']} s, of which import "
          f"{fixed['import_s']} s; per survey in the loop {per_survey:.2f} s: the overhead it explains "
          f"{100 * fixed['per_task_s'] / per_survey:.0f} %")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
