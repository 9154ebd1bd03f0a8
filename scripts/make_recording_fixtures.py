#!/usr/bin/env python3
"""Make the genuine librealsense recordings in ``tests/fixtures/recordings/``.

librealsense's own recorder (``rs.recorder`` over an ``rs.software_device``) writes tiny recordings of
a made-up D435i: depth (Z16), colour (BGR8), infrared 1 and 2 (Y8) at 64x48, accel and gyro, with
intrinsics, distortion, extrinsics, depth units and frame metadata, and deterministic pixels. They are
the oracle for "darp reads what librealsense writes":

* ROS1 ``.bag`` files come from pyrealsense2 2.57 (the last SDK that writes them), installed into an
  isolated virtual environment (``--old-venv``, created on first use);
* ROS2 ``.db3`` files come from the pyrealsense2 >= 2.58 of the running interpreter.

Each SDK writes one file with its default compression and one without. Run from the repository root::

    .venv/bin/python scripts/make_recording_fixtures.py            # writes tests/fixtures/recordings/

Pixels, timestamps and metadata are the same on every run; only the recording times (the host
clock while recording) differ.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

OLD_SDK = "pyrealsense2==2.57.7.10387"
WIDTH, HEIGHT, FPS = 64, 48, 30
N_FRAMES = 4
DEPTH_UNITS = 0.000125
SERIAL = "348522076490"
BASE_MS = {"stereo": 1_700_000_000_000.0, "color": 1_700_000_000_005.125, "motion": 86_400_123.456789}
FRAME_PERIOD_MS = 33.366


# -- the deterministic content (also used by tests to check that what was recorded is what we meant) ---
def depth_pixels(n: int):
    import numpy as np

    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    return ((yy * WIDTH + xx) * 7 + n * 1001 + 300).astype(np.uint16)


def infrared_pixels(n: int, which: int):
    import numpy as np

    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    if which == 1:
        return ((xx * 3 + yy * 5 + n * 17) % 256).astype(np.uint8)
    return ((xx * 5 + yy * 3 + n * 29 + 7) % 256).astype(np.uint8)


def color_pixels(n: int):
    """BGR, with a pure blue top-left pixel so that a channel swap is visible."""
    import numpy as np

    yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
    bgr = np.stack([(xx * 4 + n) % 256, (yy * 5 + 2 * n) % 256, (xx + yy + 40 * n) % 256], axis=-1)
    bgr = bgr.astype(np.uint8)
    bgr[0, 0] = (255, 0, 0)
    return np.ascontiguousarray(bgr)


# -- recording (runs inside the interpreter whose pyrealsense2 writes the file) ------------------------
def record(out: Path, compress: bool) -> None:
    import numpy as np
    import pyrealsense2 as rs

    dev = rs.software_device()
    for info, value in ((rs.camera_info.name, "Intel RealSense D435I"), (rs.camera_info.serial_number, SERIAL),
                        (rs.camera_info.firmware_version, "5.13.0.50"), (rs.camera_info.product_id, "0B3A")):
        dev.register_info(info, value)
    stereo, rgb, motion = (dev.add_sensor(n) for n in ("Stereo Module", "RGB Camera", "Motion Module"))

    def intrinsics(fx, fy, ppx, ppy, model, coeffs):
        i = rs.intrinsics()
        i.width, i.height, i.fx, i.fy, i.ppx, i.ppy, i.model, i.coeffs = WIDTH, HEIGHT, fx, fy, ppx, ppy, model, coeffs
        return i

    def video(sensor, stream, index, uid, fmt, bpp, intr):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = (
            stream, index, uid, WIDTH, HEIGHT, FPS, bpp, fmt)
        vs.intrinsics = intr
        return sensor.add_video_stream(vs, True)

    def imu(stream, uid, fps):
        ms = rs.motion_stream()
        ms.type, ms.index, ms.uid, ms.fps, ms.fmt = stream, 0, uid, fps, rs.format.motion_xyz32f
        mi = rs.motion_device_intrinsic()
        mi.data = [[1.01, 0.002, 0.003, 0.04], [0.005, 0.98, 0.006, -0.05], [0.007, 0.008, 1.02, 0.06]]
        mi.noise_variances, mi.bias_variances = [0.001, 0.002, 0.003], [0.004, 0.005, 0.006]
        ms.intrinsics = mi
        return motion.add_motion_stream(ms, True)

    stereo_intr = intrinsics(45.25, 45.5, 31.75, 23.5, rs.distortion.brown_conrady, [0.0] * 5)
    depth = video(stereo, rs.stream.depth, 0, 0, rs.format.z16, 2, stereo_intr)
    ir1 = video(stereo, rs.stream.infrared, 1, 1, rs.format.y8, 1, stereo_intr)
    ir2 = video(stereo, rs.stream.infrared, 2, 2, rs.format.y8, 1, stereo_intr)
    color = video(rgb, rs.stream.color, 0, 3, rs.format.bgr8, 3,
                  intrinsics(55.123456, 55.654321, 32.1, 24.2, rs.distortion.inverse_brown_conrady,
                             [0.1234567, -0.2345678, 0.0012345, -0.0023456, 0.0345678]))
    accel, gyro = imu(rs.stream.accel, 4, 100), imu(rs.stream.gyro, 5, 200)
    stereo.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)

    def extrinsics(angles, translation):
        ax, ay, az = angles
        rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
        ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
        rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
        e = rs.extrinsics()
        e.rotation = [float(v) for v in (rz @ ry @ rx).T.reshape(-1)]  # librealsense: column-major
        e.translation = list(translation)
        return e

    depth.register_extrinsics_to(ir1, extrinsics((0, 0, 0), (0.0, 0.0, 0.0)))
    depth.register_extrinsics_to(ir2, extrinsics((0, 0, 0), (-0.0501234, 0.0, 0.0)))
    depth.register_extrinsics_to(color, extrinsics((0.01, -0.02, 0.003), (0.0147123, 0.0002345, 0.0003456)))
    for profile in (accel, gyro):
        depth.register_extrinsics_to(profile, extrinsics((0, 0, 0), (-0.0120345, -0.0051234, 0.0123456)))

    recorder = rs.recorder(str(out), dev, compress)
    queue = rs.frame_queue(1000)
    stereo.open([depth, ir1, ir2])
    rgb.open(color)
    motion.open([accel, gyro])
    for sensor in (stereo, rgb, motion):
        sensor.start(queue)
    keep_alive = []  # librealsense reads the pixel buffers after on_video_frame returns

    def send(sensor, profile, pixels, bpp, timestamp, domain, number):
        keep_alive.append(pixels)
        frame = rs.software_video_frame()
        frame.pixels, frame.bpp, frame.stride = pixels, bpp, bpp * WIDTH
        frame.timestamp, frame.domain, frame.frame_number = timestamp, domain, number
        frame.profile = profile.as_video_stream_profile()
        if profile == depth:
            frame.depth_units = DEPTH_UNITS
        sensor.on_video_frame(frame)

    for n in range(N_FRAMES):
        stereo_ms = BASE_MS["stereo"] + n * FRAME_PERIOD_MS
        stereo.set_metadata(rs.frame_metadata_value.frame_counter, 1000 + n)
        stereo.set_metadata(rs.frame_metadata_value.actual_exposure, 8500 + n)
        rgb.set_metadata(rs.frame_metadata_value.frame_counter, 500 + n)
        rgb.set_metadata(rs.frame_metadata_value.white_balance, 4600 + 10 * n)
        send(stereo, depth, depth_pixels(n), 2, stereo_ms, rs.timestamp_domain.global_time, 1000 + n)
        send(stereo, ir1, infrared_pixels(n, 1), 1, stereo_ms, rs.timestamp_domain.global_time, 1000 + n)
        send(stereo, ir2, infrared_pixels(n, 2), 1, stereo_ms, rs.timestamp_domain.global_time, 1000 + n)
        send(rgb, color, color_pixels(n), 3, BASE_MS["color"] + n * FRAME_PERIOD_MS,
             rs.timestamp_domain.system_time, 500 + n)
        for k in range(2):
            for profile, scale, offset in ((accel, 9.81, 0.0), (gyro, 0.1, 0.5)):
                sample = rs.vector()
                sample.x, sample.y, sample.z = scale * (0.1 + n + 0.25 * k), -scale * 0.5, scale * (1 + 0.01 * n)
                frame = rs.software_motion_frame()
                frame.data = sample
                frame.timestamp = BASE_MS["motion"] + n * FRAME_PERIOD_MS + k * 10.0 + offset
                frame.domain, frame.frame_number = rs.timestamp_domain.hardware_clock, 2000 + 2 * n + k
                frame.profile = profile.as_motion_stream_profile()
                motion.on_motion_frame(frame)
        time.sleep(0.04)
    for sensor in (stereo, rgb, motion):
        sensor.stop()
    for sensor in (stereo, rgb, motion):
        sensor.close()
    del recorder  # the file is finished when the recorder goes away


# -- orchestration ------------------------------------------------------------------------------------
def ensure_old_venv(venv: Path) -> Path:
    """The interpreter of an isolated venv with pyrealsense2 2.57 (created when missing)."""
    python = venv / "bin" / "python"
    check = [str(python), "-c", "import pyrealsense2, numpy"]
    if python.exists() and subprocess.run(check, capture_output=True, check=False).returncode == 0:
        return python
    print(f"creating {venv} with {OLD_SDK} (needs PyPI)", flush=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "-q", OLD_SDK, "numpy"], check=True)
    return python


def sdk_version(python: Path | str) -> str:
    code = "from importlib import metadata; print(metadata.version('pyrealsense2'))"
    return subprocess.run([str(python), "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def make(python: Path | str, target: Path, compress: bool) -> None:
    """Record ``target`` with ``python``'s pyrealsense2 in a temporary folder, then move it in place."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp_file = Path(tmp) / target.name
        cmd = [str(python), __file__, "record", str(tmp_file), "--compress" if compress else "--no-compress"]
        subprocess.run(cmd, check=True)
        shutil.move(tmp_file, target)
    print(f"wrote {target} ({target.stat().st_size} bytes)", flush=True)


