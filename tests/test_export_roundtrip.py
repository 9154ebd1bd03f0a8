"""Round trips: ``darp export nerfstudio|tum|open3d`` then ``darp import`` reproduces every keyframe's pose (1e-6),
intrinsics (1e-6 px), colour and metric depth (to the exported depth unit), on the processed twin survey; and
the TUM folder pairing (rgb.txt / depth.txt / groundtruth.txt by nearest timestamp) on small hand-made folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from darp.cli._app import run
from darp.errors import FormatError
from darp.formats.intrinsics import load_intrinsics, read_open3d_intrinsic
from darp.formats.trajectories import read_nerfstudio_folder, read_tum_folder
from darp.reconstruction.keyframe_io import Keyframe, load_keyframes

UNITS_PER_M = {"nerfstudio": 1000.0, "tum": 5000.0, "open3d": 1000.0}


def _imported(out: Path) -> list[tuple[Keyframe, dict[str, str]]]:
    """The imported keyframes with import.json's record of the files each came from."""
    files = {f["frame_number"]: f for f in json.loads((out / "import.json").read_text())["files"]}
    return [(kf, files[kf.frame_number]) for kf in load_keyframes(out / "keyframes")]


def _compare(got: Keyframe, want: Keyframe, units_per_m: float) -> None:
    where = f"{want.arm} frame {want.frame_number}"
    np.testing.assert_allclose(got.T_world_cam, want.T_world_cam, rtol=0, atol=1e-6, err_msg=where)
    gi, wi = got.intrinsics, want.intrinsics
    assert (gi.width, gi.height) == (wi.width, wi.height), where
    np.testing.assert_allclose([gi.fx, gi.fy, gi.ppx, gi.ppy], [wi.fx, wi.fy, wi.ppx, wi.ppy], rtol=0, atol=1e-6,
                               err_msg=where)
    np.testing.assert_array_equal(got.rgb, want.rgb, err_msg=where)
    d_got, d_want = got.depth_m.astype(np.float64), want.depth_m.astype(np.float64)
    kept = (d_want > 0) & (d_want * units_per_m <= 65535)
    assert np.array_equal(d_got > 0, kept), where
    assert np.abs(d_got - d_want)[kept].max() <= 0.5 / units_per_m + 1e-6, where


