"""Benchmark: darp's ROS1 .bag reader against pyrealsense2 playback on the same files.

Writes (in a temporary folder) a 640x480 four-stream recording (depth z16, colour rgb8, infrared 1 and
2 y8 at 30 fps, ~20 metadata entries per frame like a D435) with darp's writer, LZ4 and uncompressed,
in two lengths. Content is random-ish but compressible: a textured, noisy object in front of a flat
background, moving a pixel per frame (LZ4 shrinks it about 2.5x).

Each reader consumes every frame the way a user would: it copies the pixels once into its own buffer
(``np.copyto``); darp hands out zero-copy views, pyrealsense2 frames are wrapped with ``np.asanyarray``.
pyrealsense2 plays back non-real-time, per sensor, into a frame queue (every frame exactly once; the
count is checked). Each configuration runs ``--repeats`` times, interleaved, and the best run is shown
(other processes share this machine). Peak memory is the resident-set high-water mark of
a subprocess that opens a file and iterates all its frames (VmHWM; file pages of the mapping count).

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
from pathlib import Path

import numpy as np

from darp.formats.bag_reader import BagRecording
from darp.formats.bag_writer import BagWriter
from darp.formats.recording_types import DeviceInfo, Intrinsics, StreamProfile

W, H = 640, 480
KEYS = ("depth", "color", "ir1", "ir2")
METADATA = ("Sensor Timestamp", "Actual Exposure", "Gain Level", "Auto Exposure", "Time Of Arrival",
            "Backend Timestamp", "Actual Fps", "Frame Laser Power", "Frame Laser Power Mode", "Exposure Priority",
            "Exposure Roi Left", "Exposure Roi Right", "Exposure Roi Top", "Exposure Roi Bottom",
            "Frame Emitter Mode", "Raw Frame Size", "Gpio Input Data")
TARGETS = {"lz4": 4.0, "none": 15.0}  # darp / pyrealsense2, depth frames per second


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
            metadata = {name: 1000 + i for name in METADATA}
            depth = np.where(np.roll(holes, i, 1), 0, np.roll(depth_mm, i, 1) + 0.7 * n).astype(np.uint16)
            writer.write_image("depth", depth, t_ms, i, metadata=metadata)
            ir = np.where(mask, np.clip(np.roll(texture, i, 1) + 2 * n, 0, 255), 40).astype(np.uint8)
            writer.write_image("ir1", ir, t_ms, i, metadata=metadata)
            writer.write_image("ir2", np.roll(ir, -9, 1), t_ms, i, metadata=metadata)
            rgb = np.where(mask[..., None], np.clip(np.roll(colour, i, 1) + n[..., None], 0, 255), (200, 190, 180))
            writer.write_image("color", rgb.astype(np.uint8), t_ms + 2.1, i, metadata=metadata)
    return path


# -- the readers -------------------------------------------------------------------------------------
def plain_read(path: Path) -> float:
    """Seconds to read the whole file in 8 MiB blocks: the limit for any reader of this file."""
    block = memoryview(bytearray(8 << 20))
    start = time.perf_counter()
    with open(path, "rb", buffering=0) as handle:
        while handle.readinto(block):
            pass
    return time.perf_counter() - start


def darp_read(path: Path, keys: tuple[str, ...], verify: bool = True) -> tuple[int, int, float]:
    """(frames, pixel bytes, seconds) for darp: open, then iterate and copy every frame once."""
    start = time.perf_counter()
    buffers: dict[str, np.ndarray] = {}
    frames = nbytes = 0
    with BagRecording(path, verify_checksums=verify) as recording:
        for frame in recording.iter_frames(keys):
            out = buffers.get(frame.info.stream)
            if out is None:
                out = buffers[frame.info.stream] = np.empty_like(frame.data)
            np.copyto(out, frame.data)
            frames, nbytes = frames + 1, nbytes + frame.data.nbytes
    return frames, nbytes, time.perf_counter() - start


def realsense_read(path: Path, keys: tuple[str, ...]) -> tuple[int, int, float]:
    """(frames, pixel bytes, seconds) for pyrealsense2: load, play non-real-time, copy every frame once."""
    import pyrealsense2 as rs

    wanted = {"depth": (rs.stream.depth, 0), "color": (rs.stream.color, 0), "ir1": (rs.stream.infrared, 1),
              "ir2": (rs.stream.infrared, 2)}
    wanted = {wanted[k] for k in keys}
    start = time.perf_counter()
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
    buffers: dict[tuple, np.ndarray] = {}
    frames = nbytes = 0
    last = start
    while True:
        ok, frame = queue.try_wait_for_frame(250)
        if not ok:
            if player.current_status() == rs.playback_status.stopped:
                break
            continue
        data = np.asanyarray(frame.get_data())
        key = (frame.get_profile().stream_type(), frame.get_profile().stream_index())
        out = buffers.get(key)
        if out is None:
            out = buffers[key] = np.empty_like(data)
        np.copyto(out, data)
        frames, nbytes, last = frames + 1, nbytes + data.nbytes, time.perf_counter()
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    return frames, nbytes, last - start


def darp_index(path: Path) -> tuple[float, float]:
    """Seconds to open (parse the index and description) and then to list every frame's timestamp."""
    start = time.perf_counter()
    with BagRecording(path) as recording:
        opened = time.perf_counter()
        for key in recording.streams:
            recording.timestamps_ms(key)
        return opened - start, time.perf_counter() - opened


