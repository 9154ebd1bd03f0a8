"""darp export: every format opened by its consumer's library where it installs (pycolmap, Open3D), else
checked by its documented file conventions and by reprojection against darp's own back-projection, on a
processed twin survey (the BOP toolkit, nerfstudio and PoinTr: tests/test_export_layouts.py)."""

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
from darp.reconstruction.backproject import world_points
from darp.reconstruction.keyframe_io import Keyframe, load_keyframes

pytestmark = pytest.mark.slow  # needs the processed twin survey (about 40 s, once per session)


@pytest.fixture(scope="module")
def keyframes(processed_path: Path) -> dict[str, Keyframe]:
    return {f"{kf.arm}_{kf.frame_number:06d}": kf for kf in load_keyframes(processed_path / "keyframes")}


@pytest.fixture(scope="module")
def exported(processed_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exports")
    for fmt in ("nerfstudio", "colmap", "open3d", "tum"):
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


def test_colmap_feature_extraction_runs_on_the_exported_database_as_is(exported: Path, tmp_path: Path,
                                                                        keyframes: dict[str, Keyframe]) -> None:
    """No camera-model option: pycolmap's default extraction keeps the database's OPENCV cameras, so the
    known-pose triangulation that follows accepts the model (a fresh database would get SIMPLE_RADIAL)."""
    import shutil

    pycolmap = pytest.importorskip("pycolmap")
    root = tmp_path / "colmap"
    shutil.copytree(exported / "colmap", root)
    database = str(root / "database.db")
    pycolmap.extract_features(database, str(root / "images"))
    pycolmap.match_exhaustive(database)
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    db = pycolmap.Database.open(database)
    try:
        assert {c.camera_id: c.model.name for c in db.read_all_cameras()} == {1: "OPENCV", 2: "OPENCV"}
        images = {im.image_id: im for im in db.read_all_images()}
        assert {i: (im.name, im.camera_id) for i, im in images.items()} == {
            i: (im.name, im.camera_id) for i, im in rec.images.items()}
        assert sum(db.num_keypoints_for_image(i) for i in images) > 0
    finally:
        db.close()
    (root / "triangulated").mkdir()
    pycolmap.triangulate_points(rec, database, str(root / "images"), str(root / "triangulated"))
    # COLMAP's own reader of its dense depth maps: darp's metric depth, exactly
    for name in ("arm110_000033.png", "arm111_000163.png"):
        depth = pycolmap.DepthMap()
        depth.read(str(exported / "colmap" / "stereo" / "depth_maps" / f"{name}.geometric.bin"))
        np.testing.assert_array_equal(depth.to_array(), keyframes[Path(name).stem].depth_m)
        mask = cv2.imread(str(exported / "colmap" / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(mask > 0, keyframes[Path(name).stem].rgb.any(axis=2))
    frames = json.loads((exported / "colmap" / "frames.json").read_text())["frames"]
    assert all(abs(f["t_s"] - keyframes[Path(f["name"]).stem].t_s) < 1e-9 for f in frames)


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


def test_nerfstudio_dataparser_fields_split_masks_and_seed_cloud(exported: Path,
                                                                 keyframes: dict[str, Keyframe]) -> None:
    """What nerfstudio's own dataparser (nerfstudio_dataparser.py, 1.1.5) reads: ``{split}_filenames`` must
    name frames' ``file_path`` for train, val and test alike once one is given; ``mask_path`` is one channel,
    nonzero = sample; ``ply_file_path`` a cloud Open3D reads with colours."""
    root = exported / "nerfstudio"
    meta = json.loads((root / "transforms.json").read_text())
    files = {f["file_path"]: f for f in meta["frames"]}
    for split, darp_split in (("train", "fuse"), ("val", "heldout"), ("test", "heldout")):
        names = meta[f"{split}_filenames"]
        assert names and set(names) <= set(files)
        assert {n for n, f in files.items() if f["darp_split"] == darp_split} == set(names), split
    for frame in meta["frames"]:
        kf = keyframes[Path(frame["file_path"]).stem]
        mask = cv2.imread(str(root / frame["mask_path"]), cv2.IMREAD_UNCHANGED)
        assert mask.ndim == 2 and mask.dtype == np.uint8
        np.testing.assert_array_equal(mask > 0, kf.rgb.any(axis=2))  # black (unseen) colour is never sampled
        obj = cv2.imread(str(root / frame["darp_object_mask_path"]), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(obj > 0, kf.support_mask)
        np.testing.assert_array_equal(cv2.imread(str(root / frame["darp_ir_path"]), cv2.IMREAD_UNCHANGED), kf.ir_left)
        assert frame["darp_t_s"] == kf.t_s
    seed = o3d.io.read_point_cloud(str(root / meta["ply_file_path"]))
    assert len(seed.points) > 100 and seed.has_colors()


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


def test_open3d_voxel_block_grid_rebuilds_darps_mesh_from_the_export(exported: Path) -> None:
    """Open3D's tensor TSDF (VoxelBlockGrid; the legacy ScalableTSDFVolume of Open3D 0.20 returns an empty
    mesh) on the exported RGB-D and trajectory lands on darp's own mesh, which the export carries as PLY."""
    import open3d.core as o3c

    root = exported / "open3d"
    mesh = o3d.io.read_triangle_mesh(str(root / "mesh.ply"))
    fused = o3d.io.read_point_cloud(str(root / "fused.ply"))
    assert len(mesh.triangles) > 0 and len(fused.points) > 0 and fused.has_colors()
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
                                         attr_channels=((1), (1)), voxel_size=0.003, block_resolution=8,
                                         block_count=20000)
    for arm in ("arm110", "arm111"):
        K = o3c.Tensor(o3d.io.read_pinhole_camera_intrinsic(str(root / arm / "camera_intrinsic.json"))
                       .intrinsic_matrix, o3c.float64)
        trajectory = o3d.io.read_pinhole_camera_trajectory(str(root / arm / "trajectory.log"))
        for n, camera in enumerate(trajectory.parameters):
            depth = o3d.t.io.read_image(str(root / arm / "depth" / f"{n:06d}.png"))
            extrinsic = o3c.Tensor(camera.extrinsic, o3c.float64)
            blocks = grid.compute_unique_block_coordinates(depth, K, extrinsic, 1000.0, 0.45)
            grid.integrate(blocks, depth, K, extrinsic, 1000.0, 0.45)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(grid.extract_triangle_mesh().to_legacy()))
    gap = scene.compute_distance(o3c.Tensor(np.asarray(mesh.vertices, np.float32))).numpy()
    assert np.median(gap) < 0.002, np.median(gap)  # TSDF at 3 mm voxels vs darp's ball-pivoting mesh


def test_tum_trajectories_at_every_frame_read_by_evo(exported: Path, keyframes: dict[str, Keyframe],
                                                     survey_path: Path) -> None:
    """groundtruth.txt is the twin's true pose of every frame, darp_poses.txt darp's; evo reads both, associates
    them by time and computes the APE; the keyframes' images sit at poses of the trajectory."""
    from evo.core import metrics, sync
    from evo.tools import file_interface

    from darp.formats.truth import read_camera_poses

    for arm in ("arm110", "arm111"):
        folder = exported / "tum" / arm
        truth = read_camera_poses(survey_path / "truth" / f"camera_poses_{arm}.npz")
        gt = file_interface.read_tum_trajectory_file(str(folder / "groundtruth.txt"))
        est = file_interface.read_tum_trajectory_file(str(folder / "darp_poses.txt"))
        mine = sorted((kf for kf in keyframes.values() if kf.arm == arm), key=lambda k: k.t_s)
        assert gt.num_poses == len(truth["t_host_s"]) == est.num_poses > 5 * len(mine)  # every frame, not keyframes
        np.testing.assert_allclose(gt.timestamps, truth["t_host_s"], atol=1e-6)
        np.testing.assert_allclose(np.array(gt.poses_se3), truth["T_world_cam"], atol=1e-9)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data(sync.associate_trajectories(gt, est, max_diff=1e-4))
        # processed with --truth-poses: darp's poses are the truth (with a calibration: eq. 1's error)
        assert ape.get_statistic(metrics.StatisticsType.rmse) < 1e-6
        depth_list = [line.split() for line in (folder / "depth.txt").read_text().splitlines() if line[0] != "#"]
        assert len(depth_list) == len(mine)
        fx, fy, cx, cy = (float(v) for v in (folder / "calibration.txt").read_text().splitlines()[1].split()[:4])
        stamps = np.array(gt.timestamps)
        for (stamp, name), kf in zip(depth_list, mine, strict=True):
            assert abs(float(stamp) - kf.t_s) < 1e-6
            T = np.array(gt.poses_se3)[np.argmin(np.abs(stamps - float(stamp)))]
            np.testing.assert_allclose(T, kf.T_world_cam, atol=1e-9)
            T = np.eye(4)
            row = next(r.split() for r in (folder / "darp_poses.txt").read_text().splitlines() if r.startswith(stamp))
            T[:3, 3] = [float(v) for v in row[1:4]]
            T[:3, :3] = Rotation.from_quat([float(v) for v in row[4:8]]).as_matrix()  # qx qy qz qw
            np.testing.assert_allclose(T, kf.T_world_cam, atol=1e-9)
            depth = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED) / 5000.0  # TUM: 5000 per metre
            uv, pts = object_pixels(kf, 50)
            z = depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
            cam = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
            np.testing.assert_allclose(cam @ T[:3, :3].T + T[:3, 3], pts, atol=1e-5)


def test_export_of_a_non_processed_folder_is_one_error_line(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "in").mkdir()
    assert run(["export", "tum", str(tmp_path / "in"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("darp: error:") and "no processed survey" in err


def test_export_formats_mirror_the_library() -> None:
    from darp.cli._options import ExportFormat
    from darp.export import FORMATS

    assert [f.value for f in ExportFormat] == list(FORMATS)