@pytest.mark.slow
def test_export_then_import_reproduces_poses_intrinsics_and_depth(processed_path: Path, tmp_path: Path) -> None:
    original = {(kf.arm, kf.frame_number): kf for kf in load_keyframes(processed_path / "keyframes")}
    arms = sorted({arm for arm, _ in original})
    checked = dict.fromkeys(UNITS_PER_M, 0)
    for fmt in UNITS_PER_M:
        assert run(["export", fmt, str(processed_path), "-o", str(tmp_path / fmt)]) == 0, fmt

    # nerfstudio: one transforms.json for both arms, intrinsics per frame (cx = ppx + 0.5 undone), depth unit read
    out = tmp_path / "in-nerfstudio"
    assert run(["import", str(tmp_path / "nerfstudio"), "-o", str(out)]) == 0
    for kf, files in _imported(out):
        arm, number = Path(files["depth"]).stem.rsplit("_", 1)
        _compare(kf, original[(arm, int(number))], UNITS_PER_M["nerfstudio"])
        checked["nerfstudio"] += 1
    # the export carries the survey's object envelope and the import takes it: processing crops as the survey did
    given = json.loads((processed_path / "results.json").read_text())["envelope"]
    for folder in (tmp_path / "nerfstudio", *(tmp_path / fmt / arm for fmt in ("tum", "open3d") for arm in arms)):
        carried = json.loads((folder / "manip_envelope.json").read_text())
        np.testing.assert_allclose(carried["center_m"], given["center_m"], atol=1e-12, err_msg=str(folder))
    assert run(["process", str(out), "-o", str(tmp_path / "processed-nerfstudio")]) == 0
    used = json.loads((tmp_path / "processed-nerfstudio" / out.name / "results.json").read_text())["envelope"]
    assert used["source"] != "estimated" and used["radius_m"] == pytest.approx(given["radius_m"], abs=1e-12)
    np.testing.assert_allclose(used["center_m"], given["center_m"], atol=1e-12)
    # without it: processing estimates the object cylinder as for a DARP survey, near the survey's own one
    (out / "manip_envelope.json").unlink()
    assert run(["process", str(out), "-o", str(tmp_path / "processed-nerfstudio-estimated")]) == 0
    estimated = json.loads(
        (tmp_path / "processed-nerfstudio-estimated" / out.name / "results.json").read_text())["envelope"]
    assert estimated["source"] == "estimated"
    assert np.linalg.norm(np.subtract(estimated["center_m"][:2], given["center_m"][:2])) < 0.02
    assert abs(estimated["height_m"] - given["height_m"]) < 0.02

    for n, arm in enumerate(arms):
        # TUM: the folder's own pairing through rgb.txt / depth.txt / groundtruth.txt, calibration.txt, 5000 per m;
        # detected for the first arm, the trajectory named for the second
        folder, out = tmp_path / "tum" / arm, tmp_path / f"in-tum-{arm}"
        named = ["--trajectory", str(folder / "groundtruth.txt"), "--trajectory-format", "tum"] if n else []
        assert run(["import", str(folder), "-o", str(out), *named]) == 0
        by_stamp = {f"{kf.t_s:.6f}": kf for (a, _), kf in original.items() if a == arm}
        for kf, files in _imported(out):
            want = by_stamp[Path(files["depth"]).stem]
            assert kf.t_s == pytest.approx(want.t_s, abs=1e-6)
            _compare(kf, want, UNITS_PER_M["tum"])
            checked["tum"] += 1

        # Open3D: trajectory.log and camera_intrinsic.json given explicitly (--trajectory, --intrinsics)
        folder, out = tmp_path / "open3d" / arm, tmp_path / f"in-open3d-{arm}"
        assert run(["import", str(folder), "-o", str(out), "--trajectory", str(folder / "trajectory.log"),
                    "--trajectory-format", "log", "--intrinsics", str(folder / "camera_intrinsic.json")]) == 0
        numbers = [f["frame_number"] for f in json.loads((folder / "frames.json").read_text())["frames"]]
        for kf, files in _imported(out):
            _compare(kf, original[(arm, numbers[int(Path(files["depth"]).stem)])], UNITS_PER_M["open3d"])
            checked["open3d"] += 1
    assert checked == dict.fromkeys(UNITS_PER_M, len(original)), checked


def _tum_folder(root: Path, depth_stamps: list[float], rgb_stamps: list[float], gt_stamps: list[float]) -> Path:
    root.mkdir(parents=True)
    (root / "depth.txt").write_text("# depth maps\n" + "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in depth_stamps))
    (root / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in rgb_stamps))
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{t:.4f} {t:.4f} 0 0 0 0 0 1\n" for t in gt_stamps))
    return root


def test_tum_folder_pairs_by_nearest_timestamp_within_the_max_difference(tmp_path: Path) -> None:
    # two depth frames in the same second; the colour and the 100 Hz ground truth are offset by a few ms
    root = _tum_folder(tmp_path / "seq", [10.10, 10.50, 11.90], [10.103, 10.497, 12.5],
                       [10.0 + 0.01 * n for n in range(150)])
    posed = read_tum_folder(root)
    assert sorted(posed.depth) == ["0", "1", "2"]
    assert posed.depth["1"].name == "10.500000.png" and posed.colour["1"].name == "10.497000.png"
    assert "2" not in posed.colour  # the nearest colour image is 0.6 s away
    assert posed.poses["0"][0, 3] == pytest.approx(10.10) and posed.poses["1"][0, 3] == pytest.approx(10.50)
    assert "2" not in posed.poses  # ground truth ends at 11.49 s
    assert posed.depth_scale_m == pytest.approx(1 / 5000) and posed.stamps["1"] == pytest.approx(10.5)
    assert not posed.intrinsics  # no calibration.txt: darp import asks for --intrinsics
    # one-to-one, closest first (associate.py): the colour image at 10.505 s goes to the depth frame at 10.503 s
    posed = read_tum_folder(_tum_folder(tmp_path / "pair", [10.50, 10.503], [10.505], [10.50, 10.503]))
    assert list(posed.colour) == ["1"] and sorted(posed.poses) == ["0", "1"]
    assert posed.poses["1"][0, 3] == pytest.approx(10.503)
    with pytest.raises(FormatError, match="within 0.001 s"):
        read_tum_folder(_tum_folder(tmp_path / "far", [20.0, 20.5], [20.0], [10.0 + 0.01 * n for n in range(150)]),
                        max_dt_s=0.001)


