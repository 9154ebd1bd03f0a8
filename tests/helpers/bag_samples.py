"""Sample RealSense .bag recordings written with darp's writer, and what was written into them: textured
images, a colour stream on the system clock and two IMU streams, with known intrinsics and extrinsics."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from darp.formats.realsense.bag.writer import BagWriter
from darp.formats.realsense.types import DeviceInfo, Intrinsics, MotionIntrinsics, StreamProfile

DEVICE = DeviceInfo("Intel RealSense D435I", "348522076490", "5.13.0.50", "0B3A",
                    {"Product Line": "D400", "Usb Type Descriptor": "3.2"})
IMU_INTRINSICS = MotionIntrinsics(tuple(1.0 + 0.01 * i for i in range(12)), (1e-4, 2e-4, 3e-4), (4e-6, 5e-6, 6e-6))


def _pose(rotvec: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


EXTRINSICS = {  # T_stream_depth
    "color": _pose((0.01, -0.02, 0.03), (0.0147, 0.0002, -0.0003)),
    "ir1": np.eye(4),
    "ir2": _pose((0.0, 0.0, 0.0), (-0.0499, 0.0, 0.0)),
    "accel": _pose((0.5, -0.3, 0.2), (-0.0117, -0.0055, 0.0051)),
    "gyro": _pose((0.5, -0.3, 0.2), (-0.0117, -0.0055, 0.0051)),
}


def profiles(width: int, height: int) -> list[StreamProfile]:
    def intr(fx: float, model: str, coeffs: tuple[float, ...]) -> Intrinsics:
        return Intrinsics(width, height, fx, fx * 1.01, width / 2 - 0.37, height / 2 + 0.21, model, coeffs)

    return [
        StreamProfile("depth", "Depth", 0, 0, "z16", 30, width, height, intr(0.6 * width, "Brown Conrady", (0.0,) * 5)),
        StreamProfile("ir1", "Infrared", 1, 0, "y8", 30, width, height, intr(0.6 * width, "Brown Conrady", (0.0,) * 5)),
        StreamProfile("ir2", "Infrared", 2, 0, "y8", 30, width, height, intr(0.6 * width, "Brown Conrady", (0.0,) * 5)),
        StreamProfile("color", "Color", 0, 1, "rgb8", 30, width, height,
                      intr(0.9 * width, "Inverse Brown Conrady", (0.12, -0.25, 0.001, -0.002, 0.07))),
        StreamProfile("accel", "Accel", 0, 2, "motion_xyz32f", 100, motion_intrinsics=IMU_INTRINSICS),
        StreamProfile("gyro", "Gyro", 0, 2, "motion_xyz32f", 200, motion_intrinsics=IMU_INTRINSICS),
    ]


@dataclass
class Sample:
    path: Path
    streams: list[StreamProfile]
    frames: dict[str, list[dict]] = field(default_factory=dict)  # per stream: ts, number, domain, data


def write_sample(path: Path, *, compression: str = "lz4", width: int = 64, height: int = 48, framesets: int = 12,
                 seed: int = 0, chunk_threshold: int = 768 * 1024,
                 image_order: tuple[str, ...] = ("depth", "ir1", "ir2", "color"), imu: bool = True) -> Sample:
    """A small recording with textured images, a colour stream on the system clock and 2 IMU streams."""
    rng = np.random.default_rng(seed)
    streams = [p for p in profiles(width, height) if imu or p.is_image]
    sample = Sample(path, streams, {p.key: [] for p in streams})
    x = np.arange(width)[None, :]
    with BagWriter(path, DEVICE, streams, depth_scale=0.00025, compression=compression,
                   extrinsics={k: v for k, v in EXTRINSICS.items() if imu or k not in ("accel", "gyro")},
                   chunk_threshold=chunk_threshold) as writer:
        for i in range(framesets):
            t_ms = 1_700_000_000_000.0 + 33.3667 * i
            images = {
                "depth": (800 + 200 * np.sin((x + 3 * i) / 7.0)
                          + rng.integers(0, 9, (height, width))).astype(np.uint16),
                "ir1": rng.integers(0, 256, (height, width), dtype=np.uint8),
                "ir2": rng.integers(0, 256, (height, width), dtype=np.uint8),
                "color": rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
            }
            for key in image_order:
                stamp = t_ms + (1.7 if key == "color" else 0.0)
                domain = "System Time" if key == "color" else "Global Time"
                number = 5000 + i if key == "color" else 100 + i
                writer.write_image(key, images[key], stamp, number, timestamp_domain=domain)
                sample.frames[key].append({"ts": stamp, "number": number, "domain": domain, "data": images[key]})
            for j in range(3 if imu else 0):
                for key, scale in (("accel", 9.81), ("gyro", 0.5)):
                    xyz = (rng.normal(size=3) * scale).astype(np.float32)
                    stamp, number = t_ms + 11.0 * j + (0.3 if key == "gyro" else 0.0), 3 * i + j
                    writer.write_motion(key, xyz, stamp, number, timestamp_domain="Global Time")
                    sample.frames[key].append({"ts": stamp, "number": number, "domain": "Global Time", "data": xyz})
    return sample
