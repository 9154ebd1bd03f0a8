"""The ChArUco board: spec validation, corner coordinates, and the printable PDF at true scale."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from darp.calibration.board import (
    DEFAULT_BOARD,
    board_image,
    choose_paper,
    corners_board_m,
    cv_board,
    make_board_spec,
    n_corners,
    write_board_pdf,
)
from darp.cli._app import run
from darp.errors import CalibrationError

PT_PER_MM = 72.0 / 25.4


def test_corners_are_a_planar_grid_of_the_square_length() -> None:
    P = corners_board_m(DEFAULT_BOARD)
    assert P.shape == (n_corners(DEFAULT_BOARD), 3) == (54, 3)
    assert np.all(P[:, 2] == 0.0)
    cols = DEFAULT_BOARD.squares_x - 1
    steps_x = np.diff(P.reshape(-1, cols, 3)[:, :, 0], axis=1)
    steps_y = np.diff(P.reshape(-1, cols, 3)[:, :, 1], axis=0)
    assert np.allclose(steps_x, 0.03) and np.allclose(steps_y, 0.03)
    assert np.allclose(P[0, :2], [0.03, 0.03])  # first inner corner: one square in from the board origin


@pytest.mark.parametrize("args, message", [
    ((10, 7, 0.03, 0.022, "DICT_9X9_1"), "unknown ArUco dictionary"),
    ((10, 7, 0.03, 0.035, "DICT_5X5_100"), "marker length"),
    ((2, 7, 0.03, 0.022, "DICT_5X5_100"), "at least 3 x 3"),
    ((20, 12, 0.03, 0.022, "DICT_5X5_100"), "needs 120 markers but DICT_5X5_100 has 100"),
])
def test_bad_board_specs_are_refused(args: tuple, message: str) -> None:
    with pytest.raises(CalibrationError, match=message):
        make_board_spec(*args)


def test_generated_image_is_detected_completely_by_opencv() -> None:
    image = board_image(DEFAULT_BOARD, px_per_square=60, margin_px=30)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board(DEFAULT_BOARD)).detectBoard(image)
    assert ids is not None and len(ids) == n_corners(DEFAULT_BOARD)
    # corner k sits at (margin + (col + 1) * square - 0.5) px: square edges fall between pixels
    cols = DEFAULT_BOARD.squares_x - 1
    k = ids.ravel()
    expected = 30 + 60 * np.stack([k % cols + 1, k // cols + 1], axis=1) - 0.5
    assert np.max(np.abs(corners.reshape(-1, 2) - expected)) < 0.1


def _pdf_streams(data: bytes) -> list[bytes]:
    out = []
    for m in re.finditer(rb"stream\r?\n", data):
        end = data.find(b"endstream", m.end())
        try:
            out.append(zlib.decompress(data[m.end():end]))
        except zlib.error:
            continue
    return out


def test_pdf_places_the_board_at_true_size(tmp_path: Path) -> None:
    path = tmp_path / "board.pdf"
    layout = write_board_pdf(DEFAULT_BOARD, path, px_per_square=100)
    data = path.read_bytes()
    assert data.startswith(b"%PDF")
    assert layout["paper"] == "A3"
    media = [float(v) for v in re.search(rb"/MediaBox \[ *([^\]]*)\]", data).group(1).split()]
    assert media[2] == pytest.approx(420 * PT_PER_MM, abs=0.01) and media[3] == pytest.approx(297 * PT_PER_MM, abs=0.01)
    # the image is drawn with "w 0 0 -h x y cm /I Do": its size on the page is the board's size
    draws = [s for s in _pdf_streams(data) if b" Do" in s]
    match = re.search(rb"([\d.]+) 0 0\s+(-?[\d.]+) ([\d.]+) ([\d.]+) cm /I\d+ Do",
                      b" ".join(draws).replace(b"\n", b" "))
    assert match is not None
    width_pt, height_pt = float(match.group(1)), abs(float(match.group(2)))
    assert width_pt == pytest.approx(300 * PT_PER_MM, abs=1e-3)
    assert height_pt == pytest.approx(210 * PT_PER_MM, abs=1e-3)
    # the embedded pattern is not resampled: exactly 100 image pixels per square
    assert re.search(rb"/Width 1000\b", data) and re.search(rb"/Height 700\b", data)
    assert b"ChArUco 10 x 7 squares, square 30.000 mm" in data  # the spec, in the PDF title


def test_paper_choice_and_refusal() -> None:
    assert choose_paper(make_board_spec(5, 4, 0.03, 0.022))[0] == "A4"
    assert choose_paper(DEFAULT_BOARD, "A2")[:1] == ("A2",)
    with pytest.raises(CalibrationError, match="does not fit on A4"):
        choose_paper(DEFAULT_BOARD, "A4")
    with pytest.raises(CalibrationError, match="unknown paper"):
        choose_paper(DEFAULT_BOARD, "B5")


def test_cli_board_writes_pdf_and_refuses_bad_spec(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert run(["calib", "board", "--out", str(tmp_path / "b.pdf"), "--squares-x", "6", "--squares-y", "5"]) == 0
    assert (tmp_path / "b.pdf").read_bytes().startswith(b"%PDF")
    assert "6 x 5 squares" in capsys.readouterr().out
    assert run(["calib", "board", "--out", str(tmp_path / "c.pdf"), "--marker-mm", "31"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "marker length" in err[0]
    assert not (tmp_path / "c.pdf").exists()