def test_tum_import_without_intrinsics_or_matching_poses_is_a_one_line_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = _tum_folder(tmp_path / "seq", [10.1, 10.5], [10.1, 10.5], [10.1, 10.5])
    assert run(["import", str(root), "-o", str(tmp_path / "out")]) == 2
    assert "--intrinsics" in capsys.readouterr().err
    far = _tum_folder(tmp_path / "far", [30.1, 30.5], [30.1], [10.1, 10.5])
    assert run(["import", str(far), "-o", str(tmp_path / "out2")]) == 2
    err = capsys.readouterr().err
    assert "darp: error:" in err and "groundtruth.txt" in err and "no depth frame has a ground-truth pose" in err
    out3 = tmp_path.parent / f"{tmp_path.name}-out3"  # outside the input folder (inside it is refused, issue 32)
    assert run(["import", str(tmp_path), "-o", str(out3)]) == 2  # darp export tum's per-arm parent
    assert "its sub-folders far, seq are: import each" in capsys.readouterr().err


def test_nerfstudio_and_open3d_intrinsics_conventions(tmp_path: Path) -> None:
    (tmp_path / "transforms.json").write_text(json.dumps({
        "fl_x": 600.0, "fl_y": 601.0, "cx": 320.5, "cy": 240.5, "depth_unit_scale_factor": 0.0002,
        "frames": [{"file_path": "images/a.png", "depth_file_path": "depth/a.png",
                    "transform_matrix": np.eye(4).tolist()},
                   {"file_path": "images/b.png", "depth_file_path": "depth/b.png", "cx": 100.5,
                    "transform_matrix": np.diag([1.0, -1.0, -1.0, 1.0]).tolist()}]}))
    posed = read_nerfstudio_folder(tmp_path)
    assert posed.depth_scale_m == 0.0002 and posed.depth["1"] == tmp_path / "depth" / "b.png"
    np.testing.assert_allclose(posed.intrinsics["0"][0], [[600, 0, 320], [0, 601, 240], [0, 0, 1]])
    assert posed.intrinsics["1"][0][0, 2] == 100.0
    np.testing.assert_allclose(posed.poses["0"], np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenGL -> OpenCV axes
    np.testing.assert_allclose(posed.poses["1"], np.eye(4))
    (tmp_path / "camera_intrinsic.json").write_text(json.dumps(
        {"width": 640, "height": 480, "intrinsic_matrix": [600.0, 0, 0, 0, 601.0, 0, 319.2, 241.7, 1]}))
    K, w, h = read_open3d_intrinsic(tmp_path / "camera_intrinsic.json")
    np.testing.assert_allclose(K, [[600, 0, 319.2], [0, 601, 241.7], [0, 0, 1]])
    np.testing.assert_allclose(load_intrinsics(tmp_path / "camera_intrinsic.json").K, K)
    o3d = pytest.importorskip("open3d")
    oracle = o3d.io.read_pinhole_camera_intrinsic(str(tmp_path / "camera_intrinsic.json"))
    np.testing.assert_allclose(oracle.intrinsic_matrix, K)
