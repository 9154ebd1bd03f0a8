"""The capture folder format: round trip, atomic index, and one-line errors for bad folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD
from darp.calibration.captures import CaptureWriter, read_captures
from darp.errors import CalibrationError, FormatError
from helpers.calibration_synthetic import COLOR, T_DEPTH_COLOR


def _write(folder: Path, n: int = 2) -> None:
    writer = CaptureWriter(folder, DEFAULT_BOARD, source="test", notes={"k": 1})
    rng = np.random.default_rng(0)
    for k in range(n):
        arm = "arm110" if k % 2 == 0 else "arm111"
        image = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
        writer.add(arm=arm, camera_serial="348522076490" if arm == "arm110" else "405622074504", time_s=10.0 + k,
                   q_rad=np.full(6, 0.1 * k), q_std_rad=np.full(6, 1e-5), image=image, intrinsics=COLOR,
                   T_depth_stream=T_DEPTH_COLOR, extra={"planned_q_rad": [0.0] * 6})
    writer.close()


def test_round_trip(tmp_path: Path) -> None:
    _write(tmp_path, 3)
    caps = read_captures(tmp_path)
    assert caps.board == DEFAULT_BOARD and caps.source == "test" and caps.notes == {"k": 1}
    assert [c.capture_id for c in caps.captures] == ["arm110_000", "arm111_000", "arm110_001"]
    assert caps.arms == ("arm110", "arm111") and len(caps.for_arm("arm110")) == 2
    rec = caps.captures[2]
    assert np.allclose(rec.q_rad, 0.2) and np.allclose(rec.q_std_rad, 1e-5) and rec.time_s == 12.0
    assert rec.intrinsics == COLOR and np.allclose(rec.T_depth_stream, T_DEPTH_COLOR)
    assert rec.stream == "color" and rec.extra == {"planned_q_rad": [0.0] * 6}
    grey = caps.load_image(rec)
    assert grey.shape == (480, 640) and grey.dtype == np.uint8
    assert caps.truth_calibration_path() is None
    assert not list(tmp_path.glob("*.partial"))


def test_writer_refuses_existing_folder_and_bad_images(tmp_path: Path) -> None:
    _write(tmp_path)
    with pytest.raises(CalibrationError, match="already holds captures"):
        CaptureWriter(tmp_path, DEFAULT_BOARD)
    writer = CaptureWriter(tmp_path / "b", DEFAULT_BOARD)
    with pytest.raises(CalibrationError, match="image is 320x240 but the intrinsics are for 640x480"):
        writer.add(arm="arm110", camera_serial="1", time_s=0.0, q_rad=np.zeros(6),
                   image=np.zeros((240, 320), np.uint8), intrinsics=COLOR, T_depth_stream=np.eye(4))
    with pytest.raises(CalibrationError, match="stream must be one of"):
        writer.add(arm="arm110", camera_serial="1", time_s=0.0, q_rad=np.zeros(6), image=np.zeros((480, 640), np.uint8),
                   intrinsics=COLOR, T_depth_stream=np.eye(4), stream="depth")


def _edit(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("target, edit, message", [
    ("captures.json", lambda d: d.update(schema="other/1"), "schema: expected 'darp-calib-captures/1'"),
    ("captures.json", lambda d: d["board"].pop("dictionary"), "board: missing dictionary"),
    ("captures.json", lambda d: d["board"].update(marker_length_m=0.05),
     "board: marker_length_m must be smaller than square_length_m"),
    ("captures.json", lambda d: d["captures"][0].update(meta="../x.json"), "must be a file name inside"),
    ("captures.json", lambda d: d["captures"].append(dict(d["captures"][0])), "duplicate capture id"),
    ("arm110_000.json", lambda d: d.update(q_rad=[0.0] * 5), "q_rad: expected shape \\(6,\\)"),
    ("arm110_000.json", lambda d: d.update(stream="depth"), "stream: must be one of color, ir1"),
    ("arm110_000.json", lambda d: d["intrinsics"].pop("fx"), "intrinsics: missing fx"),
    ("arm110_000.json", lambda d: d.update(image_size=[320, 240]), "differs from the intrinsics"),
    ("arm110_000.json", lambda d: d["T_depth_stream"][0].__setitem__(0, 2.0), "T_depth_stream: not a rigid transform"),
    ("arm110_000.json", lambda d: d.pop("time_s"), "missing time_s"),
])
def test_bad_files_give_one_line_errors_naming_the_file(tmp_path: Path, target: str, edit, message: str) -> None:
    _write(tmp_path)
    _edit(tmp_path / target, edit)
    with pytest.raises(FormatError, match=message) as info:
        read_captures(tmp_path)
    assert target in str(info.value) and "\n" not in str(info.value)


def test_missing_folder_index_and_image(tmp_path: Path) -> None:
    with pytest.raises(FormatError, match="no such directory"):
        read_captures(tmp_path / "nope")
    with pytest.raises(FormatError, match="captures.json: no such file"):
        read_captures(tmp_path)
    _write(tmp_path)
    caps = read_captures(tmp_path)
    (tmp_path / "arm110_000.png").unlink()
    with pytest.raises(FormatError, match="capture arm110_000: image file is missing"):
        caps.load_image(caps.captures[0])
    (tmp_path / "arm111_000.png").write_bytes(b"not a png")
    with pytest.raises(FormatError, match="not a readable image"):
        caps.load_image(caps.captures[1])
