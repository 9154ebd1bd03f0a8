"""COLMAP export: a known-pose model, its database, masks and depth maps, ready for ``point_triangulator``.

::

    images/<arm>_<frame>.png              colour aligned to depth
    masks/<arm>_<frame>.png.png           COLMAP's mask convention (``ImageReader.mask_path``): 0 = no
                                          features; 255 where the colour camera saw the pixel
    sparse/0/{cameras,images,points3D}.txt   one OPENCV camera per arm, ``cx = ppx + 0.5`` (COLMAP's pixel
                                          centres are at +0.5); images.txt: ``cam_from_world`` =
                                          ``inv(T_world_cam)`` as QW QX QY QZ TX TY TZ (OpenCV axes, metres)
    database.db                           the same cameras (OPENCV, prior focal length) and images with the same
                                          ids and names, so ``colmap feature_extractor`` / ``pycolmap.extract_features``
                                          with default options keeps darp's cameras (no ``--ImageReader.camera_model``)
    stereo/depth_maps/<name>.geometric.bin   darp's depth (metres, z) in COLMAP's dense array format
    frames.json                           per image: arm, frame number, split, host time t_s, camera timestamp_ms

The database is written in COLMAP's legacy schema (``cameras`` and ``images`` tables, what COLMAP's own
``scripts/python/database.py`` writes); COLMAP adds its other tables (rigs, frames, keypoints, ...) when
it opens it. Then ``pycolmap.extract_features``, ``match_exhaustive`` and ``triangulate_points`` (or
``colmap point_triangulator``) run on the folder as it is.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey
from darp.errors import FormatError
from darp.export._io import colour_valid, fmt, frame_name, mask_png, write_lines, write_png
from darp.formats.atomic import atomic_open, write_json_atomic
from darp.kinematics.transforms import rotation_to_quaternion
from darp.reconstruction.keyframe_io import Keyframe, iter_keyframes

OPENCV_MODEL_ID = 4  # COLMAP's CameraModelId.OPENCV
_SCHEMA = (
    "CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL, "
    "width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL)",
    "CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE, "
    "camera_id INTEGER NOT NULL, CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647), "
    "FOREIGN KEY(camera_id) REFERENCES cameras(camera_id))",
)


def colmap_params(kf: Keyframe) -> tuple[float, ...]:
    """OPENCV camera parameters ``fx fy cx cy k1 k2 p1 p2`` with COLMAP's +0.5 pixel centres."""
    i = kf.intrinsics
    k1, k2, p1, p2, _k3 = i.coeffs
    return float(i.fx), float(i.fy), i.ppx + 0.5, i.ppy + 0.5, float(k1), float(k2), float(p1), float(p2)


def write_depth_map(path: Path, depth_m: np.ndarray) -> Path:
    """COLMAP's dense array file (``mvs/mat.h``): ``width&height&channels&`` then float32 with x fastest
    (COLMAP's ``read_array`` reshapes to (width, height) in Fortran order)."""
    d = np.asarray(depth_m, np.float32)
    h, w = d.shape
    with atomic_open(path, "wb") as handle:
        handle.write(f"{w}&{h}&1&".encode("ascii"))
        handle.write(np.ascontiguousarray(d, "<f4").tobytes())
    return path


def write_database(path: Path, cameras: dict[tuple[float, ...], int], images: list[tuple[int, str, int]]) -> Path:
    """A COLMAP database (legacy schema) holding the cameras and images of the model."""
    if path.exists():
        path.unlink()  # COLMAP's database is one file; a fresh one, never a mix with an earlier export
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        with sqlite3.connect(tmp) as con:
            for statement in _SCHEMA:
                con.execute(statement)
            con.executemany("INSERT INTO cameras VALUES (?, ?, ?, ?, ?, 1)", [
                (camera_id, OPENCV_MODEL_ID, int(key[0]), int(key[1]), np.asarray(key[2:], "<f8").tobytes())
                for key, camera_id in cameras.items()])
            con.executemany("INSERT INTO images VALUES (?, ?, ?)", images)
        con.close()
        tmp.replace(path)
    except sqlite3.Error as err:
        tmp.unlink(missing_ok=True)
        raise FormatError(f"cannot write the COLMAP database: {err}", path) from err
    return path


def export_colmap(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """A known-pose COLMAP model with its database, images, masks and depth maps (module docstring)."""
    cameras: dict[tuple[float, ...], int] = {}
    camera_lines, image_lines = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"], [
        "# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME (cam_from_world), then POINTS2D[]"]
    images: list[tuple[int, str, int]] = []
    frames = []
    for image_id, kf in enumerate(iter_keyframes(survey.keyframes_dir), start=1):
        i, params = kf.intrinsics, colmap_params(kf)
        key = (float(i.width), float(i.height), *params)
        if key not in cameras:
            cameras[key] = len(cameras) + 1
            camera_lines.append(f"{cameras[key]} OPENCV {i.width} {i.height} " + " ".join(fmt(p) for p in params))
        T_cam_world = np.linalg.inv(np.asarray(kf.T_world_cam, np.float64))
        x, y, z, w = rotation_to_quaternion(T_cam_world[:3, :3])
        tx, ty, tz = T_cam_world[:3, 3]
        name = f"{frame_name(kf)}.png"
        write_png(out / "images" / name, kf.rgb)
        write_png(out / "masks" / f"{name}.png", mask_png(colour_valid(kf)))
        write_depth_map(out / "stereo" / "depth_maps" / f"{name}.geometric.bin", kf.depth_m)
        pose = " ".join(fmt(v) for v in (w, x, y, z, tx, ty, tz))
        image_lines += [f"{image_id} {pose} {cameras[key]} {name}", ""]
        images.append((image_id, name, cameras[key]))
        frames.append({"image_id": image_id, "name": name, "arm": kf.arm, "frame_number": kf.frame_number,
                       "split": kf.split, "t_s": kf.t_s, "timestamp_ms": kf.timestamp_ms})
    sparse = out / "sparse" / "0"
    write_lines(sparse / "cameras.txt", camera_lines)
    write_lines(sparse / "images.txt", image_lines)
    write_lines(sparse / "points3D.txt", ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"])
    write_database(out / "database.db", cameras, images)
    write_json_atomic(out / "frames.json", {"survey": survey.name, "frames": frames})
    return {"images": len(images), "cameras": len(cameras)}


__all__ = ["OPENCV_MODEL_ID", "colmap_params", "export_colmap", "write_database", "write_depth_map"]
