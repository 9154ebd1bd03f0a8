"""darp export bop / completion: the files the BOP toolkit and PoinTr read, by their documented layouts, on
the processed twin survey. Neither installs into darp's environment (bop_toolkit_lib is not on PyPI and
pins numpy < 2; PoinTr is a repository with CUDA extensions), so these tests follow their loaders' own
path templates and keys: ``bop_scenewise.load_scene_data`` / ``load_image_data`` and ``inout.load_ply``,
``calc_gt_info.py``'s keys; PoinTr's ``PCN.yaml`` templates and ``PCNDataset`` file list."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from darp.cli._app import run
from darp.dataset import read_object_truth
from darp.evaluation.point_to_mesh import point_to_mesh_distances
from darp.reconstruction.backproject import world_points
from darp.reconstruction.keyframe_io import Keyframe, load_keyframes

pytestmark = pytest.mark.slow  # needs the processed twin survey


@pytest.fixture(scope="module")
def keyframes(processed_path: Path) -> dict[str, Keyframe]:
    return {f"{kf.arm}_{kf.frame_number:06d}": kf for kf in load_keyframes(processed_path / "keyframes")}


@pytest.fixture(scope="module")
def exported(processed_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exports")
    for fmt in ("bop", "completion"):
        assert run(["export", fmt, str(processed_path), "--out", str(out / fmt)]) == 0, fmt
    return out


def test_bop_scene_has_every_file_the_toolkit_loads(exported: Path, keyframes: dict[str, Keyframe]) -> None:
    root, scene = exported / "bop", exported / "bop" / "test" / "000001"
    camera = json.loads((root / "camera.json").read_text())
    assert set(camera) >= {"cx", "cy", "fx", "fy", "width", "height", "depth_scale"}  # inout.load_cam_params
    cameras, gts, infos = (json.loads((scene / f).read_text()) for f in
                           ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"))  # load_scene_data
    assert set(cameras) == set(gts) == set(infos) and len(cameras) == len(keyframes)
    for im_id in cameras:
        (info,) = infos[im_id]
        assert set(info) == {"px_count_all", "px_count_valid", "px_count_visib", "visib_fract", "bbox_obj",
                             "bbox_visib"}
        i = int(im_id)
        for folder, name in (("rgb", f"{i:06d}.png"), ("depth", f"{i:06d}.png"), ("gray", f"{i:06d}.tiff"),
                             ("mask", f"{i:06d}_000000.png"), ("mask_visib", f"{i:06d}_000000.png")):
            assert (scene / folder / name).is_file(), (folder, name)
        mask = cv2.imread(str(scene / "mask" / f"{i:06d}_000000.png"), cv2.IMREAD_UNCHANGED) > 0
        visib = cv2.imread(str(scene / "mask_visib" / f"{i:06d}_000000.png"), cv2.IMREAD_UNCHANGED) > 0
        assert not (visib & ~mask).any() and visib.sum() == info["px_count_visib"] > 0
        assert info["px_count_all"] >= mask.sum() and 0 < info["visib_fract"] <= 1
        x, y, w, h = info["bbox_visib"]
        ys, xs = np.nonzero(visib)
        assert (x, y, x + w, y + h) == (xs.min(), ys.min(), xs.max(), ys.max())


def test_bop_model_is_centred_with_normals_and_masks_sit_on_the_object(exported: Path, survey_path: Path,
                                                                       keyframes: dict[str, Keyframe]) -> None:
    import trimesh

    root, scene = exported / "bop", exported / "bop" / "test" / "000001"
    header = (root / "models" / "obj_000001.ply").read_bytes().split(b"end_header")[0].decode()
    assert all(f"property float {n}" in header for n in ("nx", "ny", "nz"))  # the renderer's RGB mode needs them
    assert "property list uchar int vertex_indices" in header  # what inout.load_ply parses
    model = trimesh.load(root / "models" / "obj_000001.ply", process=False)
    v = np.asarray(model.vertices)
    info = json.loads((root / "models" / "models_info.json").read_text())["1"]
    np.testing.assert_allclose(v.min(axis=0) + v.max(axis=0), 0, atol=1e-3)  # origin at the bbox centre (mm)
    for axis in "xyz":
        assert info[f"min_{axis}"] == pytest.approx(-info[f"size_{axis}"] / 2, abs=1e-3)
    assert info["diameter"] > info["size_x"] > 0
    vertices_obj, _, T_world_object, _ = read_object_truth(survey_path / "truth")
    centre = (vertices_obj.min(0) + vertices_obj.max(0)) / 2
    np.testing.assert_allclose(v, 1000.0 * (vertices_obj - centre), atol=1e-2)  # the true mesh, in mm
    images = json.loads((root / "scenes.json").read_text())["scenes"]["000001"]["images"]
    cameras = json.loads((scene / "scene_camera.json").read_text())
    gts = json.loads((scene / "scene_gt.json").read_text())
    mesh = trimesh.load(survey_path / "truth" / "object.ply", process=False, force="mesh")
    for entry in images:
        kf = keyframes[f"{entry['arm']}_{entry['frame_number']:06d}"]
        assert entry["t_s"] == kf.t_s
        cam, gt = cameras[str(entry["im_id"])], gts[str(entry["im_id"])][0]
        R, t = np.array(gt["cam_R_m2c"]).reshape(3, 3), np.array(gt["cam_t_m2c"])
        # BOP: x_cam_mm = R x_model_mm + t; darp: the same vertex through T_world_object and T_world_cam
        p_cam = v @ R.T + t
        T_cam_object = np.linalg.inv(kf.T_world_cam) @ T_world_object
        p_ref = 1000.0 * ((v / 1000.0 + centre) @ T_cam_object[:3, :3].T + T_cam_object[:3, 3])
        np.testing.assert_allclose(p_cam, p_ref, atol=1e-2)
        # the visible mask's measured points lie on the true surface; the depth PNG is darp's depth in mm
        visib = cv2.imread(str(scene / "mask_visib" / f"{entry['im_id']:06d}_000000.png"), cv2.IMREAD_UNCHANGED) > 0
        index = np.flatnonzero(visib.reshape(-1) & (kf.depth > 0).reshape(-1))
        pts = world_points(kf.depth_m, kf.intrinsics, kf.T_world_cam, index).astype(np.float64)
        assert np.median(point_to_mesh_distances(pts, np.asarray(mesh.vertices), np.asarray(mesh.faces))) < 0.004
        depth = cv2.imread(str(scene / "depth" / f"{entry['im_id']:06d}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(depth.reshape(-1)[index] * cam["depth_scale"] / 1000.0,
                                   kf.depth_m.reshape(-1)[index], atol=5e-4)
        gray = cv2.imread(str(scene / "gray" / f"{entry['im_id']:06d}.tiff"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(gray, kf.ir_left)


def _pointr_config(path: Path) -> dict[str, str]:
    return dict(line.split(": ", 1) for line in path.read_text().splitlines())


def test_completion_is_pcn_as_pointr_reads_it(exported: Path, survey_path: Path) -> None:
    """PoinTr's PCNDataset: for every model of PCN.json's subsets, partials ``00`` .. ``07`` (train) or ``00``
    (val, test) and the complete cloud of N_POINTS, read with Open3D (PoinTr's IO for .pcd)."""
    root = exported / "completion"
    config = _pointr_config(root / "PCN.yaml")
    assert config["N_POINTS"] == "16384" and config["N_RENDERINGS"] == "8"
    categories = json.loads(Path(config["CATEGORY_FILE_PATH"]).read_text())
    pairs = json.loads((root / "pairs.json").read_text())
    assert categories[0]["taxonomy_name"] == "cube" and categories[0]["train"] == [survey_path.name]
    _, _, T_world_object, _ = read_object_truth(survey_path / "truth")
    mesh = o3d.io.read_triangle_mesh(str(survey_path / "truth" / "object.ply"))
    checked = 0
    for category in categories:
        for subset in ("train", "val", "test"):
            for model in category[subset]:
                complete = np.asarray(o3d.io.read_point_cloud(
                    config["COMPLETE_POINTS_PATH"] % (subset, category["taxonomy_id"], model)).points)
                assert complete.shape == (16384, 3)
                np.testing.assert_allclose(complete.min(0) + complete.max(0), 0, atol=0.004)  # centred model frame
                T_world_model = np.array(next(p for p in pairs["pairs"] if p["survey"] == model)["T_world_model"])
                world = complete @ T_world_model[:3, :3].T + T_world_model[:3, 3]
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
                assert scene.compute_distance(world.astype(np.float32)).numpy().max() < 1e-5
                for i in range(8 if subset == "train" else 1):
                    partial = np.asarray(o3d.io.read_point_cloud(
                        config["PARTIAL_POINTS_PATH"] % (subset, category["taxonomy_id"], model, i)).points)
                    assert len(partial) >= pairs["min_partial_points"]
                    pw = (partial @ T_world_model[:3, :3].T + T_world_model[:3, 3]).astype(np.float32)
                    assert np.median(scene.compute_distance(pw).numpy()) < 0.004  # on the true surface (twin noise)
                    checked += 1
    assert checked == 8
    kept = [p for p in pairs["pairs"] if p["kind"] == "keyframe"]
    assert all(p["points"] >= pairs["min_partial_points"] for p in kept)
    assert all(d["points"] < pairs["min_partial_points"] for d in pairs["dropped"])
    assert {p["kind"] for p in pairs["pairs"]} == {"keyframe", "arm", "fused"}
