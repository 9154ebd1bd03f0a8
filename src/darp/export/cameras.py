"""Posed-image exports: nerfstudio, COLMAP, Open3D (Redwood) and TUM RGB-D, each in its consumer's conventions.

Every export reads a processed survey's keyframes (``darp.dataset``) and writes one folder. The
conventions, exactly (darp: ``T_world_cam`` maps OpenCV camera coordinates to the world, metres,
pixel centres at integer coordinates):

=========== ====================================================================================================
nerfstudio  ``transforms.json``: ``transform_matrix`` = ``T_world_cam @ diag(1, -1, -1, 1)`` (camera-to-world,
            OpenGL axes: x right, y up, z back); per frame ``fl_x fl_y cx cy w h k1 k2 p1 p2``, ``camera_model``
            OPENCV, ``cx = ppx + 0.5`` (nerfstudio casts rays through pixel centres at +0.5);
            ``depth_file_path``: uint16 PNG in millimetres (``depth_unit_scale_factor`` 0.001, nerfstudio's
            default); images/ RGB PNG (aligned to depth).
colmap      ``sparse/0/{cameras,images,points3D}.txt``: one OPENCV camera per arm, ``cx = ppx + 0.5`` (COLMAP's
            pixel centres are at +0.5); images.txt holds ``cam_from_world`` = ``inv(T_world_cam)`` as
            ``QW QX QY QZ TX TY TZ`` (OpenCV axes, metres) and an empty 2-D point line; points3D.txt empty:
            a known-pose model for ``colmap point_triangulator``. images/ RGB PNG.
open3d      per arm: ``color/NNNNNN.png``, ``depth/NNNNNN.png`` (uint16 mm: Open3D's ``depth_scale`` 1000),
            ``camera_intrinsic.json`` (Open3D's PinholeCameraIntrinsic, column-major, integer pixel centres
            like OpenCV) and a Redwood ``trajectory.log`` whose matrices are ``T_world_cam``
            (camera-to-world; Open3D's reader inverts them into extrinsics).
tum         per arm: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``:
            camera-to-world ``T_world_cam``, OpenCV optical axes, metres, seconds on the host clock),
            ``rgb/`` and ``depth/`` PNG (uint16, 5000 per metre, TUM's factor) and ``calibration.txt``
            (``fx fy cx cy`` with TUM's/OpenCV's integer pixel centres, and distortion).
=========== ====================================================================================================

Poses are written with 17 significant digits, so reading them back reproduces ``T_world_cam`` to
floating-point precision.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey
from darp.export._io import OPENCV_TO_OPENGL, depth_png, fmt, frame_name, write_lines, write_png
from darp.formats.atomic import write_json_atomic
from darp.formats.intrinsics import open3d_intrinsic_json
from darp.formats.trajectories import TUM_HEADER, write_tum
from darp.kinematics.transforms import rotation_to_quaternion
from darp.reconstruction.keyframe_io import Keyframe, iter_keyframes

NERFSTUDIO_DEPTH_UNITS_PER_M = 1000.0
OPEN3D_DEPTH_UNITS_PER_M = 1000.0
TUM_DEPTH_UNITS_PER_M = 5000.0


def _keyframes(survey: ProcessedSurvey) -> list[Keyframe]:
    return list(iter_keyframes(survey.keyframes_dir))


def _by_arm(keyframes: list[Keyframe]) -> dict[str, list[Keyframe]]:
    arms: dict[str, list[Keyframe]] = {}
    for kf in keyframes:
        arms.setdefault(kf.arm, []).append(kf)
    return arms


def export_nerfstudio(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """nerfstudio's ``transforms.json`` with images and depth (see the module docstring)."""
    frames = []
    for kf in iter_keyframes(survey.keyframes_dir):
        name, i = frame_name(kf), kf.intrinsics
        write_png(out / "images" / f"{name}.png", kf.rgb)
        write_png(out / "depth" / f"{name}.png", depth_png(kf, NERFSTUDIO_DEPTH_UNITS_PER_M))
        k1, k2, p1, p2, _k3 = i.coeffs
        frames.append({
            "file_path": f"images/{name}.png", "depth_file_path": f"depth/{name}.png",
            "transform_matrix": (np.asarray(kf.T_world_cam) @ OPENCV_TO_OPENGL).tolist(),
            "fl_x": i.fx, "fl_y": i.fy, "cx": i.ppx + 0.5, "cy": i.ppy + 0.5, "w": i.width, "h": i.height,
            "k1": k1, "k2": k2, "p1": p1, "p2": p2,
            "darp_arm": kf.arm, "darp_split": kf.split, "darp_frame_number": kf.frame_number, "darp_t_s": kf.t_s,
        })
    write_json_atomic(out / "transforms.json", {
        "camera_model": "OPENCV", "depth_unit_scale_factor": 1.0 / NERFSTUDIO_DEPTH_UNITS_PER_M,
        "darp": {"survey": survey.name, "world": "darp rig world frame (metres, z up)",
                 "pose": "camera-to-world, OpenGL camera axes (x right, y up, z back)"},
        "frames": frames})
    return {"frames": len(frames)}


