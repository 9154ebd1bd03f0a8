#!/usr/bin/env python3
"""Batches on Ray: executor overhead against a plain loop, and 1 -> 2 worker scaling, on the same surveys.

1. ``--surveys`` twin surveys are made with ``darp twin generate``'s draws (cube / mug / ketchup; by
   default tiny: 424x240 at 6 fps, 2 views per arm; ``--resolution``, ``--fps`` and ``--views`` make them
   closer to real surveys), in a plain loop in this process: CPU-seconds and bytes per survey made.
2. The machine's own 1 -> 2 ceiling: one job alone, then two identical ones at once, pure compute
   (Python + single-threaded numpy in cache) and memory-bound (numpy streaming twice the L3).
3. The same surveys are processed (``darp process --truth-poses``'s stages) four ways: a plain loop
   in this process; Ray with one worker (``num_cpus=1``) and with two workers, each task in a fresh
   process forked from the worker's preloaded forkserver (darp's default, ``isolation="fork"``); and
   Ray with one worker and a fresh worker per task (``isolation="worker"``, ``max_calls=1``: what darp
   did before; ``--no-compare`` skips it). **The same thread configuration everywhere**: ``--threads``
   (default 1) threads in every library (BLAS, OpenMP, OpenCV, Open3D) in the loop (set before numpy
   loads) and in each task (``run_tasks(threads=...)``). The loop imports darp and the modules the
   forkservers preload (``darp.batch.fresh.PRELOAD``) before its batch, as Ray's start-up does (``ray.init``,
   then one warm-up task per worker that starts its forkserver); both start-ups are timed apart from the
   batch. Surveys are submitted largest first (as ``darp process`` does). Before each run the surveys'
   files are read once, so every run finds them in the page cache.
4. After the one-worker batch, tasks that do nothing measure the fixed cost per task (the fork, the
   Ray round trip).

Printed, with the load average before and after each run (this 2-core machine is shared): the overhead
of Ray with one worker against the loop (target <= 5 %; wall, CPU-seconds, and with both start-ups), the
scaling efficiency from 1 to 2 workers (``T1 / (2 * T2)``, target >= 90 %) next to the machine's ceiling
and split into its factors (a survey's slowdown and CPU with two at once, the workers' balance, the
share of the batch spent in surveys), and the **CPU accounting** of every run: CPU-seconds of every
process of the tree by role (this driver, gcs_server, raylet, dashboard, monitors, agents, workers,
forkservers, the survey processes; ``studies/cputree.py``), and per survey, inside its process, the
CPU of its main thread and of the other threads, and the CPU its process used before the call.

    .venv/bin/python studies/batch.py [--surveys 4] [--seed 0] [--resolution 424x240] [--fps 6] [--views 2]
        [--threads 1] [--work DIR] [--json results.json] [--no-compare] [--only-ray]

The idle-machine reference run (docs/scaling.md) is
``studies/batch.py --resolution 640x480 --fps 15 --views 3 --work /tmp/darp-batch`` (a second run
with the same ``--work`` skips making the surveys).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _threads_argument(argv: list[str]) -> int:
    """``--threads N`` read before numpy and darp are imported (the pools size themselves when they load)."""
    for k, arg in enumerate(argv):
        if arg == "--threads" and k + 1 < len(argv):
            return int(argv[k + 1])
        if arg.startswith("--threads="):
            return int(arg.split("=", 1)[1])
    return 1


THREADS = _threads_argument(sys.argv)
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("RAY_worker_niceness", "0")  # as darp's own local Ray: workers at the loop's priority
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
# Ray's workers, their forkservers and the survey processes import cputree.timed_process_one by reference.
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1] / "src"),
     *([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])])
from darp.batch.threads import limit_threads, thread_env  # noqa: E402  (imports nothing heavy)

# The loop and every Ray task run with the same thread configuration: THREADS threads in every library
# (BLAS, OpenMP, OpenCV, Open3D). Set before numpy loads here; Ray's workers inherit this environment
# and darp's tasks call limit_threads(num_cpus) in their process.
os.environ.update(thread_env(THREADS))

_t0 = time.perf_counter()
from cputree import RAY_OWN, CpuTree, delta, timed_process_one  # noqa: E402  (studies/cputree.py)
from darp.batch.executor import Executor, run_tasks  # noqa: E402
from darp.batch.fresh import PRELOAD, idle  # noqa: E402
from darp.batch.generate import plan_surveys, record_generated  # noqa: E402
from darp.processing.settings import ProcessSettings  # noqa: E402

for _module in PRELOAD:  # what each Ray worker's forkserver imports before the batch, the loop imports too:
    importlib.import_module(_module)  # else the loop's first survey pays the lazy imports inside its batch
IMPORT_S = time.perf_counter() - _t0  # the loop's start-up: darp's processing stack imported here
LOOP_THREADS = limit_threads(THREADS)


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
    run_tasks(idle, [()] * n, Executor("ray"), isolation=isolation, threads=THREADS)
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


def per_survey(stats: list[dict[str, Any]], wall_s: float) -> dict[str, Any]:
    """What the surveys took inside their processes, and how the batch's wall splits over the workers."""
    busy: dict[int, float] = {}
    for s in stats:
        busy[s["ppid"]] = busy.get(s["ppid"], 0.0) + s["wall_s"]
    main_cpu = sum(s["main_thread_cpu_s"] for s in stats)
    before_cpu = sum(s["process_cpu_before_s"] for s in stats) if stats[0]["pid"] != os.getpid() else 0.0
    other_cpu = sum(s["other_threads_cpu_s"] for s in stats)
    return {"survey_wall_s": round(sum(s["wall_s"] for s in stats), 2),
            "survey_cpu_s": round(main_cpu + other_cpu, 2), "main_thread_cpu_s": round(main_cpu, 2),
            "other_threads_cpu_s": round(other_cpu, 2), "threads_max": max(s["threads"] for s in stats),
            "process_cpu_s": round(sum(s["process_cpu_s"] for s in stats), 2),
            "child_cpu_before_call_s": round(before_cpu, 2),
            "worker_busy_s": sorted((round(v, 2) for v in busy.values()), reverse=True),
            "outside_surveys_s": round(wall_s - max(busy.values()), 2),
            "order": [s["name"] for s in sorted(stats, key=lambda s: s["start"])]}


