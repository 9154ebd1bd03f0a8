#!/usr/bin/env python3
"""Read speed of darp's ROS2 .db3 reader against pyrealsense2's own playback (the peer).

Records a VGA D435-like .db3 (depth, colour, IR1, IR2; smooth depth with noise, textured images) with
librealsense's recorder, PNG-compressed (its default) and uncompressed, then decodes every frame with
both. Prints frames per second for darp and pyrealsense2, and their ratio.

    .venv/bin/python benchmarks/db3_read.py [--frames 60]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # for the tests' helpers package

from results import Row, row

W, H = 640, 480


def record(path: Path, frames: int, compress: bool) -> None:
    import pyrealsense2 as rs

    dev = rs.software_device()
    stereo, rgb = dev.add_sensor("Stereo Module"), dev.add_sensor("RGB Camera")

    def add(sensor, stream, index, uid, fmt, bpp):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = stream, index, uid, W, H, 30, bpp, fmt
        i = rs.intrinsics()
        i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = W, H, 615.0, 615.0, 319.5, 239.5
        vs.intrinsics = i
        return sensor.add_video_stream(vs, True)

    profiles = [(stereo, add(stereo, rs.stream.depth, 0, 0, rs.format.z16, 2), 2),
                (stereo, add(stereo, rs.stream.infrared, 1, 1, rs.format.y8, 1), 1),
                (stereo, add(stereo, rs.stream.infrared, 2, 2, rs.format.y8, 1), 1),
                (rgb, add(rgb, rs.stream.color, 0, 3, rs.format.bgr8, 3), 3)]
    stereo.add_read_only_option(rs.option.depth_units, 0.001)
    recorder = rs.recorder(str(path), dev, compress)
    queue = rs.frame_queue(100)
    stereo.open([p for s, p, _ in profiles if s is stereo])
    rgb.open(profiles[3][1])
    stereo.start(queue)
    rgb.start(queue)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W]
    keep = []
    for n in range(frames):
        images = [
            (600 + 0.5 * xx + 0.3 * yy + rng.normal(0, 2, (H, W)) + n).astype(np.uint16),
            ((xx + yy + n) % 256 ^ rng.integers(0, 16, (H, W))).astype(np.uint8),
            ((xx * 2 + yy + n) % 256 ^ rng.integers(0, 16, (H, W))).astype(np.uint8),
            np.ascontiguousarray(np.stack([(xx + n) % 256, yy % 256, (xx ^ yy) % 256], -1).astype(np.uint8)),
        ]
        for (sensor, profile, bpp), pixels in zip(profiles, images, strict=True):
            keep.append(pixels)
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride, f.timestamp, f.frame_number = pixels, bpp, bpp * W, 1000.0 + 33.3 * n, n
            f.domain = rs.timestamp_domain.global_time
            f.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(f)
        keep = keep[-16:]
    for sensor in (stereo, rgb):
        sensor.stop()
        sensor.close()
    del recorder


def time_darp(path: Path) -> tuple[int, float]:
    from darp.formats.realsense.recording import open_recording

    start = time.perf_counter()
    with open_recording(path) as recording:
        count = sum(1 for _ in recording.iter_frames())
    return count, time.perf_counter() - start


def time_pyrealsense(path: Path) -> tuple[int, float]:
    from helpers.realsense_playback import play_back

    start = time.perf_counter()
    played = play_back(path)
    return sum(len(v) for v in played.frames.values()), time.perf_counter() - start


def measure(frames: int) -> dict[str, tuple[float, float, float]]:
    """Per file (PNG-compressed, uncompressed): darp's frames/s, pyrealsense2's, and pyrealsense2's without
    its final end-of-file poll; each printed."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for compress in (True, False):
            path = Path(tmp) / f"bench_{'png' if compress else 'raw'}.db3"
            record(path, frames, compress)
            n_darp, t_darp = time_darp(path)
            n_rs, t_rs = time_pyrealsense(path)
            # the peer's time includes its end-of-file wait (one 200 ms poll); report it both ways
            darp_fps, rs_fps, rs_fps_net = n_darp / t_darp, n_rs / t_rs, n_rs / max(t_rs - 0.2, 1e-9)
            print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, {n_darp} frames (VGA depth+colour+IR1+IR2)")
            print(f"  darp        {darp_fps:8.1f} frames/s")
            print(f"  pyrealsense2 {rs_fps:7.1f} frames/s ({rs_fps_net:.1f} without its final 200 ms poll)")
            print(f"  ratio darp/pyrealsense2: {darp_fps / rs_fps:.2f} ({darp_fps / rs_fps_net:.2f})")
            out["PNG-compressed" if compress else "uncompressed"] = (darp_fps, rs_fps, rs_fps_net)
    return out


def rows(frames: int = 60) -> list[Row]:
    """The results table's rows: frames/s of each reader per file (no target stated; the peer's number is
    without its final 200 ms end-of-file poll, the fairer of the two)."""
    return [row("db3_read", f"{kind} .db3, VGA depth+colour+IR1+IR2, {frames} frame sets", "frames/s", darp,
                rs_net, "pyrealsense2 playback")
            for kind, (darp, _, rs_net) in measure(frames).items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    measure(args.frames)


if __name__ == "__main__":
    main()
