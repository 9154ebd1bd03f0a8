"""Issue 32, values: ranges checked where values enter - settings files, board sidecars, hand-eye poses and
command-line options (NaN included, which click's ranges let through) - each refused with exit 2 and one line
naming the option or file."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from darp.cli._app import run
from darp.errors import CalibrationError, ConfigError, DarpError, FormatError


def _one_error_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("darp: error:") and all(w in err for w in words), err
    return err


@pytest.mark.parametrize("group, key, value", [("timing", "joint_log_rate_hz", 1e9), ("timing", "start_time_s", 1e300),
                                               ("camera", "width", 100000), ("camera", "fps", 1e6)])
def test_twin_settings_out_of_range_are_refused(group: str, key: str, value: float, tmp_path: Path) -> None:
    from darp.twin.settings import TwinSettings

    path = tmp_path / "settings.yaml"
    path.write_text(f"{group}:\n  {key}: {value}\n")
    with pytest.raises(ConfigError, match=f"{group}.{key}: at most") as caught:
        TwinSettings.load(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize("board, words", [
    ({"type": "charuco", "squares_x": 1, "squares_y": 5, "square_mm": 30, "marker_mm": 20}, "at least 3 x 3"),
    ({"type": "chessboard", "squares_x": 3, "squares_y": 3, "square_mm": 30}, "at least 4 x 4"),
    ({"type": "chessboard", "squares_x": 9, "squares_y": 6, "square_mm": 0}, "square_mm"),
    ({"type": "chessboard", "squares_x": 9, "squares_y": 6, "square_mm": float("nan")}, "square_mm"),
])
def test_a_board_opencv_cannot_use_is_refused(board: dict[str, Any], words: str, tmp_path: Path) -> None:
    from darp.calibration.board import parse_board

    with pytest.raises(FormatError, match=words):
        parse_board(board, tmp_path / "handeye.yaml")
    parse_board({**board, "squares_x": 9, "squares_y": 6, "square_mm": 30}, tmp_path / "handeye.yaml")


def _motion(rotvecs: np.ndarray) -> Any:
    T = np.repeat(np.eye(4)[None], len(rotvecs), axis=0)
    T[:, :3, :3] = Rotation.from_rotvec(rotvecs).as_matrix()
    T[:, :3, 3] = np.linspace(0.1, 0.3, len(rotvecs))[:, None]
    return SimpleNamespace(T_base_flange=T, for_arm=lambda arm: np.ones(len(rotvecs), bool))


def test_identical_or_one_axis_hand_eye_poses_are_refused(tmp_path: Path) -> None:
    from darp.calibration.anyarm import check_flange_motion

    with pytest.raises(CalibrationError, match="do not rotate about two different axes"):
        check_flange_motion(_motion(np.zeros((8, 3))), "arm", tmp_path)
    one_axis = np.zeros((8, 3))
    one_axis[:, 2] = np.linspace(0, 1, 8)
    with pytest.raises(CalibrationError, match="two different axes"):
        check_flange_motion(_motion(one_axis), "arm", tmp_path)
    varied = np.random.default_rng(0).normal(0, 0.3, (8, 3))
    check_flange_motion(_motion(varied), "arm", tmp_path)


@pytest.mark.parametrize("argv, words", [
    (["calib", "handeye", "{g}", "-o", "{tmp}/c.json", "--seed", "-1"], "'--seed'"),
    (["calib", "handeye", "{g}", "-o", "{tmp}/c.json", "--folds", "1"], "'--folds'"),
    (["calib", "handeye", "{g}", "-o", "{tmp}/c.json", "--folds", "-3"], "'--folds'"),
    (["calib", "solve", "{g}", "-o", "{tmp}/c.json", "--folds", "-1"], "'--folds'"),
    (["twin", "waypoints", "--object", "cube", "-o", "{tmp}/w.yaml", "--dwell-s", "1e9"], "'--dwell-s'"),
    (["twin", "waypoints", "--object", "cube", "-o", "{tmp}/w.yaml", "--dwell-s", "nan"], "'--dwell-s'"),
    (["twin", "waypoints", "--object", "cube", "-o", "{tmp}/w.yaml", "--placement", "nan,0,0"], "'--placement'"),
    (["twin", "waypoints", "--object", "cube", "-o", "{tmp}/w.yaml", "--distance-m", "inf"], "finite"),
    (["twin", "waypoints", "--object", "cube", "-o", "{tmp}/w.yaml", "--scale", "1e30"], "'--scale'"),
    (["twin", "record", "--object", "cube", "-w", "{g}/w.yaml", "-o", "{tmp}/s", "--resolution", "100000x100000"],
     "'--resolution'"),
    (["recording", "export", "{bag}", "-o", "{tmp}/x", "--start-ms", "nan"], "'--start-ms'"),
    (["recording", "export", "{bag}", "-o", "{tmp}/x", "--start-ms", "500", "--stop-ms", "100"], "not before"),
    (["import", "{g}", "-o", "{tmp}/imp", "--depth-scale-m", "0"], "'--depth-scale-m'"),
    (["twin", "generate", "-o", "{tmp}/gen", "--executor", "ray:nonsense"], "'--executor'"),
    (["twin", "generate", "-n", "1", "-o", "{tmp}/gen", "--views", "100000000"], "'--views'"),
])
def test_an_option_out_of_range_is_one_line_exit_2(argv: list[str], words: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    g = tmp_path / "g"
    g.mkdir()
    (g / "w.yaml").write_text("arms: {}\n")
    bag = Path(__file__).parent / "fixtures" / "recordings" / "rs257_uncompressed.bag"
    args = [a.format(g=g, tmp=tmp_path, bag=bag) for a in argv]
    with _NoRuntimeWarnings():
        assert run(args) == 2
    _one_error_line(capsys, words)


class _NoRuntimeWarnings:
    """No numpy RuntimeWarning (NaN comparisons) on the way to the error line."""

    def __enter__(self) -> None:
        import warnings

        self._catch = warnings.catch_warnings(record=True)
        self.caught = self._catch.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc: object) -> None:
        self._catch.__exit__(*exc)
        assert not [w for w in self.caught if issubclass(w.category, RuntimeWarning)], self.caught


def test_every_seed_option_refuses_a_negative_seed() -> None:
    import typer

    import darp.cli  # noqa: F401
    from darp.cli._app import app

    def leaves(command: Any) -> Any:
        children = getattr(command, "commands", None)
        if children:
            for child in children.values():
                yield from leaves(child)
        else:
            yield command

    seeds = [(c.name, p) for c in leaves(typer.main.get_command(app)) for p in c.params if p.name == "seed"]
    assert len(seeds) >= 5
    for name, param in seeds:
        assert param.type_descriptor.parameter_info.min == 0, name


def test_a_dead_ray_address_fails_in_seconds() -> None:
    import socket

    from darp.batch.executor import parse_executor, probe_ray_address

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    start = time.monotonic()
    with pytest.raises(DarpError, match="no Ray cluster reachable"):
        probe_ray_address(f"127.0.0.1:{port}")
    assert time.monotonic() - start < 10
    with pytest.raises(ConfigError):
        parse_executor("ray:not an address")
    assert parse_executor("ray:auto").address == "auto"


def _real_seq(tmp_path: Path) -> tuple[Path, Any]:
    import shutil

    from helpers.realdata import realdata

    real = realdata("3dmatch-frames")
    if not (real / "seq-01").is_dir():
        pytest.skip("needs the 3dmatch-frames real data")
    seq = tmp_path / "seq"
    shutil.copytree(real / "seq-01", seq)
    return seq, np.loadtxt(real / "camera-intrinsics.txt")


@pytest.mark.parametrize("damage", ["text", "size"])
def test_import_refuses_a_colour_image_it_cannot_use_instead_of_a_black_one(damage: str, tmp_path: Path) -> None:
    import cv2

    from darp.formats.trajectories import read_pose_txt
    from darp.processing.imported import ImportSpec, import_sequence

    seq, K = _real_seq(tmp_path)
    bad = seq / "frame-000116.color.png"  # not the first frame (the first is checked for registration already)
    if damage == "text":
        bad.write_bytes(b"root:x:0:0:root:/root:/bin/bash\n")
    else:
        cv2.imwrite(str(bad), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(FormatError, match="colour image") as caught:
        import_sequence(ImportSpec(seq, tmp_path / "imp", K, poses=read_pose_txt(seq), pose_source="x"))
    assert str(bad) in str(caught.value)