def process_all(surveys: list[Path], out: Path, executor: Executor, workers: int,
                isolation: str = "fork") -> dict[str, Any]:
    """Process the surveys on ``executor`` (start-up timed apart); wall, CPU by process role, per-survey stats."""
    shutil.rmtree(out, ignore_errors=True)
    cache_s = warm_page_cache(surveys)
    settings = ProcessSettings().to_dict()
    calls = [(str(s), str(out / s.name), None, True, settings, False) for s in surveys]
    costs = [folder_bytes(s) for s in surveys]  # what darp's process_batch submits by: the largest first
    before = load()
    tree = CpuTree()
    init_s = warm_s = 0.0
    fixed = None
    s_start = tree.snapshot()
    if executor.kind == "ray":
        import ray

        from darp.batch.executor import ray_init_options

        t0 = time.perf_counter()
        ray.init(**ray_init_options(None, workers))
        init_s = time.perf_counter() - t0
        if isolation == "fork":  # every worker starts its forkserver (darp imported there) before the batch
            t0 = time.perf_counter()
            forkservers = run_tasks(idle, [(1.0,)] * workers, executor, threads=THREADS)
            warm_s = time.perf_counter() - t0 - 1.0
            if len(set(forkservers)) != workers:
                print(f"warning: the warm-up reached {len(set(forkservers))} of {workers} workers", file=sys.stderr)
    s_ready = tree.snapshot()
    t0 = time.perf_counter()
    try:
        stats = run_tasks(timed_process_one, calls, executor, isolation=isolation, threads=THREADS, costs=costs)
        wall = time.perf_counter() - t0
        s_done = tree.snapshot()
        if executor.kind == "ray" and workers == 1:
            fixed = fixed_cost(len(surveys), isolation)
    finally:
        if executor.kind == "ray":
            import ray

            ray.shutdown()
    failed = [s["name"] for s in stats if s["status"] != "done"]
    if failed:
        print(f"warning: {executor} failed on {failed}", file=sys.stderr)
    cpu = delta(s_ready, s_done)
    ray_own = sum(v for k, v in cpu.items() if k in RAY_OWN)
    return {"executor": str(executor), "workers": workers, "isolation": isolation if executor.kind == "ray" else None,
            "wall_s": round(wall, 2), "ray_init_s": round(init_s, 2), "warm_up_s": round(warm_s, 2),
            "load_before": before, "load_after": load(), "fixed_cost": fixed, "page_cache_warm_s": round(cache_s, 2),
            "cpu_s": cpu, "cpu_s_total": round(sum(cpu.values()), 2), "startup_cpu_s": delta(s_start, s_ready),
            "ray_own_cores": round(ray_own / wall, 4), "surveys": per_survey(stats, wall)}