def export_colmap(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """A known-pose COLMAP text model (cameras, images, empty points) and its images."""
    cameras: dict[tuple[float, ...], int] = {}
    camera_lines, image_lines = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"], [
        "# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME (cam_from_world), then POINTS2D[]"]
    for image_id, kf in enumerate(iter_keyframes(survey.keyframes_dir), start=1):
        i = kf.intrinsics
        k1, k2, p1, p2, _k3 = i.coeffs
        params = (float(i.fx), float(i.fy), i.ppx + 0.5, i.ppy + 0.5, k1, k2, p1, p2)
        key = (float(i.width), float(i.height), *params)
        if key not in cameras:
            cameras[key] = len(cameras) + 1
            camera_lines.append(f"{cameras[key]} OPENCV {i.width} {i.height} " + " ".join(fmt(p) for p in params))
        T_cam_world = np.linalg.inv(np.asarray(kf.T_world_cam, np.float64))
        x, y, z, w = rotation_to_quaternion(T_cam_world[:3, :3])
        tx, ty, tz = T_cam_world[:3, 3]
        name = f"{frame_name(kf)}.png"
        write_png(out / "images" / name, kf.rgb)
        pose = " ".join(fmt(v) for v in (w, x, y, z, tx, ty, tz))
        image_lines += [f"{image_id} {pose} {cameras[key]} {name}", ""]
    sparse = out / "sparse" / "0"
    write_lines(sparse / "cameras.txt", camera_lines)
    write_lines(sparse / "images.txt", image_lines)
    write_lines(sparse / "points3D.txt", ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]"])
    return {"images": len(image_lines) // 2, "cameras": len(cameras)}


def open3d_intrinsic(kf: Keyframe) -> dict[str, Any]:
    """Open3D's ``camera_intrinsic.json`` (PinholeCameraIntrinsic: column-major 3x3)."""
    i = kf.intrinsics
    return open3d_intrinsic_json(i.width, i.height, i.fx, i.fy, i.ppx, i.ppy)


def export_open3d(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """Per arm: colour/depth folders, camera_intrinsic.json and a Redwood trajectory.log."""
    counts = {}
    for arm, keyframes in _by_arm(_keyframes(survey)).items():
        folder, log = out / arm, []
        for n, kf in enumerate(keyframes):
            write_png(folder / "color" / f"{n:06d}.png", kf.rgb)
            write_png(folder / "depth" / f"{n:06d}.png", depth_png(kf, OPEN3D_DEPTH_UNITS_PER_M))
            log.append(f"{n} {n} {len(keyframes)}")
            log += [" ".join(fmt(v) for v in row) for row in np.asarray(kf.T_world_cam, np.float64)]
        write_json_atomic(folder / "camera_intrinsic.json", open3d_intrinsic(keyframes[0]))
        write_lines(folder / "trajectory.log", log)
        write_json_atomic(folder / "frames.json", {
            "depth_scale": OPEN3D_DEPTH_UNITS_PER_M,
            "frames": [{"index": n, "frame_number": kf.frame_number, "split": kf.split, "t_s": kf.t_s}
                       for n, kf in enumerate(keyframes)]})
        counts[arm] = len(keyframes)
    return {"frames": counts}


def export_tum(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """Per arm: a TUM RGB-D sequence folder with its ground truth and calibration."""
    counts = {}
    for arm, keyframes in _by_arm(_keyframes(survey)).items():
        folder = out / arm
        rgb, depth, stamps = ["# color images", "# timestamp filename"], ["# depth maps", "# timestamp filename"], []
        ordered = sorted(keyframes, key=lambda k: k.t_s)
        for kf in ordered:
            stamp = f"{kf.t_s:.6f}"
            write_png(folder / "rgb" / f"{stamp}.png", kf.rgb)
            write_png(folder / "depth" / f"{stamp}.png", depth_png(kf, TUM_DEPTH_UNITS_PER_M))
            rgb.append(f"{stamp} rgb/{stamp}.png")
            depth.append(f"{stamp} depth/{stamp}.png")
            stamps.append(stamp)
        write_lines(folder / "rgb.txt", rgb)
        write_lines(folder / "depth.txt", depth)
        poses = np.array([np.asarray(kf.T_world_cam, np.float64) for kf in ordered])
        write_tum(folder / "groundtruth.txt", stamps, poses,
                  ("# ground truth trajectory (T_world_cam, OpenCV optical frame)", f"# {TUM_HEADER}"), fmt)
        i = keyframes[0].intrinsics
        write_lines(folder / "calibration.txt", [
            "# fx fy cx cy k1 k2 p1 p2 k3 (pixel centres at integers; depth PNG: 5000 per metre)",
            " ".join(fmt(v) for v in (i.fx, i.fy, i.ppx, i.ppy, *i.coeffs))])
        counts[arm] = len(keyframes)
    return {"frames": counts}


__all__ = ["export_colmap", "export_nerfstudio", "export_open3d", "export_tum", "open3d_intrinsic"]
