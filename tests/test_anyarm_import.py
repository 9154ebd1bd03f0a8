"""``darp import`` and imported surveys: trajectory formats, the real 3DMatch frames, mistakes in the data."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from darp.errors import FormatError
from darp.formats.calibration import ArmCalibration, Calibration, write_calibration
from darp.formats.trajectories import (
    OPENGL_TO_OPENCV,
    read_log,
    read_nerfstudio,
    read_pose_txt,
    write_log,
)
from darp.kinematics.transforms import axis_angle_to_rotation, invert_transform, make_transform, rotation_to_quaternion
from darp.processing.imported import ImportSpec, ImportWarning, import_sequence
from darp.reconstruction.keyframe_io import read_keyframe_index
from helpers.realdata import needs, realdata

REAL = realdata("3dmatch-frames")
needs_real = needs(REAL)
SEQ = REAL / "seq-01"


def K() -> np.ndarray:
    return np.loadtxt(REAL / "camera-intrinsics.txt")


def poses() -> dict[str, np.ndarray]:
    return read_pose_txt(SEQ)


def copy_seq(dst: Path, drop_pose: str | None = None) -> Path:
    shutil.copytree(SEQ, dst)
    if drop_pose is not None:
        (dst / f"frame-{int(drop_pose):06d}.pose.txt").unlink()
    return dst


@needs_real
def test_trajectory_formats_round_trip(tmp_path: Path) -> None:
    P = poses()
    assert sorted(P, key=int) == ["0", "1", "2", "116", "422"]
    write_log(tmp_path / "trajectory.log", P)
    frames = [{"file_path": f"images/frame_{int(k):05d}.png", "transform_matrix": (T @ OPENGL_TO_OPENCV).tolist()}
              for k, T in P.items()]
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 570.3, "cx": 320, "cy": 240, "frames": frames}))
    for got in (read_log(tmp_path / "trajectory.log"), read_nerfstudio(tmp_path / "transforms.json")[0]):
        assert got.keys() == P.keys()
        for k in P:
            assert np.allclose(got[k], P[k], atol=1e-6)  # TUM: tests/test_formats_tum.py (against evo)


@needs_real
def test_real_3dmatch_import_writes_keyframes_with_the_poses(tmp_path: Path) -> None:
    rec = import_sequence(ImportSpec(SEQ, tmp_path / "imp", K(), poses=poses(), pose_source=str(SEQ)))
    assert rec["frames"] == 5 and rec["heldout"] == 1 and 2.5 < rec["median_depth_m"] < 3.5
    # consecutive real frames overlap (shared/realdata README: ~13 mm median NN at full density; we subsample)
    assert rec["pose_check"]["neighbour_median_mm"] < 0.25 * rec["pose_check"]["neighbour_median_mm_inverted"]
    index = read_keyframe_index(tmp_path / "imp" / "keyframes")
    assert index.pose_source == "imported" and len(index.keyframes) == 5
    assert np.allclose(index.keyframes[3].T_world_cam, poses()["116"])
    kf = np.load(tmp_path / "imp" / "keyframes" / "arm" / "000116.npz")
    assert kf["depth"].dtype == np.uint16 and kf["rgb"].shape == (480, 640, 3) and kf["rgb"].max() > 0


@needs_real
def test_flange_poses_and_hand_eye_give_the_same_camera_poses(tmp_path: Path) -> None:
    from darp.cli._app import run

    X = make_transform(axis_angle_to_rotation([0.2, 1, 0.1], np.radians(12)), [0.03, -0.01, 0.05])
    T_wb = make_transform(axis_angle_to_rotation([0, 0, 1], np.radians(30)), [0.4, 0.2, 0.0])
    lines = ["# unit: mm", "id,x,y,z,qw,qx,qy,qz"]
    for k, T in poses().items():
        F = invert_transform(T_wb) @ T @ invert_transform(X)
        q = rotation_to_quaternion(F[:3, :3])
        lines.append(",".join([k, *(f"{v:.12g}" for v in (*(F[:3, 3] * 1e3), q[3], q[0], q[1], q[2]))]))
    (tmp_path / "flange.csv").write_text("\n".join(lines) + "\n")
    write_calibration(tmp_path / "cal.json", Calibration("e", "2026-01-01", {"ur5": ArmCalibration("", T_wb, X)}))
    code = run(["import", str(SEQ), "-o", str(tmp_path / "imp"), "--intrinsics", str(REAL / "camera-intrinsics.txt"),
                "--flange-poses", str(tmp_path / "flange.csv"), "-c", str(tmp_path / "cal.json"), "--unit", "mm",
                "--quaternion", "wxyz"])
    assert code == 0
    index = read_keyframe_index(tmp_path / "imp" / "keyframes")
    assert set(index.arms) == {"ur5"}
    for e in index.keyframes:
        assert np.allclose(e.T_world_cam, poses()[str(e.frame_number)], atol=1e-6)


@needs_real
def test_camera_from_world_poses_are_named_with_both_numbers(tmp_path: Path) -> None:
    inv = {k: invert_transform(T) for k, T in poses().items()}
    with pytest.raises(FormatError, match=r"camera-from-world.*mm apart \(median\) as given, .* mm with the poses "
                                          r"inverted"):
        import_sequence(ImportSpec(SEQ, tmp_path / "imp", K(), poses=inv, pose_source="poses.txt"))


@needs_real
def test_depth_scale_inconsistent_with_the_scene_is_named(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match=r"depth.png: depth scale 1 m/unit puts the scene at .* a scale of 0.001"):
        import_sequence(ImportSpec(SEQ, tmp_path / "imp", K(), depth_scale_m=1.0, poses=poses(), pose_source="x"))


@needs_real
def test_depth_not_registered_to_colour_is_named(tmp_path: Path) -> None:
    seq = copy_seq(tmp_path / "seq")
    for f in seq.glob("*.color.png"):
        img = cv2.imread(str(f))
        cv2.imwrite(str(f), cv2.resize(img, (1280, 720)))
    with pytest.raises(FormatError, match="color.png: colour is 1280 x 720 but depth 640 x 480: the depth is not "
                                          "registered to colour"):
        import_sequence(ImportSpec(seq, tmp_path / "imp", K(), poses=read_pose_txt(seq), pose_source="x"))


@needs_real
def test_missing_and_duplicated_frames_are_named(tmp_path: Path) -> None:
    seq = copy_seq(tmp_path / "seq", drop_pose="116")
    with pytest.warns(ImportWarning, match=r"no pose for 1 of 5 depth frames \(e.g. frame 116\)"):
        rec = import_sequence(ImportSpec(seq, tmp_path / "imp", K(), poses=read_pose_txt(seq), pose_source="poses"))
    assert rec["frames"] == 4
    shutil.copy(seq / "frame-000001.depth.png", seq / "frame_1.depth.png")
    with pytest.raises(FormatError, match="two images for frame 1"):
        import_sequence(ImportSpec(seq, tmp_path / "imp2", K(), poses=read_pose_txt(seq), pose_source="poses"))


@needs_real
@pytest.mark.slow
def test_real_3dmatch_process_fuses_meshes_and_evaluates(tmp_path: Path) -> None:
    from darp.cli._app import run

    assert run(["import", str(SEQ), "-o", str(tmp_path / "imp"), "--intrinsics", str(REAL / "camera-intrinsics.txt"),
                "--trajectory", str(SEQ), "--trajectory-format", "pose-txt"]) == 0
    # the paper's surface (voxel support and ball pivoting) with a room's settings; the default is test_real_fusion's
    (tmp_path / "room.yaml").write_text("surface:\n  method: paper\n"
                                        "fusion:\n  voxel_size_m: 0.01\n  min_frames: 2\n  min_view_bins: 1\n"
                                        "  depth:\n    max_depth_m: 5.0\n    discontinuity_abs_m: 0.02\n")
    assert run(["process", str(tmp_path / "imp"), "-o", str(tmp_path / "out"), "--settings",
                str(tmp_path / "room.yaml")]) == 0
    r = json.loads((tmp_path / "out" / "imp" / "results.json").read_text())
    assert r["schema"] == "darp-results/1" and r["pose_source"] == "imported" and r["cross_arm"] is None
    assert r["keyframes"]["fuse"] == 4 and r["keyframes"]["heldout"] == 1 and r["mesh"]["triangles"] > 1000
    # a room at 3 m from 4 frames (3DMatch's structured light): the held-out frame's points lie on the mesh to
    # about 6 mm median (1 cm voxels); far from a tabletop's 2 mm, but the surface is there
    assert r["heldout"]["aggregate"]["median_mm"] < 10.0
    assert (tmp_path / "out" / "imp" / "figures" / "imported_mesh.png").stat().st_size > 10000
    assert run(["report", str(tmp_path / "out")]) == 0
    assert "imported" in (tmp_path / "out" / "report.md").read_text()


@needs_real
def test_an_envelope_crops_fusion_and_evaluation(tmp_path: Path) -> None:
    from darp.formats.envelope import Envelope, write_envelope
    from darp.processing.imported import process_imported
    from darp.reconstruction.backproject import DepthFilterSettings
    from darp.reconstruction.cloud_io import read_ply
    from darp.reconstruction.fusion import FusionSettings

    P = poses()
    d = cv2.imread(str(SEQ / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    v, u = np.nonzero(d[::8, ::8])
    z = d[::8, ::8][v, u] * 1e-3
    k = K()
    pts = np.stack([(u * 8 - k[0, 2]) / k[0, 0] * z, (v * 8 - k[1, 2]) / k[1, 1] * z, z], 1)
    pts = pts @ P["0"][:3, :3].T + P["0"][:3, 3]
    c = np.median(pts, axis=0)
    write_envelope(tmp_path / "env.json", Envelope(object_name="corner", center_m=(c[0], c[1], c[2] - 1.0),
                                                   radius_m=0.4, height_m=2.0))
    import_sequence(ImportSpec(SEQ, tmp_path / "imp", k, poses=P, pose_source="p", envelope=tmp_path / "env.json"))
    fs = FusionSettings(depth=DepthFilterSettings(max_depth_m=5.0, discontinuity_abs_m=0.02), voxel_size_m=0.01,
                        min_frames=2, min_view_bins=1)
    r = process_imported(tmp_path / "imp", tmp_path / "out", fs)
    assert r["envelope"]["source"] == "manip_envelope.json"
    fused = read_ply(tmp_path / "out" / "fused.ply").points
    assert 100 < len(fused) < 22665  # the whole room fuses to 22,665 points with these settings
    assert np.max(np.linalg.norm(fused[:, :2] - c[:2], axis=1)) < 0.4 + fs.envelope_margin_m + 0.01