def best(runs: list[tuple[int, int, float]]) -> tuple[int, int, float]:
    counts = {(frames, nbytes) for frames, nbytes, _ in runs}
    if len(counts) != 1:
        raise RuntimeError(f"runs disagree on the frames delivered: {counts}")
    return min(runs, key=lambda run: run[2])


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
    """Subprocess entry: open and iterate every frame; print resident-set sizes in MiB as JSON."""
    recording = BagRecording(path)
    after_open = _peak_rss_mib()
    frames, _, _ = darp_read(Path(path), KEYS)
    peak = _peak_rss_mib()
    recording.close()
    print(json.dumps({"frames": frames, "after_open_mib": after_open, "peak_mib": peak}))


def peak_memory(path: Path) -> dict:
    out = subprocess.run([sys.executable, __file__, "--probe", str(path)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


# -- the report --------------------------------------------------------------------------------------
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
    repeats = args.repeats or (1 if args.quick else 3)
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


def speed_table(files: dict, framesets: int, repeats: int) -> None:
    print(f"\nSPEED (short recordings; best of {repeats} runs; MB = 10^6 bytes)")
    print("  frames/s: frames delivered per second, open included")
    print("  payload MB/s: pixel bytes delivered and copied once by the consumer per second")
    print("  file MB/s (plain read): the whole file read in 8 MiB blocks, the ceiling for any reader\n")
    header = f"{'file':18s} {'streams':8s} {'reader':27s} {'frames':>6s} {'frames/s':>9s} {'payload MB/s':>13s} {'vs rs2':>7s}"
    print(header)
    print("-" * len(header))
    summary = {}
    for compression in ("lz4", "none"):
        path = files[compression, framesets]
        size_mb = path.stat().st_size / 1e6
        plain_s = min(plain_read(path) for _ in range(repeats))
        name = f"{compression} {size_mb:.0f} MB"
        print(f"{name:18s} {'-':8s} {'plain read (8 MiB blocks)':27s} {'':>6s} {'':>9s} {size_mb / plain_s:13.0f} "
              f"{'':>7s}  <- file MB/s")
        for label, keys in (("depth", ("depth",)), ("all", KEYS)):
            readers = {"pyrealsense2 2.59 playback": lambda k=keys, p=path: realsense_read(p, k),
                       "darp": lambda k=keys, p=path: darp_read(p, k)}
            if compression == "lz4":
                readers["darp, no LZ4 checksum"] = lambda k=keys, p=path: darp_read(p, k, verify=False)
            runs: dict[str, list] = {r: [] for r in readers}
            for _ in range(repeats):  # interleaved, so that both readers see the same machine load
                for reader, run in readers.items():
                    runs[reader].append(run())
            results = {reader: best(r) for reader, r in runs.items()}
            rs_fps = results["pyrealsense2 2.59 playback"][0] / results["pyrealsense2 2.59 playback"][2]
            for reader, (frames, nbytes, seconds) in results.items():
                fps = frames / seconds
                print(f"{name:18s} {label:8s} {reader:27s} {frames:6d} {fps:9.0f} {nbytes / seconds / 1e6:13.0f} "
                      f"{fps / rs_fps:6.2f}x")
                summary[compression, label, reader] = (fps, fps / rs_fps, nbytes / seconds / 1e6, size_mb / plain_s)
    for compression in ("lz4", "none"):
        opened, listed = min(darp_index(files[compression, framesets]) for _ in range(repeats))
        print(f"darp {compression}: open (index + description) {opened * 1e3:.0f} ms; then timestamps of all "
              f"{4 * framesets} frames (lazy frame table, one pass over the chunks) {listed * 1e3:.0f} ms")
    print("\nTARGETS")
    for compression, target in TARGETS.items():
        _, ratio, _, _ = summary[compression, "depth", "darp"]
        print(f"  {compression:4s} depth frames/s darp / pyrealsense2 = {ratio:.2f}x (target >= {target:g}x: "
              f"{'met' if ratio >= target else 'missed'})")
    _, _, payload, plain = summary["none", "all", "darp"]
    print(f"  none all-stream payload MB/s / plain read MB/s = {payload / plain:.0%} (target >= 50%: "
          f"{'met' if payload >= 0.5 * plain else 'missed'})")


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
