"""Benchmark: darp's ROS1 .bag reader against pyrealsense2 playback on the same files.

Writes (in a temporary folder) a 640x480 four-stream recording (depth z16, colour rgb8, infrared 1 and
2 y8 at 30 fps, ~20 metadata entries per frame like a D435) with darp's writer, LZ4 and uncompressed
(768 KiB chunks, as librealsense's recorder), in two lengths. Content is random-ish but compressible: a
textured, noisy object in front of a flat background, moving a pixel per frame (LZ4: about 2.7x).

Both readers hand frames to the same consumer, in one of two modes:

- ``copy``: the consumer copies every pixel once into its own buffer (``np.copyto``): a consumer that
  uses all the data. darp's frames are zero-copy views (into the file mapping or a decoded chunk), so
  here darp pays for bringing the pixels in; pyrealsense2 has already copied them into its frames.
- ``view``: the consumer reads one pixel per frame: the cost of the readers themselves.

pyrealsense2 plays back non-real-time, per sensor, into a frame queue, with ``np.asanyarray`` on each
frame's data; the frame numbers each reader delivers are checked: every frame exactly once, in order.
Each configuration runs ``--repeats`` times, interleaved; the best wall time and the least CPU time
(user + system of the whole process, all threads) are shown, with the load average, because this
machine is shared (also per configuration: the 1-minute load average right after its runs). TARGETS gives
a verdict for every file, frames read (depth only, and all four streams: what DARP's pipeline reads) and
consumer mode: darp at least TARGET_RATIO times pyrealsense2's frames/s; and one for the plain-read share:
an all-stream copy of the uncompressed file at least PLAIN_READ_SHARE of a plain read's bandwidth. Peak
memory is the resident-set high-water mark of a subprocess that opens a file and iterates all its frames
(VmHWM; file pages of the mapping count).

    .venv/bin/python benchmarks/bag_read.py [--quick] [--framesets N] [--repeats R]
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
from collections.abc import Callable
from pathlib import Path

import numpy as np

from darp.formats.realsense.bag.reader import BagRecording
from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.rosbag1.lz4 import native
from darp.formats.realsense.types import DeviceInfo, Intrinsics, StreamProfile
from results import Row, Target, row

W, H = 640, 480
KEYS = ("depth", "color", "ir1", "ir2")
METADATA = ("Sensor Timestamp", "Actual Exposure", "Gain Level", "Auto Exposure", "Time Of Arrival",
            "Backend Timestamp", "Actual Fps", "Frame Laser Power", "Frame Laser Power Mode", "Exposure Priority",
            "Exposure Roi Left", "Exposure Roi Right", "Exposure Roi Top", "Exposure Roi Bottom",
            "Frame Emitter Mode", "Raw Frame Size", "Gpio Input Data")
TARGET_RATIO = 2.0  # darp / pyrealsense2 2.59 frames/s (wall), in every file, streams read and consumer mode
PLAIN_READ_SHARE = 0.5  # darp's all-stream payload MB/s (uncompressed, copy) / a plain read's MB/s
READS = {"depth": "depth only", "all": "all four streams"}  # what the DARP pipeline reads: all four
RS2 = "pyrealsense2 2.59 playback"
FILES = {"lz4": "LZ4", "none": "uncompressed"}  # the results table's names of the two recordings


# -- the recording --------------------------------------------------------------------------------
def write_recording(path: Path, compression: str, framesets: int, seed: int = 0) -> Path:
    intr = Intrinsics(W, H, 615.0, 615.0, 319.5, 239.5)
    streams = [StreamProfile("depth", "Depth", 0, 0, "z16", 30, W, H, intr),
               StreamProfile("ir1", "Infrared", 1, 0, "y8", 30, W, H, intr),
               StreamProfile("ir2", "Infrared", 2, 0, "y8", 30, W, H, intr),
               StreamProfile("color", "Color", 0, 1, "rgb8", 30, W, H, intr)]
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    inside = ((x - 320) / 200) ** 2 + ((y - 260) / 150) ** 2 < 1
    depth_mm = np.where(inside, 700 + 80 * np.cos((x - 320) / 60) * np.cos((y - 260) / 50), 1500 + 0.3 * x)
    holes = (np.sin(x / 23.0) * np.cos(y / 17.0) > 0.9) & inside
    texture = rng.integers(0, 255, (H // 4, W // 4)).repeat(4, 0).repeat(4, 1).astype(np.float32)
    texture = (texture + np.roll(texture, 2, 0) + np.roll(texture, 2, 1) + np.roll(texture, 1, (0, 1))) / 4
    colour = np.stack([texture, np.roll(texture, 3, 1), np.roll(texture, 5, 0)], -1)
    noise = rng.normal(0, 1, (4, H, W)).astype(np.float32)
    device = DeviceInfo("Intel RealSense D435", "348522076490", "5.13.0.50", "0B07")
    with BagWriter(path, device, streams, compression=compression, overwrite=True) as writer:
        for i in range(framesets):
            t_ms, n = 1_700_000_000_000.0 + 33.333 * i, noise[i % 4]
            mask = np.roll(inside, i, 1)
            metadata = dict.fromkeys(METADATA, 1000 + i)
            depth = np.where(np.roll(holes, i, 1), 0, np.roll(depth_mm, i, 1) + 0.7 * n).astype(np.uint16)
            writer.write_image("depth", depth, t_ms, i, metadata=metadata)
            ir = np.where(mask, np.clip(np.roll(texture, i, 1) + 2 * n, 0, 255), 40).astype(np.uint8)
            writer.write_image("ir1", ir, t_ms, i, metadata=metadata)
            writer.write_image("ir2", np.roll(ir, -9, 1), t_ms, i, metadata=metadata)
            rgb = np.where(mask[..., None], np.clip(np.roll(colour, i, 1) + n[..., None], 0, 255), (200, 190, 180))
            writer.write_image("color", rgb.astype(np.uint8), t_ms + 2.1, i, metadata=metadata)
    return path


# -- the readers -------------------------------------------------------------------------------------
class Run:
    """One timed read: frames and pixel bytes delivered, wall and CPU seconds (whole process, all threads),
    and the frame numbers delivered per stream (checked against the recording). The consumer's own
    bookkeeping per frame is the same for both readers (a list append and a vDSO clock read)."""

    def __init__(self) -> None:
        self.frames = self.nbytes = 0
        self.numbers: dict[str, list[int]] = {}
        self._buffers: dict[str, np.ndarray] = {}
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        self.wall_s = self.cpu_s = 0.0

    def consume(self, key: str, number: int, data: np.ndarray, copy: bool) -> None:
        """What the benchmark's consumer does with a frame: copy every pixel once, or read one pixel."""
        if copy:
            out = self._buffers.get(key)
            if out is None:
                out = self._buffers[key] = np.empty_like(data)
            np.copyto(out, data)
        else:
            data.flat[-1]
        self.numbers.setdefault(key, []).append(number)
        self.frames, self.nbytes = self.frames + 1, self.nbytes + data.nbytes
        self.wall_s = time.perf_counter() - self._t0

    def finish(self, wall_to_now: bool = True) -> Run:
        """Stop the clocks: wall time up to now (or to the last frame delivered), CPU time up to now."""
        if wall_to_now:
            self.wall_s = time.perf_counter() - self._t0
        self.cpu_s = time.process_time() - self._c0
        return self