def _compute_job(seconds_of_work: float, kind: str, out: Any) -> None:
    """A fixed amount of work timed in its process: ``compute`` (Python arithmetic and single-threaded numpy
    in cache) or ``memory`` (numpy streaming 64 MB arrays, twice the L3 cache: memory bandwidth)."""
    import numpy as np

    t0, c0 = time.perf_counter(), time.process_time()
    rng = np.random.default_rng(0)
    if kind == "compute":
        a = rng.standard_normal((256, 256))
        total = 0
        for k in range(int(seconds_of_work * 4e6)):
            total += k * k % 7
        for _ in range(int(seconds_of_work * 300)):
            a = np.tanh(a @ a.T / 256.0)
    else:
        src, dst = rng.standard_normal(8 << 20), np.empty(8 << 20)
        for _ in range(int(seconds_of_work * 100)):
            np.multiply(src, 1.0001, out=dst)
            np.add(dst, 1.0, out=src)
    out.put((time.perf_counter() - t0, time.process_time() - c0))


def compute_ceiling(kind: str = "compute", seconds_of_work: float = 2.0) -> dict[str, Any]:
    """The machine's own 1 -> 2 process ceiling: one job alone, then two identical ones at once.

    ``T1 / T2`` (T2: the slower of the pair) is what two processes can give here at most (1.0: two full
    cores; about 0.6 when the two vCPUs are SMT siblings on the host, less when other jobs hold the cores
    or, for ``memory``, when one job already takes most of the memory bandwidth); the CPU-seconds a job
    needs alone and in the pair show that contention even under load."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    runs: dict[str, Any] = {}
    for n in (1, 2):
        queue = ctx.Queue()
        jobs = [ctx.Process(target=_compute_job, args=(seconds_of_work, kind, queue)) for _ in range(n)]
        for job in jobs:
            job.start()
        results = [queue.get() for _ in jobs]
        for job in jobs:
            job.join()
        runs[str(n)] = {"wall_s": [round(w, 3) for w, _ in results], "cpu_s": [round(c, 3) for _, c in results]}
    t1, t2 = runs["1"]["wall_s"][0], max(runs["2"]["wall_s"])
    c1, c2 = runs["1"]["cpu_s"][0], sum(runs["2"]["cpu_s"]) / 2
    return {**runs, "efficiency_pct": round(100 * t1 / t2, 1), "cpu_per_job_pair_vs_alone": round(c2 / c1, 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--surveys", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", default="424x240", help="camera resolution WxH of the surveys")
    parser.add_argument("--fps", type=int, default=6)
    parser.add_argument("--views", type=int, default=2, help="orbit views per arm")
    parser.add_argument("--threads", type=int, default=1,
                        help="threads of every library (BLAS, OpenMP, OpenCV, Open3D), the loop's and each Ray task's")
    parser.add_argument("--work", type=Path, default=None, help="keep the surveys here (default: a temp folder)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--no-compare", action="store_true", help="skip the fresh-worker-per-task run")
    parser.add_argument("--only-ray", action="store_true", help="skip the loop (CPU accounting of the Ray runs only)")
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

    ceiling = compute_ceiling("compute")
    ceiling_memory = compute_ceiling("memory")
    loop = None if args.only_ray else process_all(surveys, work / "loop", Executor(), 1, "worker")
    processed_bytes = [folder_bytes(work / ("ray1" if loop is None else "loop") / s.name) for s in surveys]
    ray1 = process_all(surveys, work / "ray1", Executor("ray"), 1)
    ray2 = process_all(surveys, work / "ray2", Executor("ray"), 2)
    fresh1 = None if args.no_compare else process_all(surveys, work / "ray1w", Executor("ray"), 1, "worker")
    processed_bytes = [folder_bytes(work / "ray1" / s.name) for s in surveys] if loop is None else processed_bytes

    def pct(ratio: float) -> float:
        return round(100 * (ratio - 1.0), 1)

    base = loop or ray1
    made = [m for m in make if not m["skipped"]]
    s1, s2 = ray1["surveys"], ray2["surveys"]
    result: dict[str, Any] = {
        "surveys": args.surveys, "cpu_count": os.cpu_count(), "threads": THREADS, "loop_threads": LOOP_THREADS,
        "make": make,
        "make_cpu_s_per_survey": round(sum(m["cpu_s"] for m in made) / len(made), 2) if made else None,
        "survey_bytes_mean": int(sum(m["bytes"] for m in make) / len(make)),
        "processed_bytes_mean": int(sum(processed_bytes) / len(processed_bytes)),
        "process_cpu_s_per_survey": round(base["surveys"]["survey_cpu_s"] / args.surveys, 2),
        "loop_import_s": round(IMPORT_S, 2), "compute_ceiling": ceiling, "memory_ceiling": ceiling_memory,
        "loop": loop, "ray_1_worker": ray1, "ray_2_workers": ray2, "ray_1_fresh_worker_per_task": fresh1,
        "scaling_efficiency_pct": round(100 * ray1["wall_s"] / (2.0 * ray2["wall_s"]), 1),
        # scaling = (surveys' time alone / two at once) x (balance of the workers) x (share of the batch in surveys)
        "scaling_factors": {
            "survey_slowdown_two_at_once": round(s2["survey_wall_s"] / s1["survey_wall_s"], 3),
            "survey_cpu_two_at_once": round(s2["survey_cpu_s"] / s1["survey_cpu_s"], 3),
            "balance": round(s2["survey_wall_s"] / (2 * s2["worker_busy_s"][0]), 3),
            "busy_share_1": round(s1["worker_busy_s"][0] / ray1["wall_s"], 3),
            "busy_share_2": round(s2["worker_busy_s"][0] / ray2["wall_s"], 3)},
    }
    if loop is not None:
        result["ray_overhead_pct"] = pct(ray1["wall_s"] / loop["wall_s"])
        result["ray_overhead_cpu_pct"] = pct(ray1["cpu_s_total"] / loop["cpu_s_total"])
        result["ray_overhead_with_startup_pct"] = pct((ray1["wall_s"] + ray1["ray_init_s"] + ray1["warm_up_s"])
                                                      / (loop["wall_s"] + IMPORT_S))
        result["fresh_worker_overhead_pct"] = None if fresh1 is None else pct(fresh1["wall_s"] / loop["wall_s"])
    report(args, result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)


def report(args: argparse.Namespace, result: dict[str, Any]) -> None:
    """The summary on stdout (everything is in the JSON too)."""
    loop, ray1, ray2, fresh1 = (result[k] for k in ("loop", "ray_1_worker", "ray_2_workers",
                                                   "ray_1_fresh_worker_per_task"))
    print(f"surveys: {args.surveys} ({args.resolution}, {args.fps} fps, {args.views} views per arm), "
          f"{os.cpu_count()} CPUs, {THREADS} thread(s) per survey in every library, loop and Ray "
          f"(loop: {result['loop_threads']}); load averages with each run")
    print(f"make a survey: {result['make_cpu_s_per_survey']} CPU-s, {result['survey_bytes_mean'] / 1e6:.1f} MB; "
          f"process it: {result['process_cpu_s_per_survey']} CPU-s, {result['processed_bytes_mean'] / 1e6:.1f} MB")
    c = result["compute_ceiling"]
    print(f"machine ceiling, 1 -> 2 pure-compute processes: {c['efficiency_pct']} % "
          f"(one alone {c['1']['wall_s'][0]} s, "
          f"two at once {c['2']['wall_s']} s; CPU-s per job in the pair / alone {c['cpu_per_job_pair_vs_alone']})")
    m = result["memory_ceiling"]
    print(f"machine ceiling, 1 -> 2 memory-bound processes: {m['efficiency_pct']} % "
          f"(one alone {m['1']['wall_s'][0]} s, two at once {m['2']['wall_s']} s; CPU-s per job in the pair / alone "
          f"{m['cpu_per_job_pair_vs_alone']})")
    print(f"loop start-up (import darp here): {IMPORT_S:.2f} s")
    for name, r in (("loop", loop), ("ray_1_worker", ray1), ("ray_2_workers", ray2),
                    ("ray_1_fresh_worker_per_task", fresh1)):
        if r is None:
            continue
        sv = r["surveys"]
        print(f"{name:<28} wall {r['wall_s']:7.2f} s  load {r['load_before']} -> {r['load_after']}  "
              f"(ray.init {r['ray_init_s']:.2f} s, warm-up {r['warm_up_s']:.2f} s; start-up CPU "
              f"{sum(r['startup_cpu_s'].values()):.1f} s)")
        print(f"    CPU-s in the batch: {r['cpu_s_total']} = {r['cpu_s']}")
        print(f"    surveys: {sv['survey_wall_s']} s wall, {sv['survey_cpu_s']} CPU-s ({sv['main_thread_cpu_s']} main "
              f"thread + {sv['other_threads_cpu_s']} other threads, up to {sv['threads_max']} threads; process "
              f"{sv['process_cpu_s']}, child before the call {sv['child_cpu_before_call_s']}); workers busy "
              f"{sv['worker_busy_s']} s; Ray's own processes {r['ray_own_cores']} cores; order {sv['order']}")
    if loop is not None:
        print(f"Ray overhead vs plain loop (1 worker, fork per task): {result['ray_overhead_pct']} % wall "
              f"(target <= 5 %), {result['ray_overhead_cpu_pct']} % CPU-s; with both start-ups: "
              f"{result['ray_overhead_with_startup_pct']} %")
        if fresh1 is not None:
            print(f"  a fresh Ray worker per task instead (max_calls=1): {result['fresh_worker_overhead_pct']} %")
    f = result["scaling_factors"]
    print(f"scaling 1 -> 2 workers: efficiency {result['scaling_efficiency_pct']} % (target >= 90 %; this machine's "
          f"pure-compute ceiling {c['efficiency_pct']} %); a survey takes x{f['survey_slowdown_two_at_once']} the wall "
          f"and x{f['survey_cpu_two_at_once']} the CPU with two at once; balance {f['balance']}; share of the batch "
          f"in surveys {f['busy_share_1']} (1 worker) / {f['busy_share_2']} (2)")
    per = (loop or ray1)["wall_s"] / args.surveys
    for name, r in (("fork", ray1), ("fresh worker", fresh1)):
        if r is not None and r["fixed_cost"]:
            cost = r["fixed_cost"]["per_task_s"]
            print(f"fixed cost of a Ray task ({name}): {cost} s per task against {per:.2f} s per survey "
                  f"({100 * cost / per:.1f} %)")


if __name__ == "__main__":
    main()
