"""Object-level exports of twin surveys: BOP (6D pose) and PCN/PoinTr-style completion pairs.

Both need the twin's ground truth (``truth/object.json``, ``truth/object.ply`` of the raw survey that
``results.json`` names). Conventions:

=========== ====================================================================================================
bop         ``models/obj_NNNNNN.ply`` (the true mesh in its object frame, **millimetres**) and
            ``models_info.json``; one scene per survey, ``test/NNNNNN/``: ``rgb/``, ``depth/`` (uint16 mm,
            ``depth_scale`` 1.0), ``scene_camera.json`` (``cam_K`` row-major with OpenCV's integer pixel
            centres, ``cam_R_w2c``/``cam_t_w2c`` world-to-camera in mm) and ``scene_gt.json``
            (``cam_R_m2c``/``cam_t_m2c``: model-to-camera, mm, OpenCV axes). ``scenes.json`` maps scene ids
            to surveys and object ids to names.
completion  PCN's layout: ``complete/<object>/<survey>.pcd`` (16384 points sampled on the true surface) and
            ``partial/<object>/<survey>/<name>.pcd``: one per keyframe (its object points), per arm
            (``arm110``, ``arm111``) and ``fused``; all in the object's canonical frame (``T_world_object``
            of the truth maps it to the world), metres, float32; ``pairs.json`` lists every pair.
=========== ====================================================================================================
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey, completion_pairs, read_object_truth
from darp.export._io import depth_png, write_pcd, write_png
from darp.formats.atomic import write_json_atomic
from darp.reconstruction.cloud_io import write_mesh_ply
from darp.reconstruction.keyframe_io import iter_keyframes

BOP_DEPTH_SCALE = 1.0  # depth PNG value * depth_scale = millimetres


def _flat(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a, np.float64).reshape(-1)]


def models_info(vertices_mm: np.ndarray) -> dict[str, float]:
    """BOP's per-model info: bounding box and diameter (largest vertex distance), millimetres."""
    lo, hi = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    from scipy.spatial import ConvexHull

    hull = vertices_mm[ConvexHull(vertices_mm).vertices] if len(vertices_mm) > 3 else vertices_mm
    diameter = float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)))
    return {"diameter": diameter, "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2])}


def export_bop(surveys: list[ProcessedSurvey], out: Path) -> dict[str, Any]:
    """A BOP dataset folder: models in mm and one scene per twin survey."""
    objects: dict[str, int] = {}
    infos: dict[str, Any] = {}
    scenes: dict[str, Any] = {}
    for scene_id, survey in enumerate(surveys, start=1):
        vertices, triangles, T_world_object, meta = read_object_truth(survey.require_truth("the bop export"))
        name = str(meta.get("name", survey.name))
        if name not in objects:
            objects[name] = len(objects) + 1
            v_mm = 1000.0 * vertices
            write_mesh_ply(out / "models" / f"obj_{objects[name]:06d}.ply", v_mm, triangles,
                           comments=[f"darp twin object {name}, millimetres, object frame"])
            infos[str(objects[name])] = models_info(v_mm)
        obj_id = objects[name]
        folder = out / "test" / f"{scene_id:06d}"
        cameras, gts, frames = {}, {}, []
        for im_id, kf in enumerate(iter_keyframes(survey.keyframes_dir)):
            T_cam_world = np.linalg.inv(np.asarray(kf.T_world_cam, np.float64))
            T_cam_object = T_cam_world @ T_world_object
            write_png(folder / "rgb" / f"{im_id:06d}.png", kf.rgb)
            write_png(folder / "depth" / f"{im_id:06d}.png", depth_png(kf, 1000.0 / BOP_DEPTH_SCALE))
            cameras[str(im_id)] = {"cam_K": _flat(kf.intrinsics.K), "depth_scale": BOP_DEPTH_SCALE,
                                   "cam_R_w2c": _flat(T_cam_world[:3, :3]),
                                   "cam_t_w2c": _flat(1000.0 * T_cam_world[:3, 3])}
            gts[str(im_id)] = [{"cam_R_m2c": _flat(T_cam_object[:3, :3]),
                                "cam_t_m2c": _flat(1000.0 * T_cam_object[:3, 3]), "obj_id": obj_id}]
            frames.append({"im_id": im_id, "arm": kf.arm, "frame_number": kf.frame_number, "split": kf.split})
        write_json_atomic(folder / "scene_camera.json", cameras)
        write_json_atomic(folder / "scene_gt.json", gts)
        scenes[f"{scene_id:06d}"] = {"survey": survey.name, "obj_id": obj_id, "images": frames}
    write_json_atomic(out / "models" / "models_info.json", infos)
    write_json_atomic(out / "scenes.json", {"objects": objects, "scenes": scenes})
    return {"scenes": len(scenes), "objects": len(objects)}


def export_completion(surveys: list[ProcessedSurvey], out: Path, complete_points: int = 16384,
                      seed: int = 0) -> dict[str, Any]:
    """PCN/PoinTr-style partial/complete pairs in each object's canonical frame."""
    pairs = []
    for survey in surveys:
        _, _, _, meta = read_object_truth(survey.require_truth("the completion export"))
        obj = str(meta.get("name", survey.name))
        complete_rel = f"complete/{obj}/{survey.name}.pcd"
        wrote_complete = False
        for pair in completion_pairs(survey.folder, complete_points=complete_points, seed=seed):
            if not wrote_complete:
                write_pcd(out / complete_rel, pair.complete)
                wrote_complete = True
            rel = f"partial/{obj}/{survey.name}/{pair.name.split('/', 1)[1]}.pcd"
            write_pcd(out / rel, pair.partial)
            pairs.append({"partial": rel, "complete": complete_rel, "kind": pair.kind, "object": obj,
                          "survey": survey.name, "points": len(pair.partial),
                          "T_world_object": np.asarray(pair.T_world_object).tolist()})
    write_json_atomic(out / "pairs.json", {"frame": "object (canonical), metres", "pairs": pairs})
    return {"pairs": len(pairs)}


__all__ = ["export_bop", "export_completion", "models_info"]