def plain_read(path: Path) -> Run:
    """The whole file read in 8 MiB blocks: the limit for any reader of this file."""
    run, block = Run(), memoryview(bytearray(8 << 20))
    with open(path, "rb", buffering=0) as handle:
        while handle.readinto(block):
            pass
    return run.finish()


def darp_read(path: Path, keys: tuple[str, ...], copy: bool, **options) -> Run:
    """darp: open, then stream every frame of ``keys`` to the consumer."""
    run = Run()
    with BagRecording(path, **options) as recording:
        for frame in recording.iter_frames(keys):
            run.consume(frame.info.stream, frame.info.frame_number, frame.data, copy)
    return run.finish()


def realsense_read(path: Path, keys: tuple[str, ...], copy: bool) -> Run:
    """pyrealsense2: load, play non-real-time per sensor into a frame queue, consume every frame."""
    import pyrealsense2 as rs

    names = {(rs.stream.depth, 0): "depth", (rs.stream.color, 0): "color", (rs.stream.infrared, 1): "ir1",
             (rs.stream.infrared, 2): "ir2"}
    wanted = {k for k, name in names.items() if name in keys}
    run = Run()
    device = rs.context().load_device(str(path))
    player = device.as_playback()
    player.set_real_time(False)
    player.pause()
    queue = rs.frame_queue(1 << 20, keep_frames=True)
    sensors = []
    for sensor in device.query_sensors():
        chosen = [p for p in sensor.get_stream_profiles() if (p.stream_type(), p.stream_index()) in wanted]
        if chosen:
            sensor.open(chosen)
            sensor.start(queue)
            sensors.append(sensor)
    player.resume()
    while True:
        ok, frame = queue.try_wait_for_frame(250)
        if not ok:
            if player.current_status() == rs.playback_status.stopped:
                break
            continue
        profile = frame.get_profile()
        key = names[profile.stream_type(), profile.stream_index()]
        run.consume(key, frame.get_frame_number(), np.asanyarray(frame.get_data()), copy)
    run.finish(wall_to_now=False)  # wall time up to the last frame delivered, not the end-of-file wait
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    return run


