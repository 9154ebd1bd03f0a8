"""Issue 32, inputs: every reader opens its file through darp.formats.io_input, so a named pipe, /dev/zero or a
folder given as any input is refused at once in one line naming it, and no read grows past its format's limit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from darp.errors import DarpError, FormatError
from darp.formats.io_input import LIMITS, decode_image, load_numpy, read_input_bytes


def _readers() -> dict[str, Callable[[Path], Any]]:
    from darp.calibration.captures import read_captures
    from darp.formats.arm_poses import read_arm_poses
    from darp.formats.calibration import read_calibration
    from darp.formats.intrinsics import load_intrinsics
    from darp.formats.schema import load_json_object
    from darp.formats.trajectories import read_nerfstudio_folder, read_tum_trajectory
    from darp.kinematics.rig import load_rig
    from darp.processing.results import read_results
    from darp.processing.settings import load_settings
    from darp.reconstruction.cloud_io import read_ply
    from darp.reconstruction.keyframe_io import read_keyframe, read_keyframe_index
    from darp.twin.settings import TwinSettings
    from darp.twin.waypoints import load_waypoints

    return {"calibration (-c)": read_calibration, "rig (--rig)": load_rig, "process settings": load_settings,
            "twin settings (--settings)": TwinSettings.load, "waypoints (-w)": load_waypoints,
            "arm_poses.csv": read_arm_poses, "capture JSON": load_json_object,
            "captures.json": lambda p: read_captures(p.parent), "intrinsics.npz": load_intrinsics,
            "transforms.json": read_nerfstudio_folder, "TUM trajectory": read_tum_trajectory,
            "keyframe .npz": read_keyframe, "keyframes.json": read_keyframe_index, "PLY cloud": read_ply,
            "results.json": read_results}


@pytest.fixture(scope="module")
def readers() -> dict[str, Callable[[Path], Any]]:
    return _readers()


# a folder given to these readers is read as the folder that holds the file, so "folder" is no special file there
FOLDER_READERS = ("transforms.json", "keyframes.json", "results.json")


@pytest.mark.parametrize(("name", "kind"), [(name, kind) for name in _readers() for kind in ("pipe", "zero", "folder")
                                            if not (kind == "folder" and name in FOLDER_READERS)])
def test_every_reader_refuses_a_special_file_at_once(name: str, kind: str, tmp_path: Path,
                                                     readers: dict[str, Callable[[Path], Any]]) -> None:
    fname = {"captures.json": "captures.json", "intrinsics.npz": "intrinsics.npz", "transforms.json": "transforms.json",
             "keyframes.json": "keyframes.json", "results.json": "results.json"}.get(name, "input.yaml")
    path = tmp_path / fname
    if kind == "pipe":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    start = time.monotonic()
    target = Path("/dev/zero") if kind == "zero" and name != "captures.json" else path
    if kind == "zero" and name == "captures.json":
        path.symlink_to("/dev/zero")
    with pytest.raises(DarpError) as caught:
        readers[name](target)
    assert time.monotonic() - start < 5
    message = str(caught.value)
    assert "\n" not in message and str(target) in message
    assert {"pipe": "named pipe", "zero": "character device", "folder": "folder"}[kind] in message, message


def test_a_read_never_grows_past_its_limit(tmp_path: Path) -> None:
    path = tmp_path / "big.json"
    path.write_bytes(b" " * 101)
    with pytest.raises(FormatError, match="over darp's limit"):
        read_input_bytes(path, "a JSON file", limit=100)
    assert read_input_bytes(path, limit=101) == b" " * 101
    assert LIMITS["yaml"] < LIMITS["json"]


def test_a_truncated_npz_is_one_line(tmp_path: Path) -> None:
    from darp.formats.intrinsics import load_intrinsics

    good = tmp_path / "good.npz"
    np.savez(good, K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
    assert load_numpy(good)["K"][0, 0] == 500.0
    bad = tmp_path / "intrinsics.npz"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(FormatError, match="truncated or damaged") as caught:
        load_intrinsics(bad)
    assert str(bad) in str(caught.value)


def test_a_huge_png_is_refused_from_its_header(tmp_path: Path) -> None:
    import cv2

    path = tmp_path / "big.png"
    assert cv2.imwrite(str(path), np.zeros((4, 4), np.uint8))
    data = bytearray(path.read_bytes())
    data[16:24] = (100000).to_bytes(4, "big") * 2  # IHDR width, height
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="100000x100000 pixels"):
        decode_image(path, cv2.IMREAD_UNCHANGED)


def _nerfstudio(folder: Path, frames: list[dict[str, Any]], **top: Any) -> Path:
    path = folder / "transforms.json"
    path.write_text(json.dumps({"fl_x": 500.0, "fl_y": 500.0, "cx": 320.0, "cy": 240.0, **top, "frames": frames}))
    return path


def test_transforms_json_listing_one_frame_100000_times_is_refused_quickly(tmp_path: Path) -> None:
    from darp.formats.trajectories import read_nerfstudio_folder

    frame = {"file_path": "rgb/0.png", "depth_file_path": "depth/0.png", "transform_matrix": np.eye(4).tolist()}
    path = _nerfstudio(tmp_path, [frame] * 100_000)
    start = time.monotonic()
    with pytest.raises(FormatError, match="frame 1 .*repeats frame 0 \\(duplicate frames\\)"):
        read_nerfstudio_folder(path)
    assert time.monotonic() - start < 10


def test_nerfstudio_focal_length_zero_is_one_line(tmp_path: Path) -> None:
    from darp.formats.trajectories import read_nerfstudio_folder

    frame = {"file_path": "rgb/0.png", "depth_file_path": "depth/0.png", "transform_matrix": np.eye(4).tolist()}
    with pytest.raises(FormatError, match="frame 0.*fx, fy > 0"):
        read_nerfstudio_folder(_nerfstudio(tmp_path, [frame], fl_x=0.0, fl_y=0.0))


@pytest.mark.parametrize("option", ["--rig", "-c"])
def test_cli_named_pipe_input_is_one_line_not_a_hang(option: str, tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    argv = ["rig", "show", "--rig", str(fifo)] if option == "--rig" else \
        ["calib", "check", str(tmp_path), "-c", str(fifo)]
    result = subprocess.run([sys.executable, "-m", "darp", *argv], capture_output=True, text=True, timeout=60,
                            env={**os.environ})
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and "named pipe" in result.stderr and str(fifo) in result.stderr


@pytest.mark.parametrize("chunk", [7, 64, 4 * 1024 * 1024])
def test_the_streamed_joint_log_equals_its_rows_at_any_piece_size(chunk: int, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """The reader parses pieces of the file; rows split across pieces, CRLF, blank lines and a cut-short last line
    come out as a whole-file read would (the expected arrays are computed here with numpy from the text)."""
    import darp.formats.arm_poses as arm_poses

    rng = np.random.default_rng(chunk)
    rows = []
    for k in range(300):
        arm = ("arm110", "arm111")[k % 2]
        rows.append((1.7e9 + k * 0.015, arm, *rng.uniform(-2, 2, 6)))
    lines = [f"{t:.6f},{a}," + ",".join(f"{v:.9f}" for v in q) for t, a, *q in rows]
    lines.insert(100, "")  # a blank line keeps the true line numbers
    text = "time_s,arm,q1,q2,q3,q4,q5,q6\r\n" + "\r\n".join(lines) + "\r\n1.0,arm1"  # cut short: dropped
    path = tmp_path / "arm_poses.csv"
    path.write_bytes(text.encode())
    monkeypatch.setattr(arm_poses, "CHUNK_BYTES", chunk)
    log = arm_poses.read_arm_poses(path)
    assert log.truncated_tail_line == len(lines) + 2
    for j, arm in enumerate(("arm110", "arm111")):
        mine = [r for r in rows if r[1] == arm]
        assert np.array_equal(log.times(arm), [float(f"{r[0]:.6f}") for r in mine])
        assert np.array_equal(log.joints(arm), [[float(f"{v:.9f}") for v in r[2:]] for r in mine])
        numbers = [n + 2 + (n >= 100) for n in range(j, 300, 2)]
        assert log.lines(arm).tolist() == numbers


def test_a_marker_that_is_a_pipe_still_marks_and_does_not_hang(tmp_path: Path) -> None:
    from darp.formats.survey import partial_survey_reason
    from darp.processing.runner import unfinished_reason

    os.mkfifo(tmp_path / "PARTIAL.txt")
    os.mkfifo(tmp_path / "UNFINISHED.txt")
    assert partial_survey_reason(tmp_path) == "PARTIAL.txt present"
    assert unfinished_reason(tmp_path) == "unfinished"


def test_a_rejected_survey_is_marked_partial_with_its_reason(tmp_path: Path) -> None:
    """A survey collect rejected (here: terminated by a controller fault) is flagged when processed, as a
    partial one is: its recordings are finalised and it otherwise looks whole."""
    from darp.acquisition.episode import Episode
    from darp.formats.survey import partial_survey_reason

    episode = Episode(tmp_path, "mug")
    folder = episode.reject("fault", "motion stopped by a fault: arm111: control loop stopped")
    assert folder.name == "mug.rejected"
    assert partial_survey_reason(folder) == "REJECTED.txt says 'rejected: fault'"
