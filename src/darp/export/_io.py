"""Small writers the exports share: PNG images, PCD clouds, text, all written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from darp.errors import FormatError
from darp.formats.atomic import atomic_open, write_text_atomic
from darp.reconstruction.keyframe_io import Keyframe

# OpenCV camera (x right, y down, z forward) -> OpenGL/Blender camera (x right, y up, z backward)
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def write_png(path: Path, image: np.ndarray) -> Path:
    """An 8-bit (grey or RGB, RGB order in memory) or 16-bit PNG, atomically."""
    return write_image(path, image)


def write_image(path: Path, image: np.ndarray) -> Path:
    """An image in the format of the path's suffix (``.png``, ``.tiff``), atomically; RGB order in memory."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = np.ascontiguousarray(img[:, :, ::-1])  # OpenCV writes BGR
    # TIFF uncompressed: OpenCV's default LZW needs an extra codec package in tifffile / imageio readers
    params = [cv2.IMWRITE_TIFF_COMPRESSION, 1] if path.suffix in (".tif", ".tiff") else []
    ok, buffer = cv2.imencode(path.suffix, img, params)
    if not ok:
        raise FormatError(f"{path.suffix} encoding failed", path)
    with atomic_open(path, "wb") as handle:
        handle.write(buffer.tobytes())
    return path


def depth_png(kf: Keyframe, units_per_m: float) -> np.ndarray:
    """Depth as uint16 in ``1/units_per_m`` metre steps (0 = no depth); values past 65535 become 0."""
    value = np.rint(kf.depth_m.astype(np.float64) * units_per_m)
    value[(value > 65535) | ~np.isfinite(value)] = 0
    return value.astype(np.uint16)


def write_pcd(path: Path, points: np.ndarray) -> Path:
    """A binary PCD v0.7 cloud of float32 x y z (what PCN/PoinTr and Open3D read)."""
    p = np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))
    header = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
              f"COUNT 1 1 1\nWIDTH {len(p)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(p)}\nDATA binary\n")
    with atomic_open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(p.astype("<f4").tobytes())
    return path


def colour_valid(kf: Keyframe) -> np.ndarray:
    """(H, W) bool: pixels the colour camera saw (alignment leaves the rest black; a seen pixel of pure black
    would read as unseen, which only shrinks the mask)."""
    return np.asarray(np.asarray(kf.rgb).any(axis=2))


def mask_png(mask: np.ndarray) -> np.ndarray:
    """A boolean mask as an 8-bit single-channel image: 255 where true, 0 elsewhere."""
    return np.asarray(mask, bool).astype(np.uint8) * 255


def write_lines(path: Path, lines: list[str]) -> Path:
    write_text_atomic(path, "".join(f"{line}\n" for line in lines))
    return path


def frame_name(kf: Keyframe) -> str:
    """``<arm>_<frame number>``: unique within a survey."""
    return f"{kf.arm}_{kf.frame_number:06d}"


def fmt(x: float) -> str:
    """A float with 17 significant digits (round-trips exactly)."""
    return repr(float(x))
