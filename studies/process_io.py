#!/usr/bin/env python3
"""What processing one survey reads and touches, stage by stage (``darp process --truth-poses``'s stages).

Per stage (and for opening the survey): CPU-seconds of the process (all threads), wall, bytes of the
survey's bags brought into the page cache (``fincore`` after evicting the bags with
``POSIX_FADV_DONTNEED`` before the run, so this is what the stage read from the bags, read-ahead
included), the process's ``read_chars`` / ``read_bytes`` (psutil: ``read()`` calls and block I/O; a bag
is read through ``mmap``, which ``read_chars`` does not count), page faults, the stage's peak RSS
(``/proc/self/clear_refs`` resets it between stages), and the reader's work: messages whose header was
parsed for the frame table, frames streamed (``iter_frames``) and read at random (``read_frame``) per
stream with their payload bytes, LZ4 chunks decoded. ``--hash`` prints the sha256 of every output
(``results.json`` and ``stages.json`` without their timings), to check that a change to the reader leaves
the outputs byte-identical.

    .venv/bin/python studies/process_io.py [SURVEY ...] [--out DIR] [--warm] [--json out.json] [--hash]

Without a survey it makes one tiny twin survey (424x240, 6 fps, 2 views per arm) in a temporary folder.

The modules a Ray worker's forkserver preloads (``darp.batch.fresh.PRELOAD``) are imported first, so
the figures are a survey's own, as in a batch. Wall-clock figures are only meaningful on an idle
machine; CPU-seconds and bytes are the robust ones.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

if __name__ == "__main__":  # one thread per library, set before numpy loads (not when a test imports this)
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.update(dict.fromkeys(("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"), "1"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import psutil

from darp.batch.threads import limit_threads
from darp.formats.realsense.bag import reader as bag_reader
from darp.formats.realsense.bag.chunks import ChunkStore

COUNTS: Counter[str] = Counter()


def _install_counters() -> None:
    """Count the reader's work: frame-table messages, streamed and random-access frames, LZ4 decodes."""
    cls = bag_reader.BagRecording
    table, stream, read, decode = cls._frame_table, cls.iter_frames, cls.read_frame, ChunkStore._decode

    def frame_table(self: Any, keys: list[str]) -> Any:
        before = set(self._tables)
        out = table(self, keys)
        for key in set(out) - before:
            COUNTS[f"table messages {key}"] += int(self._data[key].size)
        return out

    def iter_frames(self: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
        for frame in stream(self, *args, **kwargs):
            COUNTS[f"streamed {frame.info.stream}"] += 1
            COUNTS["streamed payload bytes"] += int(frame.data.nbytes)
            yield frame

    def read_frame(self: Any, key: str, index: int) -> Any:
        frame = read(self, key, index)
        COUNTS[f"read_frame {key}"] += 1
        COUNTS["read_frame payload bytes"] += int(frame.data.nbytes)
        return frame

    def lz4(self: Any, number: int) -> Any:
        COUNTS["lz4 chunks decoded"] += 1
        return decode(self, number)

    cls._frame_table, cls.iter_frames, cls.read_frame = frame_table, iter_frames, read_frame  # type: ignore[method-assign]
    ChunkStore._decode = lz4  # type: ignore[method-assign]


def bags(survey: Path) -> list[Path]:
    return sorted(survey.glob("*.bag"))


def evict(paths: list[Path]) -> None:
    """Drop the files' pages from the page cache (clean pages nobody maps)."""
    for path in paths:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def cached_bytes(paths: list[Path]) -> int:
    """Bytes of the files resident in the page cache (util-linux ``fincore``)."""
    if not paths or shutil.which("fincore") is None:
        return -1
    out = subprocess.run(["fincore", "--bytes", "--noheadings", "--raw", "-o", "RES", *map(str, paths)],
                         capture_output=True, text=True, check=True, env=dict(os.environ)).stdout
    return sum(int(v) for v in out.split())


def reset_peak_rss() -> None:
    with contextlib.suppress(OSError), open("/proc/self/clear_refs", "w") as handle:
        handle.write("5")


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return -1.0


class Meter:
    """Counters of this process between two points."""

    def __init__(self, files: list[Path]) -> None:
        self.files, self.proc = files, psutil.Process()

    def read(self) -> dict[str, float]:
        r, io = resource.getrusage(resource.RUSAGE_SELF), self.proc.io_counters()
        return {"cpu_s": r.ru_utime + r.ru_stime, "wall_s": time.perf_counter(), "read_chars": io.read_chars,
                "read_bytes": io.read_bytes, "minflt": r.ru_minflt, "majflt": r.ru_majflt,
                "bag_cached_bytes": cached_bytes(self.files), **{k: float(v) for k, v in COUNTS.items()}}

    @contextlib.contextmanager
    def measure(self, into: dict[str, Any], name: str) -> Iterator[None]:
        reset_peak_rss()
        before = self.read()
        try:
            yield
        finally:
            after = self.read()
            row = {k: round(after[k] - before.get(k, 0.0), 3) for k in after}
            row["peak_rss_mb"] = round(peak_rss_mb(), 1)
            into[name] = {k: v for k, v in row.items() if v}


def process(survey: Path, out: Path, warm: bool) -> dict[str, Any]:
    from darp.processing import batch as processing_batch
    from darp.processing.settings import ProcessSettings

    files = bags(survey)
    if warm:
        for path in files:
            with open(path, "rb") as handle:
                while handle.read(1 << 24):
                    pass
    else:
        evict(files)
    meter, rows = Meter(files), {}
    stages = processing_batch.PROCESS_STAGES

    def wrapped(stage: Any) -> Any:
        def run(job: Any) -> Any:
            with meter.measure(rows, stage.name):
                return stage.run(job)
        return dataclasses.replace(stage, run=run)

    processing_batch.PROCESS_STAGES = tuple(wrapped(s) for s in stages)
    total: dict[str, Any] = {}
    try:
        with meter.measure(total, "survey"):
            processing_batch.process_folder(survey, out, None, settings=ProcessSettings(), truth_poses=True)
    finally:
        processing_batch.PROCESS_STAGES = stages
    staged = {k: sum(r.get(k, 0) for r in rows.values()) for k in ("cpu_s", "wall_s")}
    rows["open and close (outside the stages)"] = {k: round(total["survey"].get(k, 0) - staged[k], 3)
                                                   for k in staged}
    return {"survey": survey.name, "bags_bytes": sum(p.stat().st_size for p in files), "warm": warm,
            "stages": rows, "total": total["survey"]}


def strip_timings(value: Any) -> Any:
    """A JSON document without its timing fields (stages' ``seconds``; results.json's ``stages``: names kept)."""
    if isinstance(value, dict):
        return {k: sorted(v) if k == "stages" and all(isinstance(x, (int, float, type(None))) for x in v.values())
                else strip_timings(v) for k, v in value.items() if k not in ("seconds", "timings", "created")}
    if isinstance(value, list):
        return [strip_timings(v) for v in value]
    return value


def output_hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (JSON documents without their timings)."""
    hashes = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        data = path.read_bytes()
        if path.suffix == ".json":
            data = json.dumps(strip_timings(json.loads(data)), sort_keys=True).encode()
        hashes[str(path.relative_to(folder))] = hashlib.sha256(data).hexdigest()
    return hashes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("surveys", nargs="*", type=Path,
                        help="survey folders (default: one tiny twin survey made in a temporary folder)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary one)")
    parser.add_argument("--warm", action="store_true", help="read the bags into the page cache first (default: evict)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--hash", action="store_true", help="print the sha256 of every output (timings stripped)")
    args = parser.parse_args()
    limit_threads(1)
    import importlib

    from darp.batch.fresh import PRELOAD

    for module in PRELOAD:  # as a Ray worker's forkserver does: a survey's CPU without darp's lazy imports
        importlib.import_module(module)
    _install_counters()
    work = Path(tempfile.mkdtemp(prefix="darp-process-io-"))
    if args.out is None:
        args.out = work / "processed"
    if not args.surveys:  # without arguments: a tiny twin survey
        from darp.batch.generate import plan_surveys, record_generated

        (spec,) = plan_surveys(1, 0, ["mug"], views=2, fps=6, width=424, height=240)
        record_generated(spec, str(work / "surveys"))
        args.surveys = [work / "surveys" / spec.name]
    results = []
    for survey in args.surveys:
        out = args.out / survey.name
        shutil.rmtree(out, ignore_errors=True)
        COUNTS.clear()
        result = process(survey, out, args.warm)
        if args.hash:
            result["sha256"] = output_hashes(out)
        results.append(result)
        print(f"{survey.name}: bags {result['bags_bytes'] / 1e6:.1f} MB")
        for name, row in {**result["stages"], "total": result["total"]}.items():
            print(f"  {name}: " + ", ".join(f"{k} {v:g}" for k, v in row.items()))
        for name, digest in result.get("sha256", {}).items():
            print(f"  sha256 {digest[:16]} {name}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    shutil.rmtree(work, ignore_errors=True)  # only what this run made (a default survey or output)


if __name__ == "__main__":
    main()