def write_readme(out: Path, files: dict[str, str], versions: dict[str, str]) -> None:
    lines = [
        "# Genuine librealsense recordings",
        "",
        "Written by librealsense's own recorder (`rs.recorder` over an `rs.software_device`) with",
        "`scripts/make_recording_fixtures.py`; do not edit them by hand, re-run the script. The tests in",
        "`tests/test_formats_genuine.py` check that darp's readers return exactly what pyrealsense2 returns",
        "when it plays these files back.",
        "",
        "Content: a made-up Intel RealSense D435I (serial 348522076490, firmware 5.13.0.50): depth Z16,",
        "infrared 1 and 2 Y8 (Stereo Module), colour BGR8 (RGB Camera), all 64x48 at 30 fps, 4 frames each;",
        "accel (100 Hz) and gyro (200 Hz), 8 samples each (Motion Module). Depth units 0.000125 m.",
        "Intrinsics with Brown-Conrady and inverse Brown-Conrady models, IMU intrinsics, extrinsics from",
        "depth to every stream, frame metadata (frame counter, exposure, white balance), all three",
        "timestamp domains (global time: depth/IR, system time: colour, hardware clock: IMU).",
        "Pixels, frame numbers and timestamps are deterministic; recording times (host clock) are not.",
        "",
        "| file | written by | compression | bytes | sha256 |",
        "|---|---|---|---|---|",
    ]
    for name, (writer, compression) in files.items():
        data = (out / name).read_bytes()
        lines.append(f"| `{name}` | {writer} | {compression} | {len(data)} | "
                     f"`{hashlib.sha256(data).hexdigest()[:16]}` |")
    lines += ["", "Versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()) + ".", ""]
    (out / "README.md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command")
    rec = sub.add_parser("record", help="(internal) record one file with this interpreter's pyrealsense2")
    rec.add_argument("out", type=Path)
    rec.add_argument("--compress", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).resolve().parent.parent / "tests/fixtures/recordings")
    parser.add_argument("--old-venv", type=Path, default=Path("/tmp/rs257-venv"))
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.out, args.compress)
        return 0
    new_version = metadata.version("pyrealsense2")
    if tuple(int(p) for p in new_version.split(".")[:2]) < (2, 58):
        parser.error(f"this interpreter has pyrealsense2 {new_version}; .db3 files need >= 2.58")
    old_python = ensure_old_venv(args.old_venv)
    old_version = sdk_version(old_python)
    args.out.mkdir(parents=True, exist_ok=True)
    files = {
        "rs257_lz4.bag": (f"pyrealsense2 {old_version}", "LZ4 chunks (recorder default)", old_python, True),
        "rs257_uncompressed.bag": (f"pyrealsense2 {old_version}", "none", old_python, False),
        "rs259_png.db3": (f"pyrealsense2 {new_version}", "PNG images (recorder default)", sys.executable, True),
        "rs259_uncompressed.db3": (f"pyrealsense2 {new_version}", "none", sys.executable, False),
    }
    for name, (_, _, python, compress) in files.items():
        make(python, args.out / name, compress)
    py = f"{sys.version_info.major}.{sys.version_info.minor}"
    write_readme(args.out, {k: v[:2] for k, v in files.items()},
                 {"pyrealsense2 (bag)": old_version, "pyrealsense2 (db3)": new_version, "Python": py})
    return 0


if __name__ == "__main__":
    sys.exit(main())
