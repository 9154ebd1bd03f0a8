"""darp export: every format opened by its consumer's library where it installs (pycolmap, Open3D), else
checked by reprojection against darp's own back-projection, on a processed twin survey."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from darp.cli._app import run
from darp.dataset import read_object_truth
from darp.reconstruction.backproject import world_points
from darp.reconstruction.keyframe_io import Keyframe, load_keyframes

pytestmark = pytest.mark.slow  # needs the processed twin survey (about 40 s, once per session)


@pytest.fixture(scope="module")
def keyframes(processed_path: Path) -> dict[str, Keyframe]:
    return {f"{kf.arm}_{kf.frame_number:06d}": kf for kf in load_keyframes(processed_path / "keyframes")}


@pytest.fixture(scope="module")
def exported(processed_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exports")
    for fmt in ("nerfstudio", "colmap", "open3d", "tum", "bop", "completion"):
        assert run(["export", fmt, str(processed_path), "--out", str(out / fmt)]) == 0, fmt
    return out


def object_pixels(kf: Keyframe, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """(pixel (N, 2) u, v; world points (N, 3) by darp's back-projection) of valid object-support pixels."""
    index = np.flatnonzero((kf.depth > 0).reshape(-1) & kf.support_mask.reshape(-1))
    index = index[np.linspace(0, len(index) - 1, min(n, len(index))).astype(int)]
    assert len(index) > 20
    w = kf.intrinsics.width
    pts = world_points(kf.depth_m, kf.intrinsics, kf.T_world_cam, index).astype(np.float64)
    return np.stack([index % w, index // w], axis=1).astype(np.float64), pts


def test_colmap_model_opens_in_pycolmap_and_reprojects(exported: Path, keyframes: dict[str, Keyframe]) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(exported / "colmap" / "sparse" / "0"))
    assert len(rec.images) == len(keyframes) and len(rec.cameras) == 2 and len(rec.points3D) == 0
    for image in rec.images.values():
        kf = keyframes[Path(image.name).stem]
        assert (exported / "colmap" / "images" / image.name).is_file()
        uv, pts = object_pixels(kf)
        cam_from_world = image.cam_from_world()
        in_cam = np.array([cam_from_world * p for p in pts])
        projected = rec.cameras[image.camera_id].img_from_cam(in_cam)
        # COLMAP's pixel centres are at +0.5; darp's at integers
        np.testing.assert_allclose(projected - 0.5, uv, atol=2e-3)
        np.testing.assert_allclose(cam_from_world.matrix(), np.linalg.inv(kf.T_world_cam)[:3], atol=1e-9)


def test_nerfstudio_rays_hit_darps_points(exported: Path, keyframes: dict[str, Keyframe]) -> None:
    meta = json.loads((exported / "nerfstudio" / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and len(meta["frames"]) == len(keyframes)
    for frame in meta["frames"]:
        kf = keyframes[Path(frame["file_path"]).stem]
        c2w = np.array(frame["transform_matrix"])
        uv, pts = object_pixels(kf)
        # nerfstudio's ray through pixel (u, v): centre at +0.5, OpenGL camera (y up, looking down -z)
        d = np.stack([(uv[:, 0] + 0.5 - frame["cx"]) / frame["fl_x"], -(uv[:, 1] + 0.5 - frame["cy"]) / frame["fl_y"],
                      -np.ones(len(uv))], axis=1)
        depth = cv2.imread(str(exported / "nerfstudio" / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)] * meta["depth_unit_scale_factor"]
        hits = c2w[:3, 3] + (d * z[:, None]) @ c2w[:3, :3].T
        np.testing.assert_allclose(hits, pts, atol=1e-5)  # depth in mm: the raw Z16 values, exact
        rgb = cv2.imread(str(exported / "nerfstudio" / frame["file_path"]))[:, :, ::-1]
        np.testing.assert_array_equal(rgb, kf.rgb)


def test_open3d_reads_intrinsics_trajectory_and_rebuilds_the_points(exported: Path,
                                                                    keyframes: dict[str, Keyframe]) -> None:
    for arm in ("arm110", "arm111"):
        folder = exported / "open3d" / arm
        intrinsic = o3d.io.read_pinhole_camera_intrinsic(str(folder / "camera_intrinsic.json"))
        trajectory = o3d.io.read_pinhole_camera_trajectory(str(folder / "trajectory.log"))
        frames = json.loads((folder / "frames.json").read_text())["frames"]
        assert len(trajectory.parameters) == len(frames) > 0
        for n in (0, len(frames) - 1):
            kf = keyframes[f"{arm}_{frames[n]['frame_number']:06d}"]
            np.testing.assert_allclose(trajectory.parameters[n].extrinsic, np.linalg.inv(kf.T_world_cam), atol=1e-9)
            colour = o3d.io.read_image(str(folder / "color" / f"{n:06d}.png"))
            depth = o3d.io.read_image(str(folder / "depth" / f"{n:06d}.png"))
            rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(colour, depth, depth_scale=1000.0,
                                                                      depth_trunc=10.0,
                                                                      convert_rgb_to_intensity=False)
            cloud = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, intrinsic, trajectory.parameters[n].extrinsic)
            _, pts = object_pixels(kf)
            gap, _ = cKDTree(np.asarray(cloud.points)).query(pts)
            assert gap.max() < 1e-5


def test_tum_groundtruth_is_the_camera_to_world_pose(exported: Path, keyframes: dict[str, Keyframe]) -> None:
    for arm in ("arm110", "arm111"):
        folder = exported / "tum" / arm
        gt = [line.split() for line in (folder / "groundtruth.txt").read_text().splitlines() if line[0] != "#"]
        depth_list = [line.split() for line in (folder / "depth.txt").read_text().splitlines() if line[0] != "#"]
        mine = sorted((kf for kf in keyframes.values() if kf.arm == arm), key=lambda k: k.t_s)
        assert len(gt) == len(depth_list) == len(mine)
        fx, fy, cx, cy = (float(v) for v in (folder / "calibration.txt").read_text().splitlines()[1].split()[:4])
        for row, (stamp, name), kf in zip(gt, depth_list, mine, strict=True):
            assert row[0] == stamp and abs(float(stamp) - kf.t_s) < 1e-6
            T = np.eye(4)
            T[:3, 3] = [float(v) for v in row[1:4]]
            T[:3, :3] = Rotation.from_quat([float(v) for v in row[4:8]]).as_matrix()  # qx qy qz qw
            np.testing.assert_allclose(T, kf.T_world_cam, atol=1e-9)
            depth = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED) / 5000.0  # TUM: 5000 per metre
            uv, pts = object_pixels(kf, 50)
            z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
            cam = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
            np.testing.assert_allclose(cam @ T[:3, :3].T + T[:3, 3], pts, atol=1e-5)


def test_bop_pose_projects_the_model_onto_the_object(exported: Path, keyframes: dict[str, Keyframe],
                                                     survey_path: Path) -> None:
    import trimesh

    root = exported / "bop"
    scenes = json.loads((root / "scenes.json").read_text())
    model = trimesh.load(root / "models" / "obj_000001.ply", process=False)
    vertices_obj, _, T_world_object, _ = read_object_truth(survey_path / "truth")
    np.testing.assert_allclose(np.asarray(model.vertices), 1000.0 * vertices_obj, atol=1e-2)  # millimetres
    info = json.loads((root / "models" / "models_info.json").read_text())["1"]
    assert info["diameter"] > info["size_x"] > 0
    scene = root / "test" / "000001"
    cameras = json.loads((scene / "scene_camera.json").read_text())
    gts = json.loads((scene / "scene_gt.json").read_text())
    images = scenes["scenes"]["000001"]["images"]
    assert len(images) == len(cameras) == len(gts) == len(keyframes)
    for entry in images:
        kf = keyframes[f"{entry['arm']}_{entry['frame_number']:06d}"]
        cam, gt = cameras[str(entry["im_id"])], gts[str(entry["im_id"])][0]
        K, R, t = (np.array(cam["cam_K"]).reshape(3, 3), np.array(gt["cam_R_m2c"]).reshape(3, 3),
                   np.array(gt["cam_t_m2c"]))
        # BOP: x_cam_mm = R x_model_mm + t; darp: the same point through T_world_object and T_world_cam
        p_cam = np.asarray(model.vertices) @ R.T + t
        ref = (np.linalg.inv(kf.T_world_cam) @ T_world_object)
        p_ref = 1000.0 * (vertices_obj @ ref[:3, :3].T + ref[:3, 3])
        np.testing.assert_allclose(p_cam, p_ref, atol=1e-2)
        # the measured depth agrees with the posed model where the model's surface is seen (twin noise: mm)
        uv, pts = object_pixels(kf, 100)
        depth = cv2.imread(str(scene / "depth" / f"{entry['im_id']:06d}.png"), cv2.IMREAD_UNCHANGED)
        z_mm = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)] * cam["depth_scale"]
        R_w2c, t_w2c = np.array(cam["cam_R_w2c"]).reshape(3, 3), np.array(cam["cam_t_w2c"])
        np.testing.assert_allclose(z_mm, (1000.0 * pts @ R_w2c.T + t_w2c)[:, 2], atol=0.05)
        assert gt["obj_id"] == 1 and K[0, 2] == kf.intrinsics.ppx


def test_completion_pairs_lie_on_the_true_surface(exported: Path) -> None:
    root = exported / "completion"
    pairs = json.loads((root / "pairs.json").read_text())["pairs"]
    kinds = {p["kind"] for p in pairs}
    assert kinds == {"keyframe", "arm", "fused"}
    complete = np.asarray(o3d.io.read_point_cloud(str(root / pairs[0]["complete"])).points)
    assert complete.shape == (16384, 3)
    tree = cKDTree(complete)
    for pair in pairs:
        if pair["kind"] == "keyframe" and pair["points"] < 50:
            continue
        partial = np.asarray(o3d.io.read_point_cloud(str(root / pair["partial"])).points)
        assert len(partial) == pair["points"]
        gap, _ = tree.query(partial)
        # object frame: the partial sits on the complete surface (twin depth noise, sampling spacing ~1 mm)
        assert np.median(gap) < 0.004, (pair["partial"], np.median(gap))


def test_export_of_a_non_processed_folder_is_one_error_line(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["export", "tum", str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("darp: error:") and "no processed survey" in err


def test_export_formats_mirror_the_library() -> None:
    from darp.cli._options import ExportFormat
    from darp.export import FORMATS

    assert [f.value for f in ExportFormat] == list(FORMATS)