def darp_index(path: Path) -> tuple[float, float]:
    """Seconds to open (parse the index and description) and then to list every frame's timestamp."""
    start = time.perf_counter()
    with BagRecording(path) as recording:
        opened = time.perf_counter()
        for key in recording.streams:
            recording.timestamps_ms(key)
        return opened - start, time.perf_counter() - opened


def check(runs: list[Run], keys: tuple[str, ...], framesets: int, reader: str) -> None:
    """Every frame of every stream read exactly once, in order (the writer numbers frame sets 0, 1, ...)."""
    for run in runs:
        for key in keys:
            if run.numbers.get(key) != list(range(framesets)):
                got = run.numbers.get(key, [])
                raise RuntimeError(f"{reader}: stream {key} delivered {len(got)} frames, {len(set(got))} distinct, "
                                   f"expected 0..{framesets - 1} once each")


# -- peak memory in a subprocess ---------------------------------------------------------------------
def _peak_rss_mib() -> float:
    """This process's resident-set high-water mark. Linux's VmHWM belongs to the process image; ru_maxrss
    would also count the parent's memory at fork time."""
    try:
        with open("/proc/self/status") as status:
            return next(int(line.split()[1]) for line in status if line.startswith("VmHWM")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def probe(path: str) -> None:
    """Subprocess entry: open and iterate (copying) every frame; print resident-set sizes in MiB as JSON."""
    recording = BagRecording(path)
    after_open = _peak_rss_mib()
    run = darp_read(Path(path), KEYS, copy=True)
    peak = _peak_rss_mib()
    recording.close()
    print(json.dumps({"frames": run.frames, "after_open_mib": after_open, "peak_mib": peak}))


def peak_memory(path: Path) -> dict:
    out = subprocess.run([sys.executable, __file__, "--probe", str(path)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


# -- the report --------------------------------------------------------------------------------------
def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} CPUs"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="short recordings, one run each (a smoke test)")
    parser.add_argument("--framesets", type=int, default=None, help="frame sets in the short recording")
    parser.add_argument("--repeats", type=int, default=None, help="runs per configuration (best is shown)")
    parser.add_argument("--probe", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.probe:
        probe(args.probe)
        return
    framesets = args.framesets or (60 if args.quick else 240)
    repeats = args.repeats or (1 if args.quick else 5)
    print(f"{load()}; LZ4 decoding: {'native (python-lz4 library via ctypes)' if native() else 'python-lz4 API'}")
    with tempfile.TemporaryDirectory(prefix="darp-bag-bench-") as tmp:
        files = {}
        t0 = time.perf_counter()
        for compression in ("lz4", "none"):
            for length in (framesets, 3 * framesets):
                path = Path(tmp) / f"{compression}_{length}.bag"
                files[compression, length] = write_recording(path, compression, length)
        print(f"wrote 4 recordings in {time.perf_counter() - t0:.1f} s ({W}x{H}, depth+colour+IR1+IR2, 30 fps); "
              f"short: {framesets} frame sets, long: {3 * framesets}")
        speed_table(files, framesets, repeats)
        memory_table(files, framesets)
    print(f"\n{load()}")


def _readers(compression: str, keys: tuple[str, ...], copy: bool, path: Path) -> dict[str, Callable[[], Run]]:
    readers = {RS2: lambda: realsense_read(path, keys, copy), "darp": lambda: darp_read(path, keys, copy)}
    if compression == "lz4":  # decode threads and checksums concern LZ4 chunks only
        readers["darp, no decode threads"] = lambda: darp_read(path, keys, copy, decode_threads=0)
        readers["darp, no LZ4 checksum"] = lambda: darp_read(path, keys, copy, verify_checksums=False)
    return readers


def speed_table(files: dict, framesets: int, repeats: int) -> dict:
    """Print the speed table and the targets' verdicts; returns the summary they are made from."""
    print(f"\nSPEED (short recordings; best of {repeats} interleaved runs; MB = 10^6 bytes; {load()})")
    print("  frames/s: frames delivered per second of wall time, open included")
    print("  CPU ms/frame: least CPU time (user + system, all threads of the process) per frame")
    print("  payload MB/s: pixel bytes delivered per second of wall time")
    print("  vs rs2: frames/s ratio to pyrealsense2 in the same mode (CPU: CPU-time ratio)")
    print("  load: 1-minute load average right after the configuration's runs (the machine is shared)\n")
    header = (f"{'file':14s} {'streams':7s} {'mode':5s} {'reader':26s} {'frames':>6s} {'frames/s':>9s} "
              f"{'CPU ms/fr':>9s} {'MB/s':>6s} {'vs rs2':>7s} {'CPU':>6s} {'load':>5s}")
    print(header)
    print("-" * len(header))
    summary = {}
    for compression in ("lz4", "none"):
        path = files[compression, framesets]
        size_mb = path.stat().st_size / 1e6
        plain = [plain_read(path) for _ in range(repeats)]
        plain_s, plain_cpu = min(r.wall_s for r in plain), min(r.cpu_s for r in plain)
        name = f"{compression} {size_mb:.0f} MB"
        summary[compression, "plain"] = (size_mb / plain_s, size_mb / plain_cpu)
        print(f"{name:14s} {'-':7s} {'-':5s} {'plain read, 8 MiB blocks':26s} {'':>6s} {'':>9s} "
              f"{plain_cpu * 1e3:7.0f}ms {size_mb / plain_s:6.0f}   <- file MB/s (CPU: whole file)")
        for label, keys in (("depth", ("depth",)), ("all", KEYS)):
            for mode in ("copy", "view"):
                readers = _readers(compression, keys, mode == "copy", path)
                runs: dict[str, list[Run]] = {r: [] for r in readers}
                for _ in range(repeats):  # interleaved, so that every reader sees the same machine load
                    for reader, read in readers.items():
                        runs[reader].append(read())
                for reader, reader_runs in runs.items():
                    check(reader_runs, keys, framesets, reader)
                rs_wall = min(r.wall_s for r in runs[RS2])
                rs_cpu = min(r.cpu_s for r in runs[RS2])
                load_1min = os.getloadavg()[0]
                for reader, reader_runs in runs.items():
                    frames, nbytes = reader_runs[0].frames, reader_runs[0].nbytes
                    wall, cpu = min(r.wall_s for r in reader_runs), min(r.cpu_s for r in reader_runs)
                    print(f"{name:14s} {label:7s} {mode:5s} {reader:26s} {frames:6d} {frames / wall:9.0f} "
                          f"{cpu / frames * 1e3:9.3f} {nbytes / wall / 1e6:6.0f} {rs_wall / wall:6.2f}x "
                          f"{rs_cpu / cpu:5.2f}x {load_1min:5.2f}")
                    summary[compression, label, mode, reader] = (rs_wall / wall, nbytes / wall / 1e6,
                                                                 nbytes / cpu / 1e6, rs_cpu / cpu, load_1min)
                    summary[compression, label, mode, reader, "frames/s"] = frames / wall
            print()
    for compression in ("lz4", "none"):
        opened, listed = min(darp_index(files[compression, framesets]) for _ in range(repeats))
        print(f"darp {compression}: open (index + description) {opened * 1e3:.1f} ms; then timestamps of all "
              f"{4 * framesets} frames (frame table, one pass over the chunks) {listed * 1e3:.0f} ms")
    print_targets(summary)
    return summary


def print_targets(summary: dict) -> None:
    """One verdict per (file, frames read, consumer) against TARGET_RATIO: the depth-only read and the
    all-four-streams read (what DARP's pipeline does: keyframes export colour, depth and both IRs); then the
    plain-read share of the uncompressed all-stream copy."""
    print(f"\nTARGETS (darp with its defaults >= {TARGET_RATIO:g}x pyrealsense2 2.59 in every mode; an all-stream copy "
          f">= {PLAIN_READ_SHARE:.0%} of a plain read's bandwidth; {load()})")
    print("  target measure: frames/s ratio, wall time, open included; CPU-time ratio for reference only")
    header = (f"  {'file':5s} {'frames read':17s} {'consumer':8s} {'darp/rs2 wall':>13s} {'target':>7s} "
              f"{'verdict':8s} {'(CPU ratio)':>11s} {'load':>5s}")
    print(header)
    met = total = 0
    for compression in ("lz4", "none"):
        for label, read in READS.items():
            for mode in ("copy", "view"):
                ratio, _, _, cpu_ratio, load_1min = summary[compression, label, mode, "darp"]
                ok = ratio >= TARGET_RATIO
                met, total = met + ok, total + 1
                print(f"  {compression:5s} {read:17s} {mode:8s} {ratio:12.2f}x {'>= ' + f'{TARGET_RATIO:g}x':>7s} "
                      f"{'met' if ok else 'MISSED':8s} {cpu_ratio:10.2f}x {load_1min:5.2f}")
    _, payload, payload_cpu, _, load_1min = summary["none", "all", "copy", "darp"]
    plain, plain_cpu = summary["none", "plain"]
    ok = payload >= PLAIN_READ_SHARE * plain
    met, total = met + ok, total + 1
    print(f"  none  all four streams  copy     payload {payload:.0f} MB/s = {payload / plain:.1%} of a plain "
          f"read's {plain:.0f} MB/s (target >= {PLAIN_READ_SHARE:.0%}: {'met' if ok else 'MISSED'}); "
          f"per CPU second: {payload_cpu / plain_cpu:.1%}; load {load_1min:.2f}")
    print(f"  {met} of {total} targets met")


def rows(framesets: int = 120, repeats: int = 3) -> list[Row]:
    """The results table's rows: every target of :func:`print_targets` (frames/s against pyrealsense2, and the
    plain-read share), on the short recordings only (the long ones serve the memory table)."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with tempfile.TemporaryDirectory(prefix="darp-bag-bench-") as tmp:
        files = {(c, framesets): write_recording(Path(tmp) / f"{c}_{framesets}.bag", c, framesets)
                 for c in ("lz4", "none")}
        summary = speed_table(files, framesets, repeats)
    out = []
    ratio_target = Target("ratio", ">=", TARGET_RATIO, "bag_read.py TARGET_RATIO")
    for compression in ("lz4", "none"):
        for label, read in READS.items():
            for mode in ("copy", "view"):
                out.append(row("bag_read", f"{FILES[compression]} bag, {read}, consumer {mode}", "frames/s",
                               summary[compression, label, mode, "darp", "frames/s"],
                               summary[compression, label, mode, RS2, "frames/s"], RS2, ratio_target))
    _, payload, _, _, _ = summary["none", "all", "copy", "darp"]
    plain, _ = summary["none", "plain"]
    out.append(row("bag_read", "uncompressed bag, all four streams, consumer copy: payload vs plain read", "MB/s",
                   payload, plain, "plain read, 8 MiB blocks", Target("ratio", ">=", PLAIN_READ_SHARE,
                                                                     "bag_read.py PLAIN_READ_SHARE")))
    return out


def memory_table(files: dict, framesets: int) -> None:
    print("\nPEAK MEMORY (subprocess: open, then iterate and copy every frame of all streams; peak resident set)")
    print(f"{'file':26s} {'frames':>7s} {'after open MiB':>15s} {'peak MiB':>9s}")
    for compression in ("lz4", "none"):
        for length in (framesets, 3 * framesets):
            path = files[compression, length]
            m = peak_memory(path)
            name = f"{compression}, {length} frame sets, {path.stat().st_size / 1e6:.0f} MB"
            print(f"{name:26s} {m['frames']:7d} {m['after_open_mib']:15.0f} {m['peak_mib']:9.0f}")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
