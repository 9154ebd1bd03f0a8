#!/usr/bin/env python3
"""Run every peer benchmark and write ONE results table: ``make bench``.

Each benchmark (``BENCHMARKS``) runs in its own child interpreter (its thread settings and imports stay its
own, and a crash is a row, not the end of the run) with the small defaults of its ``rows()``; the child
hands its rows back as JSON in a file. Rows (case, darp, peer, ratio, target, verdict) and the machine go
to ``.bench/results.md`` and ``.bench/results.json`` (written atomically after every benchmark, so a run
cut short keeps what it measured); each benchmark's own report goes to ``.bench/logs/<name>.log``. The
table is printed at the end. Exit status 1 when a benchmark failed (a target not met is a result, not a
failure).

    .venv/bin/python benchmarks/run.py [--only kinematics,fusion] [--out .bench]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from results import Row, machine, markdown, write  # noqa: E402  (benchmarks/results.py)

# the peer benchmarks and their peers, cheapest first; the other scripts here are this runner and its results module
BENCHMARKS = {"kinematics": "Pinocchio", "db3_read": "pyrealsense2", "bag_read": "pyrealsense2",
              "twin_camera": "MuJoCo's ray caster and the facts' timings", "fusion": "Open3D's TSDF and libigl",
              "viewpoints": "the paper's fixed orbit", "handeye": "OpenCV's hand-eye methods",
              "calibration": "OpenCV's hand-eye and robot-world solvers",
              "real_fusion": "Open3D's VoxelBlockGrid TSDF on real depth"}


def load(name: str, folder: Path = HERE) -> ModuleType:
    """``<folder>/<name>.py`` as a module (not run as a script)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", folder / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


def child(name: str, rows_file: Path, folder: Path) -> None:
    """In the child: the benchmark's rows, as JSON records, into ``rows_file``."""
    rows: list[Row] = load(name, folder).rows()
    rows_file.write_text(json.dumps([r.record() for r in rows]))


def run_one(name: str, logs: Path, folder: Path = HERE) -> tuple[list[Row], float]:
    """``<folder>/<name>.py``'s rows, made in a child interpreter; its report into ``logs/<name>.log``; a failure
    (an exception, a crash, no rows) becomes one error row."""
    logs.mkdir(parents=True, exist_ok=True)
    rows_file = logs / f"{name}.rows.json"
    rows_file.unlink(missing_ok=True)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    t0 = time.perf_counter()
    with open(logs / f"{name}.log", "w") as log:
        done = subprocess.run([sys.executable, __file__, "--child", name, str(rows_file), str(folder)], stdout=log,
                              stderr=subprocess.STDOUT, env=env, check=False)
    seconds = time.perf_counter() - t0
    if done.returncode == 0 and rows_file.is_file():
        rows = [Row.from_record(r) for r in json.loads(rows_file.read_text())]
        rows_file.unlink()
        return rows, seconds
    tail = (logs / f"{name}.log").read_text(errors="replace").strip().splitlines()[-1:] or ["no output"]
    return [Row(name, "run", "", None, error=f"exit {done.returncode}: {tail[0][:200]}")], seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=None, help="comma-separated benchmarks (default: all)")
    parser.add_argument("--out", type=Path, default=ROOT / ".bench", help="folder of the results table")
    parser.add_argument("--child", nargs=3, metavar=("NAME", "ROWS_JSON", "FOLDER"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.child[0], Path(args.child[1]), Path(args.child[2]))
        return 0
    names = tuple(BENCHMARKS) if args.only is None else tuple(n.strip() for n in args.only.split(",") if n.strip())
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHMARKS)}")
    info = machine()
    rows: list[Row] = []
    runs: dict[str, dict[str, object]] = {}
    started = time.perf_counter()
    for k, name in enumerate(names, 1):
        print(f"[{k}/{len(names)}] {name} (darp vs {BENCHMARKS[name]}) ...", end=" ", flush=True)
        got, seconds = run_one(name, args.out / "logs", HERE)
        rows += got
        runs[name] = {"seconds": round(seconds, 1), "rows": len(got), "log": str(args.out / "logs" / f"{name}.log")}
        md, js = write(args.out, rows, info, runs)  # after every benchmark: a run cut short keeps its rows
        failed = [r.error for r in got if r.error]
        print(f"{seconds:.0f} s, {len(got)} rows" + (f", FAILED: {failed[0]}" if failed else ""), flush=True)
    print()
    print(markdown(rows, info, runs))
    print(f"{len(names)} benchmarks in {time.perf_counter() - started:.0f} s; table: {md} and {js}; "
          f"each benchmark's report: {args.out / 'logs'}")
    return 1 if any(r.error for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
