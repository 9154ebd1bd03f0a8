"""Readers for the files people have (issue 29, item 3), against real files and real libraries.

Oracles: the real Doosan A0509 + D435 files (shared/realdata: its ``camera_intrinsics.npz``, 4x4 flange
poses and upstream hand-eye), SciPy's rotations for quaternions, OpenCV's ArUco detector for the marker
diagnosis, and darp's own seeded fold split for the folds file.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.calibration.anyarm import detect_folder, load_capture_folder, solve_folder
from darp.calibration.board import Board
from darp.calibration.detect import detect_corners
from darp.errors import FormatError
from darp.formats.hand_eye import T_BODY_OPTICAL, read_hand_eye
from darp.formats.intrinsics import load_intrinsics
from darp.formats.pairing import rgbd_frames
from darp.formats.pose_tables import read_pose_table
from darp.formats.poses import PoseConventions, read_matrix_file
from darp.geometry.rigid import OrthonormalisedWarning
from helpers.realdata import needs, realdata

DOOSAN = realdata("doosan-a0509-d435-charuco")
needs_doosan = needs(DOOSAN)
SIDECAR = ("board: {type: charuco, squares_x: 7, squares_y: 5, square_mm: 30, marker_mm: 22, dictionary: DICT_4X4_50}\n"
           "unit: mm\narm: doosan\n")


def doosan_npz() -> tuple[np.ndarray, np.ndarray]:
    with np.load(DOOSAN / "camera_intrinsics.npz") as z:
        return np.asarray(z["cameraMatrix"], float), np.asarray(z["distCoeffs"], float).reshape(-1)


def doosan_poses() -> dict[str, np.ndarray]:
    """The real flange poses (mm) by file name."""
    return {f.name: read_matrix_file(f) for f in sorted((DOOSAN / "poses").glob("pose_*.txt"))}


@needs_doosan
def test_realsense_and_ros_intrinsics_read_the_real_cameras_values(tmp_path: Path) -> None:
    K, dist = doosan_npz()
    forms = {
        "rs.json": json.dumps({"Image Size": [1280, 720], "Principal Point": [K[0, 2], K[1, 2]],
                               "Focal Length": [K[0, 0], K[1, 1]], "Distortion Coefficients": dist.tolist(),
                               "Distortion Model": "Brown Conrady"}),
        "rs_nested.json": json.dumps({"color": {"Width": 1280, "Height": 720, "PPX": K[0, 2], "PPY": K[1, 2],
                                                "Fx": K[0, 0], "Fy": K[1, 1], "Coeffs": dist.tolist()}}),
        "camera_info.yaml": "image_width: 1280\nimage_height: 720\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: "
                            f"{K.ravel().tolist()}\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n"
                            f"  cols: 5\n  data: {dist.tolist()}\n",
        "camera_info.json": json.dumps({"header": {"frame_id": "camera_color_optical_frame"}, "height": 720,
                                        "width": 1280, "distortion_model": "plumb_bob", "d": dist.tolist(),
                                        "k": K.ravel().tolist(), "r": np.eye(3).ravel().tolist()}),
        "msg.yaml": f"height: 720\nwidth: 1280\ndistortion_model: plumb_bob\nD: {dist.tolist()}\nK: "
                    f"{K.ravel().tolist()}\n",
    }
    for name, text in forms.items():
        (tmp_path / name).write_text(text)
        cam = load_intrinsics(tmp_path / name)
        assert np.allclose(cam.K, K, rtol=0, atol=1e-9), name
        assert np.allclose(cam.dist[:5], dist, atol=1e-12) and cam.size == (1280, 720), name
        assert cam.model == "Brown Conrady"
    (tmp_path / "bad.json").write_text(json.dumps({"Focal Length": [900, 900]}))
    with pytest.raises(FormatError, match=r"bad\.json.*Principal Point"):
        load_intrinsics(tmp_path / "bad.json")


@needs_doosan
def test_pose_tables_npz_json_csv_txt_give_the_real_poses(tmp_path: Path) -> None:
    real = doosan_poses()
    names = list(real)
    M = np.array(list(real.values()))
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat()  # xyzw, SciPy as the oracle
    np.savez(tmp_path / "stack.npz", poses=M, ids=np.array(names))
    (tmp_path / "records.json").write_text(json.dumps([{"image": n, "pose": T.tolist()} for n, T in real.items()]))
    (tmp_path / "quat.csv").write_text("# unit: mm\nname,x,y,z,qw,qx,qy,qz\n" + "".join(
        n + "," + ",".join(repr(float(v)) for v in [*T[:3, 3], qq[3], *qq[:3]]) + "\n"
        for (n, T), qq in zip(real.items(), q, strict=True)))
    (tmp_path / "rows.txt").write_text("".join(n + " " + " ".join(repr(float(v)) for v in T.ravel()) + "\n"
                                               for n, T in real.items()))
    (tmp_path / "folder").mkdir()
    for n, T in real.items():  # the crash: a folder of .npz flange poses
        np.savez(tmp_path / "folder" / n.replace(".txt", ".npz"), T=T)
    conv = PoseConventions("mm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OrthonormalisedWarning)  # six-decimal rotations: 1.3e-6 off, no warning
        tables = {f: read_pose_table(tmp_path / f, conv) for f in ("stack.npz", "records.json", "quat.csv", "rows.txt",
                                                                    "folder")}
    for f, table in tables.items():
        assert table.order == [str(i) for i in range(len(real))], f  # pose_000 -> id "0"
        for i, T in enumerate(M):
            got = table.poses[str(i)]
            assert np.allclose(got[:3, 3], T[:3, 3] * 1e-3, atol=1e-9), f
            assert np.allclose(got[:3, :3], T[:3, :3], atol=3e-6), f  # re-orthonormalised to the rule
    assert tables["quat.csv"].quaternions and not tables["stack.npz"].quaternions
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.md").write_text("x")
    with pytest.raises(FormatError, match="no pose files"):
        read_pose_table(tmp_path / "empty", conv)
    np.savez(tmp_path / "odd.npz", a=np.zeros((3, 3)))
    with pytest.raises(FormatError, match=r"odd\.npz: no pose table"):
        read_pose_table(tmp_path / "odd.npz", conv)


@needs_doosan
def test_hand_eye_files_easy_handeye_moveit_bare_matrix(tmp_path: Path) -> None:
    X = read_matrix_file(DOOSAN / "handeye_T_tool_cam.txt")  # upstream's, translation in mm
    X[:3, 3] *= 1e-3
    q = Rotation.from_matrix(X[:3, :3]).as_quat()
    (tmp_path / "eh.yaml").write_text(
        "eye_on_hand: true\nrobot_effector_frame: tool0\ntracking_base_frame: camera_color_optical_frame\n"
        "transformation:\n" + "".join(f"  {k}: {v!r}\n" for k, v in zip(
            ("x", "y", "z", "qx", "qy", "qz", "qw"), [*X[:3, 3].tolist(), *q.tolist()], strict=True)))
    args = " ".join(repr(float(v)) for v in [*X[:3, 3], *q])
    (tmp_path / "cal.launch").write_text(f'<launch><node pkg="tf2_ros" type="static_transform_publisher" '
                                         f'args="{args} tool0 camera_link" /></launch>')
    np.save(tmp_path / "X.npy", X)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OrthonormalisedWarning)
        got = {"bare mm": read_hand_eye(DOOSAN / "handeye_T_tool_cam.txt", "mm"),
               "easy_handeye": read_hand_eye(tmp_path / "eh.yaml"), "moveit": read_hand_eye(tmp_path / "cal.launch"),
               "npy": read_hand_eye(tmp_path / "X.npy")}
    for name, he in got.items():
        assert np.allclose(he.T_wrist_cam[:3, 3], X[:3, 3], atol=1e-9), name
        assert np.allclose(he.T_wrist_cam[:3, :3], X[:3, :3], atol=2e-5), name  # 6 digits, re-orthonormalised
    assert got["easy_handeye"].optical and not got["moveit"].optical  # camera_link: a ROS body frame
    assert np.allclose(T_BODY_OPTICAL[:3, :3] @ [0, 0, 1], [1, 0, 0])  # optical z (forward) is body x
    with pytest.raises(FormatError, match=r"handeye_T_tool_cam\.txt.*--hand-eye-unit mm"):
        read_hand_eye(DOOSAN / "handeye_T_tool_cam.txt", "m")


def test_flat_colour_depth_folder_pairs_jpg_with_png(tmp_path: Path) -> None:
    for stem in ("0", "1", "12"):
        cv2.imwrite(str(tmp_path / f"{stem}.jpg"), np.zeros((4, 4, 3), np.uint8))
        cv2.imwrite(str(tmp_path / f"{stem}.png"), np.ones((4, 4), np.uint16))
    colour, depth = rgbd_frames(tmp_path)
    assert sorted(colour) == sorted(depth) == ["0", "1", "12"]
    assert all(p.suffix == ".png" for p in depth.values()) and all(p.suffix == ".jpg" for p in colour.values())
    assert cv2.imread(str(depth["12"]), cv2.IMREAD_UNCHANGED).dtype == np.uint16


def test_duplicated_marker_is_named_as_the_reason(tmp_path: Path) -> None:
    board = Board("charuco", 7, 5, 0.03, 0.022, "DICT_4X4_50")
    img = board.cv_charuco().generateImage((1400, 1000), marginSize=150)
    corners, ids, _ = cv2.aruco.ArucoDetector(board.cv_charuco().getDictionary(),
                                              cv2.aruco.DetectorParameters()).detectMarkers(img)
    q = corners[list(ids.reshape(-1)).index(0)].reshape(4, 2)
    (x0, y0), (x1, y1) = q.min(0).astype(int) - 8, q.max(0).astype(int) + 8
    dup = img.copy()
    dup[10:10 + y1 - y0, 600:600 + x1 - x0] = img[y0:y1, x0:x1]  # marker 0 printed twice
    assert len(detect_corners(board, img)[0]) == 24 and len(detect_corners(board, dup)[0]) == 0  # OpenCV drops it
    root = tmp_path / "caps"
    (root / "images").mkdir(parents=True)
    (root / "poses").mkdir()
    for i in range(4):
        cv2.imwrite(str(root / "images" / f"img_{i}.png"), dup if i == 0 else img)
        np.savetxt(root / "poses" / f"pose_{i}.txt", np.eye(4))
    (root / "handeye.yaml").write_text(SIDECAR.replace("unit: mm", "unit: m"))
    (root / "intrinsics.json").write_text(json.dumps({"fx": 1000, "fy": 1000, "cx": 700, "cy": 500}))
    dets, _, _ = detect_folder(load_capture_folder(root))
    reason = {d.capture_id: d.reason for d in dets}
    assert "too few corners (0 < 8)" in reason["0"] and "marker id 0 appears 2 times" in reason["0"]
    assert reason["1"] == ""


@needs_doosan
def test_folds_file_reproduces_the_seeded_split_and_scores_corner_and_centre(tmp_path: Path) -> None:
    root = tmp_path / "caps"
    (root / "poses").mkdir(parents=True)
    (root / "board_poses").mkdir()
    for f in sorted((DOOSAN / "poses").glob("pose_*.txt")):
        (root / "poses" / f.name).symlink_to(f)
    for f in sorted((DOOSAN / "poses").glob("boardpose_*.npz")):
        (root / "board_poses" / f.name).symlink_to(f)
    (root / "intrinsics.npz").symlink_to(DOOSAN / "camera_intrinsics.npz")
    (root / "handeye.yaml").write_text(SIDECAR)
    a = solve_folder(root, folds=5, seed=1, compare=False).calibration.report["heldout"]
    (tmp_path / "folds.txt").write_text("capture fold\n" + "".join(f"pose_{int(c):03d}.txt {f}\n"
                                                                   for c, f in a["fold_of"].items()))
    b = solve_folder(root, folds_file=tmp_path / "folds.txt", compare=False).calibration.report["heldout"]
    assert b["fold_of"] == a["fold_of"]
    for key in ("board_consistency_mm", "board_corner_consistency_mm", "board_consistency_deg"):
        assert b[key] == a[key]
    # the corner (board origin) is off the board centre, so its held-out distance differs from the centre's
    assert a["board_corner_consistency_mm"]["mean"] != a["board_consistency_mm"]["mean"]
    (tmp_path / "short.txt").write_text("pose_000.txt 0\n")
    with pytest.raises(FormatError, match=r"short\.txt.*has no fold"):
        solve_folder(root, folds_file=tmp_path / "short.txt", compare=False)


def test_refinement_choices_mirror_the_library() -> None:
    from darp.calibration.anyarm import REFINEMENTS
    from darp.cli.calib import Refinement

    assert [r.value for r in Refinement] == list(REFINEMENTS)


@needs_doosan
def test_six_value_poses_read_with_a_declared_rotation_form(tmp_path: Path) -> None:
    real = doosan_poses()
    M = np.array(list(real.values()))
    R = Rotation.from_matrix(M[:, :3, :3])
    forms = {"rotvec": R.as_rotvec(), "euler-xyz-deg": R.as_euler("xyz", degrees=True),
             "euler-ZYX-rad": R.as_euler("ZYX")}
    for form, rot in forms.items():
        path = tmp_path / f"{form}.csv"
        path.write_text(f"# unit: mm, rotation: {form}\n" + "".join(
            n + "," + ",".join(repr(float(v)) for v in [*T[:3, 3], *r]) + "\n"
            for (n, T), r in zip(real.items(), rot, strict=True)))
        table = read_pose_table(path)
        for i, T in enumerate(M):
            assert np.allclose(table.poses[str(i)][:3, :3], T[:3, :3], atol=3e-6), form
            assert np.allclose(table.poses[str(i)][:3, 3], T[:3, 3] * 1e-3, atol=1e-9), form
    path = tmp_path / "undeclared.csv"
    path.write_text("".join(n + "," + ",".join(repr(float(v)) for v in [*T[:3, 3], *r]) + "\n"
                            for (n, T), r in zip(real.items(), forms["rotvec"], strict=True)))
    with pytest.raises(FormatError, match=r"undeclared\.csv: 6 values per pose.*declare rotation: rotvec"):
        read_pose_table(path, PoseConventions("mm"))


def test_a_quaternion_table_missing_a_column_is_named_as_such(tmp_path: Path) -> None:
    """A header that names quaternion columns over six values is a missing column, not an undeclared rotation
    vector: the error says so instead of asking for ``rotation: rotvec``."""
    path = tmp_path / "poses.csv"
    path.write_text("id,x,y,z,qx,qy,qz\n0,0.1,0.2,0.3,0.0,0.0,0.0\n1,0.2,0.2,0.3,0.0,0.0,0.1\n")
    with pytest.raises(FormatError, match=r"poses\.csv: 6 values per pose but the header names quaternion columns "
                                          r"\(qx, qy, qz\).*is a column missing"):
        read_pose_table(path)
    path.write_text("# rotation: rotvec\nid,x,y,z,qx,qy,qz\n0,0.1,0.2,0.3,0.0,0.0,0.0\n")  # declared: read as asked
    assert np.allclose(read_pose_table(path).poses["0"][:3, 3], [0.1, 0.2, 0.3])
