"""The twin's ChArUco board: one board record (the calibration's), the texture size rule, the drawn geometry.

Oracles: OpenCV's own ``CharucoBoard.generateImage`` (the texture MuJoCo holds must be exactly the
printed pattern plus a white margin) and MuJoCo's compiled model (texture size and bytes, plate size).
"""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from darp.calibration.board import DEFAULT_BOARD
from darp.errors import CalibrationError, TwinError
from darp.formats.calibration import CharucoBoardSpec
from darp.twin.camera.render import mujoco
from darp.twin.objects.board import BOARD_THICKNESS_M, BoardTexture, add_charuco_board

BOARD_7X5 = CharucoBoardSpec(squares_x=7, squares_y=5, square_length_m=0.03, marker_length_m=0.022,
                             dictionary="DICT_5X5_100")


def compiled(board: CharucoBoardSpec, **kwargs) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    add_charuco_board(spec, board, **kwargs)
    return spec.compile()


def opencv_texture(board: CharucoBoardSpec, px_per_square: int, margin_px: int) -> np.ndarray:
    """The printed pattern straight from OpenCV plus a white margin, as RGB (what the texture must hold)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cv = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_length_m,
                                board.marker_length_m, dictionary)
    grey = cv.generateImage((board.squares_x * px_per_square, board.squares_y * px_per_square), marginSize=0,
                            borderBits=1)
    grey = np.pad(grey, margin_px, constant_values=255)
    return np.repeat(grey[:, :, None], 3, axis=2)


def test_default_calibration_board_texture_is_128_px_per_square_with_32_px_margin() -> None:
    model = compiled(DEFAULT_BOARD)
    width, height = int(model.tex_width[0]), int(model.tex_height[0])
    assert (width, height) == (10 * 128 + 2 * 32, 7 * 128 + 2 * 32) == (1344, 960)
    assert width % 64 == 0 and height % 64 == 0
    texels = model.tex_data[: width * height * 3].reshape(height, width, 3)
    assert np.array_equal(texels, opencv_texture(DEFAULT_BOARD, 128, 32))
    # The drawn plate covers the squares plus the 32-texel margin: 32 * 30 mm / 128 = 7.5 mm a side.
    plate = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "charuco_plate")
    expected_half = [0.5 * (0.300 + 2 * 0.0075), 0.5 * (0.210 + 2 * 0.0075), 0.5 * BOARD_THICKNESS_M]
    np.testing.assert_allclose(model.geom_size[plate], expected_half, rtol=0, atol=1e-12)


def test_default_texture_meets_the_size_rule_for_every_board_shape() -> None:
    for squares_x in range(3, 16):
        for squares_y in range(3, 16):
            board = CharucoBoardSpec(squares_x, squares_y, 0.025, 0.018, "DICT_6X6_250")
            width, height = BoardTexture().size_px(board)
            assert width % 64 == 0 and height % 64 == 0, (squares_x, squares_y)


def test_texture_sizes_off_the_rule_are_refused_with_a_margin_that_works() -> None:
    off = BoardTexture(px_per_square=96, margin_px=32)  # 7 x 96 + 64 = 736 = 11.5 x 64
    with pytest.raises(TwinError, match="736 x 544 px .*multiples of 64") as err:
        off.size_px(BOARD_7X5)
    margin = int(re.search(r"use margin_px (\d+)", str(err.value)).group(1))
    assert BoardTexture(px_per_square=96, margin_px=margin).size_px(BOARD_7X5) == (704, 512)
    # The old 43 px margin (a margin_m of 10 mm) gave a 982 x 726 texture: refused, never silently drawn.
    spec = mujoco.MjSpec()
    with pytest.raises(TwinError, match="982 x 726 px"):
        add_charuco_board(spec, BOARD_7X5, texture=BoardTexture(px_per_square=128, margin_px=43))
    assert len(spec.textures) == 0


def test_texture_that_no_margin_can_fix_says_so() -> None:
    # 10 x 96 = 960 asks for a margin that is a multiple of 32 px, 7 x 96 = 672 for one 16 px off that.
    with pytest.raises(TwinError, match="no margin fits 96 px per square"):
        BoardTexture(px_per_square=96, margin_px=0).size_px(DEFAULT_BOARD)


def test_a_smaller_texture_that_meets_the_rule_is_drawn_as_asked() -> None:
    model = compiled(BOARD_7X5, texture=BoardTexture(px_per_square=64, margin_px=0), thickness_m=0.005)
    assert (int(model.tex_width[0]), int(model.tex_height[0])) == (448, 320)
    texels = model.tex_data[: 448 * 320 * 3].reshape(320, 448, 3)
    assert np.array_equal(texels, opencv_texture(BOARD_7X5, 64, 0))
    plate = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "charuco_plate")
    np.testing.assert_allclose(model.geom_size[plate], [0.105, 0.075, 0.0025], rtol=0, atol=1e-12)


def test_bad_boards_textures_and_thicknesses_are_refused() -> None:
    with pytest.raises(TwinError, match="px_per_square must be >= 8"):
        BoardTexture(px_per_square=4)
    with pytest.raises(TwinError, match="integers"):
        BoardTexture(px_per_square=128.0)  # type: ignore[arg-type]
    with pytest.raises(TwinError, match="thickness"):
        add_charuco_board(mujoco.MjSpec(), BOARD_7X5, thickness_m=0.0)
    with pytest.raises(TwinError, match="CharucoBoardSpec"):
        add_charuco_board(mujoco.MjSpec(), {"squares_x": 7})  # type: ignore[arg-type]
    too_many_markers = CharucoBoardSpec(12, 12, 0.03, 0.022, "DICT_4X4_50")  # needs 72 of 50 markers
    with pytest.raises(CalibrationError, match="needs 72 markers"):
        add_charuco_board(mujoco.MjSpec(), too_many_markers)
