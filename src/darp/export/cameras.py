"""Posed-image exports: nerfstudio, Open3D (Redwood) and TUM RGB-D, each in its consumer's conventions (COLMAP:
:mod:`darp.export.colmap`).

Every export reads a processed survey's keyframes (``darp.dataset``) and writes one folder. The
conventions, exactly (darp: ``T_world_cam`` maps OpenCV camera coordinates to the world, metres,
pixel centres at integer coordinates):

=========== ====================================================================================================
nerfstudio  ``transforms.json``: ``transform_matrix`` = ``T_world_cam @ diag(1, -1, -1, 1)`` (camera-to-world,
            OpenGL axes: x right, y up, z back); per frame ``fl_x fl_y cx cy w h k1 k2 p1 p2``, ``camera_model``
            OPENCV, ``cx = ppx + 0.5`` (nerfstudio casts rays through pixel centres at +0.5);
            ``depth_file_path``: uint16 PNG in millimetres (nerfstudio's default ``--depth-unit-scale-factor``
            0.001; also written as ``depth_unit_scale_factor``); ``mask_path``: 255 where the colour camera saw
            the pixel (nerfstudio samples no ray where it is 0); darp's split as ``train_filenames``
            (fuse) and ``val_filenames`` = ``test_filenames`` (held out); ``ply_file_path``: the fused cloud
            in its colours (splatfacto's seed points). images/ RGB PNG (aligned to depth). darp's own keys
            (nerfstudio ignores them): per frame ``darp_object_mask_path`` (object support), ``darp_ir_path``
            (left IR, the depth camera), ``darp_t_s`` (host time), ``darp_timestamp_ms`` (camera clock).
open3d      the survey's own ``fused.ply``, ``arm110.ply``, ``arm111.ply`` and ``mesh.ply``; per arm:
            ``color/NNNNNN.png``, ``depth/NNNNNN.png`` (uint16 mm: Open3D's ``depth_scale`` 1000),
            ``camera_intrinsic.json`` (Open3D's PinholeCameraIntrinsic, column-major, integer pixel centres
            like OpenCV) and a Redwood ``trajectory.log`` whose matrices are ``T_world_cam``
            (camera-to-world; Open3D's reader inverts them into extrinsics); ``frames.json``: per index the
            frame number, split and times.
tum         per arm: ``rgb.txt``, ``depth.txt`` (the keyframes), ``darp_poses.txt`` (darp's pose of every frame
            that has one: what processing used) and, for a twin survey only, ``groundtruth.txt`` (the true
            pose of every frame); both ``timestamp tx ty tz qx qy qz qw``: camera-to-world ``T_world_cam``,
            OpenCV optical axes, metres, seconds on the host clock; ``rgb/`` and ``depth/`` PNG (uint16, 5000
            per metre, TUM's factor) and ``calibration.txt`` (``fx fy cx cy`` with TUM's/OpenCV's integer
            pixel centres, and distortion).
=========== ====================================================================================================

Poses are written with 17 significant digits, so reading them back reproduces ``T_world_cam`` to
floating-point precision.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import CLOUD_FILES, MESH_FILE, ProcessedSurvey
from darp.export._io import (
    OPENCV_TO_OPENGL,
    colour_valid,
    depth_png,
    fmt,
    frame_name,
    mask_png,
    write_lines,
    write_png,
)
from darp.export.poses import estimated_poses, true_poses
from darp.formats.atomic import atomic_path, write_json_atomic
from darp.formats.intrinsics import open3d_intrinsic_json
from darp.formats.trajectories import TUM_HEADER, write_tum
from darp.reconstruction.cloud_io import read_ply, write_cloud_ply
from darp.reconstruction.keyframe_io import Keyframe, iter_keyframes
from darp.reconstruction.keyframes import FUSE, HELDOUT

NERFSTUDIO_DEPTH_UNITS_PER_M = 1000.0
OPEN3D_DEPTH_UNITS_PER_M = 1000.0
TUM_DEPTH_UNITS_PER_M = 5000.0
TUM_GROUNDTRUTH = "groundtruth.txt"  # TUM's name: true poses only (a twin survey's truth)
TUM_ESTIMATE = "darp_poses.txt"  # darp's own trajectory, e.g. evo_ape tum groundtruth.txt darp_poses.txt


def _keyframes(survey: ProcessedSurvey) -> list[Keyframe]:
    return list(iter_keyframes(survey.keyframes_dir))


def _by_arm(keyframes: list[Keyframe]) -> dict[str, list[Keyframe]]:
    arms: dict[str, list[Keyframe]] = {}
    for kf in keyframes:
        arms.setdefault(kf.arm, []).append(kf)
    return arms


def export_nerfstudio(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """nerfstudio's ``transforms.json`` with images, depth, masks, darp's split and a seed cloud (module docstring)."""
    frames: list[dict[str, Any]] = []
    split: dict[str, list[str]] = {FUSE: [], HELDOUT: []}
    for kf in iter_keyframes(survey.keyframes_dir):
        name, i = frame_name(kf), kf.intrinsics
        write_png(out / "images" / f"{name}.png", kf.rgb)
        write_png(out / "depth" / f"{name}.png", depth_png(kf, NERFSTUDIO_DEPTH_UNITS_PER_M))
        write_png(out / "masks" / f"{name}.png", mask_png(colour_valid(kf)))
        write_png(out / "object_masks" / f"{name}.png", mask_png(kf.support_mask))
        write_png(out / "ir" / f"{name}.png", kf.ir_left)
        k1, k2, p1, p2, _k3 = i.coeffs
        frames.append({
            "file_path": f"images/{name}.png", "depth_file_path": f"depth/{name}.png",
            "mask_path": f"masks/{name}.png",
            "transform_matrix": (np.asarray(kf.T_world_cam) @ OPENCV_TO_OPENGL).tolist(),
            "fl_x": i.fx, "fl_y": i.fy, "cx": i.ppx + 0.5, "cy": i.ppy + 0.5, "w": i.width, "h": i.height,
            "k1": k1, "k2": k2, "p1": p1, "p2": p2,
            "darp_object_mask_path": f"object_masks/{name}.png", "darp_ir_path": f"ir/{name}.png",
            "darp_arm": kf.arm, "darp_split": kf.split, "darp_frame_number": kf.frame_number, "darp_t_s": kf.t_s,
            "darp_timestamp_ms": kf.timestamp_ms,
        })
        split[kf.split].append(f"images/{name}.png")
    meta: dict[str, Any] = {
        "camera_model": "OPENCV", "depth_unit_scale_factor": 1.0 / NERFSTUDIO_DEPTH_UNITS_PER_M,
        "train_filenames": split[FUSE], "val_filenames": split[HELDOUT], "test_filenames": split[HELDOUT],
        "darp": {"survey": survey.name, "world": "darp rig world frame (metres, z up)",
                 "pose": "camera-to-world, OpenGL camera axes (x right, y up, z back)",
                 "masks": "mask_path: colour seen; darp_object_mask_path: object support"}}
    cloud = survey.folder / CLOUD_FILES["fused"]
    if cloud.is_file():
        ply = read_ply(cloud)
        colours = (np.column_stack([ply.vertex[c] for c in ("red", "green", "blue")]).astype(np.uint8)
                   if "red" in ply.vertex else None)
        write_cloud_ply(out / "sparse_pc.ply", ply.points, colours=colours,
                        comments=[f"darp {survey.name}: the fused cloud, world frame, metres"])
        meta["ply_file_path"] = "sparse_pc.ply"
    write_json_atomic(out / "transforms.json", {**meta, "frames": frames})
    return {"frames": len(frames), "train": len(split[FUSE]), "val": len(split[HELDOUT])}


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
            "frames": [{"index": n, "frame_number": kf.frame_number, "split": kf.split, "t_s": kf.t_s,
                        "timestamp_ms": kf.timestamp_ms}
                       for n, kf in enumerate(keyframes)]})
        counts[arm] = len(keyframes)
    for name in (*CLOUD_FILES.values(), MESH_FILE):
        if (survey.folder / name).is_file():  # darp's own cloud and mesh, to compare a reconstruction with
            with atomic_path(out / name) as tmp:
                shutil.copyfile(survey.folder / name, tmp)
    return {"frames": counts}


def export_tum(survey: ProcessedSurvey, out: Path) -> dict[str, Any]:
    """Per arm: a TUM RGB-D sequence folder (keyframe images), darp's trajectory at every frame and, for a
    twin survey, the true one as ``groundtruth.txt``, and the calibration."""
    counts = {}
    for arm, keyframes in _by_arm(_keyframes(survey)).items():
        folder = out / arm
        rgb, depth = ["# color images", "# timestamp filename"], ["# depth maps", "# timestamp filename"]
        for kf in sorted(keyframes, key=lambda k: k.t_s):
            stamp = f"{kf.t_s:.6f}"
            write_png(folder / "rgb" / f"{stamp}.png", kf.rgb)
            write_png(folder / "depth" / f"{stamp}.png", depth_png(kf, TUM_DEPTH_UNITS_PER_M))
            rgb.append(f"{stamp} rgb/{stamp}.png")
            depth.append(f"{stamp} depth/{stamp}.png")
        write_lines(folder / "rgb.txt", rgb)
        write_lines(folder / "depth.txt", depth)
        trajectories = {TUM_GROUNDTRUTH: (true_poses(survey, arm), "the twin's true camera poses"),
                        TUM_ESTIMATE: (estimated_poses(survey, arm), "darp's camera poses (what processing used)")}
        if trajectories[TUM_ESTIMATE][0] is None:  # a processed folder without poses/: the keyframes' poses
            trajectories[TUM_ESTIMATE] = ((np.array([k.t_s for k in keyframes]),
                                           np.array([k.T_world_cam for k in keyframes])), "darp's keyframe poses")
        for name, (poses, what) in trajectories.items():
            if poses is None:
                continue
            order = np.argsort(np.asarray(poses[0], np.float64), kind="stable")
            write_tum(folder / name, [f"{float(poses[0][k]):.6f}" for k in order], np.asarray(poses[1])[order],
                      (f"# {what}: T_world_cam (camera-to-world, OpenCV optical frame), host seconds",
                       f"# {TUM_HEADER}"), fmt)
        i = keyframes[0].intrinsics
        write_lines(folder / "calibration.txt", [
            "# fx fy cx cy k1 k2 p1 p2 k3 (pixel centres at integers; depth PNG: 5000 per metre)",
            " ".join(fmt(v) for v in (i.fx, i.fy, i.ppx, i.ppy, *i.coeffs))])
        counts[arm] = len(keyframes)
    return {"frames": counts}


__all__ = ["export_nerfstudio", "export_open3d", "export_tum", "open3d_intrinsic"]
