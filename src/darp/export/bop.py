"""BOP export of twin surveys (6D object pose), in the BOP toolkit's scene-wise format.

Needs the twin's ground truth (``truth/object.json``, ``truth/object.ply`` of the raw survey that
``results.json`` names). Layout (``bop_toolkit_lib.dataset.bop_scenewise``)::

    camera.json                      fx fy cx cy width height depth_scale (the first image's camera; per-image
                                     cam_K in scene_camera.json is what counts: the two arms' cameras differ)
    models/obj_NNNNNN.ply            the true mesh in mm with vertex normals, origin at its bounding-box centre
    models/models_info.json          diameter, min_x/y/z, size_x/y/z (mm; min = -size / 2)
    test/NNNNNN/                     one scene per survey
        rgb/III.png  depth/III.png   colour aligned to depth; depth uint16 mm (depth_scale 1.0)
        gray/III.tiff                left infrared (the depth camera itself, so the same cam_K)
        mask/III_000000.png          the model's silhouette in the ground-truth pose (amodal)
        mask_visib/III_000000.png    its visible part: BOP's bop19 test, delta 15 mm, against the depth image
        scene_camera.json            cam_K (row-major, OpenCV's integer pixel centres), depth_scale,
                                     cam_R_w2c / cam_t_w2c (world-to-camera, mm)
        scene_gt.json                cam_R_m2c / cam_t_m2c (model-to-camera, mm), obj_id
        scene_gt_info.json           px_count_all/valid/visib, visib_fract, bbox_obj, bbox_visib
    scenes.json                      darp's record: scene -> survey, object names -> ids, per image the arm,
                                     frame number, split, host time t_s and camera timestamp_ms

The masks and ``scene_gt_info.json`` follow the toolkit's ``scripts/calc_gt_info.py`` and
``calc_gt_masks.py``: the model is rendered (here by ray casting with Open3D) on a canvas three times the
image size, so ``px_count_all`` and ``bbox_obj`` count the parts outside the image.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.dataset import ProcessedSurvey, read_object_truth
from darp.export._io import depth_png, write_image, write_png
from darp.formats.atomic import write_json_atomic
from darp.reconstruction.cloud_io import write_mesh_ply
from darp.reconstruction.keyframe_io import Keyframe, iter_keyframes

BOP_DEPTH_SCALE = 1.0  # depth PNG value * depth_scale = millimetres
VISIB_DELTA_MM = 15.0  # calc_gt_info.py's tolerance of the visibility test


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


@dataclass
class BopModel:
    """One object's model: vertices (m) in the model frame (origin at the bounding-box centre of the
    twin's object frame), triangles, ``T_object_model`` and Open3D's ray-casting scene of it."""

    obj_id: int
    vertices_m: np.ndarray
    triangles: np.ndarray
    T_object_model: np.ndarray
    scene: Any

    @classmethod
    def from_truth(cls, obj_id: int, vertices_obj: np.ndarray, triangles: np.ndarray) -> BopModel:
        import open3d as o3d

        centre = 0.5 * (vertices_obj.min(axis=0) + vertices_obj.max(axis=0))
        T_object_model = np.eye(4)
        T_object_model[:3, 3] = centre
        vertices = np.asarray(vertices_obj - centre, np.float64)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor.from_numpy(vertices.astype(np.float32)),
                            o3d.core.Tensor.from_numpy(np.asarray(triangles, np.uint32)))
        return cls(obj_id, vertices, np.asarray(triangles, np.int64), T_object_model, scene)

    def write(self, path: Path, name: str) -> dict[str, float]:
        """The model PLY in millimetres with vertex normals (the toolkit's renderer shades with them)."""
        import trimesh

        normals = trimesh.Trimesh(self.vertices_m, self.triangles, process=False).vertex_normals
        v_mm = 1000.0 * self.vertices_m
        write_mesh_ply(path, v_mm, self.triangles, normals=np.asarray(normals, np.float64),
                       comments=[f"darp twin object {name}, millimetres, origin at the bounding-box centre"])
        return models_info(v_mm)

    def render_depth_m(self, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """Z-depth (m, 0 = no model) of the model on a canvas of 3x the image: rows ``-height..2*height``,
        columns ``-width..2*width`` (the image is the middle third), OpenCV pixel centres."""
        import open3d as o3d

        canvas = np.zeros((3 * height, 3 * width), np.float32)
        p_cam = self.vertices_m @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
        front = p_cam[:, 2] > 1e-6
        if not front.any():
            return canvas
        if front.all():  # the model's pixels lie within its vertices' projected bounding box
            u = K[0, 0] * p_cam[:, 0] / p_cam[:, 2] + K[0, 2]
            v = K[1, 1] * p_cam[:, 1] / p_cam[:, 2] + K[1, 2]
            u0, u1 = (int(np.clip(np.floor(u.min()) - 1, -width, 2 * width)),
                      int(np.clip(np.ceil(u.max()) + 2, -width, 2 * width)))
            v0, v1 = (int(np.clip(np.floor(v.min()) - 1, -height, 2 * height)),
                      int(np.clip(np.ceil(v.max()) + 2, -height, 2 * height)))
        else:
            u0, u1, v0, v1 = -width, 2 * width, -height, 2 * height
        if u1 <= u0 or v1 <= v0:
            return canvas
        uu, vv = np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
        rays_cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1)
        T_model_cam = np.linalg.inv(T_cam_model)
        directions = rays_cam.reshape(-1, 3) @ T_model_cam[:3, :3].T  # camera z = 1: t_hit is the z-depth
        origins = np.broadcast_to(T_model_cam[:3, 3], directions.shape)
        rays = o3d.core.Tensor.from_numpy(np.hstack([origins, directions]).astype(np.float32))
        t_hit = self.scene.cast_rays(rays)["t_hit"].numpy().reshape(uu.shape)
        canvas[v0 + height:v1 + height, u0 + width:u1 + width] = np.where(np.isfinite(t_hit), t_hit, 0.0)
        return canvas


def _distance_image(depth: np.ndarray, K: np.ndarray, u0: int = 0, v0: int = 0) -> np.ndarray:
    """Distance from the camera centre (BOP's ``depth_im_to_dist_im``) of a z-depth image whose top-left
    pixel is (u0, v0)."""
    h, w = depth.shape
    uu, vv = np.meshgrid(np.arange(u0, u0 + w), np.arange(v0, v0 + h))
    scale = np.sqrt(((uu - K[0, 2]) / K[0, 0]) ** 2 + ((vv - K[1, 2]) / K[1, 1]) ** 2 + 1.0)
    return np.asarray(depth * scale, np.float64)


def _bbox(xs: np.ndarray, ys: np.ndarray) -> list[int]:
    """BOP's (x, y, w, h) of pixel coordinates (``misc.calc_2d_bbox``, unclipped)."""
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


def gt_masks_and_info(model: BopModel, kf: Keyframe, T_cam_model: np.ndarray,
                      depth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(mask, mask_visib, scene_gt_info entry) of one ground-truth instance, as calc_gt_info.py computes them
    (bop19 visibility: the model is visible where it is at most delta behind the measured surface, or where
    there is no measurement)."""
    i = kf.intrinsics
    K, w, h = i.K, i.width, i.height
    large = 1000.0 * model.render_depth_m(T_cam_model, K, w, h)
    gt = large[h:2 * h, w:2 * w]
    dist_gt = _distance_image(gt, K)
    dist_im = _distance_image(depth_mm.astype(np.float64), K)
    mask = dist_gt > 0
    visib = mask & ((dist_gt - dist_im <= VISIB_DELTA_MM) | (dist_im == 0))
    px_all, px_visib = int((large > 0).sum()), int(visib.sum())
    bbox_obj, bbox_visib = [-1] * 4, [-1] * 4
    if px_visib > 0:
        ys, xs = np.nonzero(large > 0)
        bbox_obj = _bbox(xs - w, ys - h)
        ys, xs = np.nonzero(visib)
        bbox_visib = _bbox(xs, ys)
    info = {"px_count_all": px_all, "px_count_valid": int((dist_im[mask] > 0).sum()), "px_count_visib": px_visib,
            "visib_fract": float(px_visib / px_all) if px_all else 0.0, "bbox_obj": bbox_obj,
            "bbox_visib": bbox_visib}
    return mask, visib, info


def camera_json(kf: Keyframe) -> dict[str, float]:
    """The dataset's ``camera.json`` from one keyframe's camera."""
    i = kf.intrinsics
    return {"cx": float(i.ppx), "cy": float(i.ppy), "fx": float(i.fx), "fy": float(i.fy), "width": int(i.width),
            "height": int(i.height), "depth_scale": BOP_DEPTH_SCALE}


def export_bop(surveys: list[ProcessedSurvey], out: Path) -> dict[str, Any]:
    """A BOP dataset folder: models in mm and one scene per twin survey (see the module docstring)."""
    models: dict[str, BopModel] = {}
    infos: dict[str, Any] = {}
    scenes: dict[str, Any] = {}
    camera: dict[str, float] | None = None
    for scene_id, survey in enumerate(surveys, start=1):
        vertices, triangles, T_world_object, meta = read_object_truth(survey.require_truth("the bop export"))
        name = str(meta.get("name", survey.name))
        if name not in models:
            models[name] = model = BopModel.from_truth(len(models) + 1, vertices, triangles)
            infos[str(model.obj_id)] = model.write(out / "models" / f"obj_{model.obj_id:06d}.ply", name)
        model = models[name]
        T_world_model = T_world_object @ model.T_object_model
        folder = out / "test" / f"{scene_id:06d}"
        cameras, gts, gt_infos, frames = {}, {}, {}, []
        for im_id, kf in enumerate(iter_keyframes(survey.keyframes_dir)):
            camera = camera or camera_json(kf)
            T_cam_world = np.linalg.inv(np.asarray(kf.T_world_cam, np.float64))
            T_cam_model = T_cam_world @ T_world_model
            depth = depth_png(kf, 1000.0 / BOP_DEPTH_SCALE)
            write_png(folder / "rgb" / f"{im_id:06d}.png", kf.rgb)
            write_png(folder / "depth" / f"{im_id:06d}.png", depth)
            write_image(folder / "gray" / f"{im_id:06d}.tiff", kf.ir_left)
            mask, visib, info = gt_masks_and_info(model, kf, T_cam_model, depth * BOP_DEPTH_SCALE)
            gt_infos[str(im_id)] = [info]
            write_png(folder / "mask" / f"{im_id:06d}_000000.png", mask.astype(np.uint8) * 255)
            write_png(folder / "mask_visib" / f"{im_id:06d}_000000.png", visib.astype(np.uint8) * 255)
            cameras[str(im_id)] = {"cam_K": _flat(kf.intrinsics.K), "depth_scale": BOP_DEPTH_SCALE,
                                   "cam_R_w2c": _flat(T_cam_world[:3, :3]),
                                   "cam_t_w2c": _flat(1000.0 * T_cam_world[:3, 3])}
            gts[str(im_id)] = [{"cam_R_m2c": _flat(T_cam_model[:3, :3]),
                                "cam_t_m2c": _flat(1000.0 * T_cam_model[:3, 3]), "obj_id": model.obj_id}]
            frames.append({"im_id": im_id, "arm": kf.arm, "frame_number": kf.frame_number, "split": kf.split,
                           "t_s": kf.t_s, "timestamp_ms": kf.timestamp_ms})
        write_json_atomic(folder / "scene_camera.json", cameras)
        write_json_atomic(folder / "scene_gt.json", gts)
        write_json_atomic(folder / "scene_gt_info.json", gt_infos)
        scenes[f"{scene_id:06d}"] = {"survey": survey.name, "obj_id": model.obj_id, "images": frames,
                                     "T_world_model": T_world_model.tolist()}
    write_json_atomic(out / "models" / "models_info.json", infos)
    if camera is not None:
        write_json_atomic(out / "camera.json", camera)
    write_json_atomic(out / "scenes.json", {"objects": {n: m.obj_id for n, m in models.items()}, "scenes": scenes})
    return {"scenes": len(scenes), "objects": len(models)}


__all__ = ["BOP_DEPTH_SCALE", "BopModel", "camera_json", "export_bop", "gt_masks_and_info", "models_info"]
