"""The ChArUco calibration board in the MuJoCo twin: a textured quad on a thin backing plate.

The board is :class:`darp.formats.calibration.CharucoBoardSpec`, the same record calibration files and
capture sets store; its OpenCV board, inner corners and printed image come from
:mod:`darp.calibration.board`. This module adds only what drawing it needs: the texture's resolution
(:class:`BoardTexture`) and :func:`add_charuco_board`.

The board frame is OpenCV's ChArUco object frame: origin at the outer corner of the first chessboard
square (the top-left of the printed image), x along the columns, y along the rows, z into the board. The
printed face therefore faces -z; :func:`darp.calibration.board.corners_board_m` gives the inner corners
in this frame. ``T_parent_board`` places this frame in the parent MuJoCo body.

The board is a textured quad mesh (explicit texture coordinates, so the orientation is exact) in front
of a thin backing box (the physical plate, grey). MuJoCo samples textures with trilinear mipmapping, so
the texture's width and height must be multiples of 64: then every mipmap level the sampling uses has
exactly half the texels of the one above. With an odd level (e.g. 1366 -> 683 -> 341) the coarser
levels are stretched by a fraction of a texel, which moved rendered corners by a few hundredths of a
pixel depending on the viewing angle and biased the twin's calibrated base-to-base tilt by about
0.05 deg. :class:`BoardTexture` enforces the rule; its default (128 px per square, 32 px white margin)
meets it for every board.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from darp.calibration.board import board_image, board_size_m, validate_board
from darp.errors import TwinError
from darp.formats.calibration import CharucoBoardSpec
from darp.twin.camera.render import mujoco  # imported there after choosing the headless GL backend

TEXTURE_SIDE_MULTIPLE_PX = 64  # texture width and height: mipmap levels halve exactly (module docstring)
BOARD_THICKNESS_M = 0.003  # the backing plate; the printed face lies at the plate's top


@dataclass(frozen=True)
class BoardTexture:
    """How finely the twin draws a board: texels per chessboard square and the white margin in texels.

    About as fine as the camera sees the board at the closest working distance keeps it sharp: a 30 mm
    square at 0.3 m spans about 60 colour pixels (D435 colour at 640 x 480), so 128 px gives about 2
    texels per pixel. Sizes off the multiple-of-64 rule (module docstring) are refused with a hint.
    """

    px_per_square: int = 128
    margin_px: int = 32

    def __post_init__(self) -> None:
        if not isinstance(self.px_per_square, int) or not isinstance(self.margin_px, int):
            raise TwinError(f"board texture: px_per_square and margin_px must be integers, got "
                            f"{self.px_per_square!r} and {self.margin_px!r}")
        if self.px_per_square < 8 or self.margin_px < 0:
            raise TwinError(f"board texture: px_per_square must be >= 8 and margin_px >= 0, got "
                            f"{self.px_per_square} and {self.margin_px}")

    def size_px(self, board: CharucoBoardSpec) -> tuple[int, int]:
        """(width, height) of ``board``'s texture; a :class:`TwinError` unless both are multiples of 64."""
        width = board.squares_x * self.px_per_square + 2 * self.margin_px
        height = board.squares_y * self.px_per_square + 2 * self.margin_px
        if width % TEXTURE_SIDE_MULTIPLE_PX or height % TEXTURE_SIDE_MULTIPLE_PX:
            raise TwinError(
                f"board texture {width} x {height} px ({board.squares_x} x {board.squares_y} squares of "
                f"{self.px_per_square} px, {self.margin_px} px margin): width and height must be multiples "
                f"of {TEXTURE_SIDE_MULTIPLE_PX} or MuJoCo's mipmaps shift the rendered corners; "
                f"{self._advice(board)}")
        return width, height

    def _advice(self, board: CharucoBoardSpec) -> str:
        side, half = TEXTURE_SIDE_MULTIPLE_PX, TEXTURE_SIDE_MULTIPLE_PX // 2  # margins count twice
        squares = (board.squares_x, board.squares_y)
        px = self.px_per_square
        fitting = [m for m in range(half) if all((n * px + 2 * m) % side == 0 for n in squares)]
        if fitting:
            return f"with {px} px per square use margin_px {fitting[0]} (+ a multiple of {half})"
        return (f"no margin fits {px} px per square on this board; use a multiple of "
                f"{TEXTURE_SIDE_MULTIPLE_PX} px per square (default {BoardTexture.px_per_square} px, "
                f"{BoardTexture.margin_px} px margin)")

    def margin_m(self, board: CharucoBoardSpec) -> float:
        """The white margin around the squares in metres (a whole number of texels)."""
        return self.margin_px * board.square_length_m / self.px_per_square

    def extent_m(self, board: CharucoBoardSpec) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the textured area in the board frame: the squares plus the margin."""
        m = self.margin_m(board)
        w, h = board_size_m(board)
        return -m, -m, w + m, h + m

    def image(self, board: CharucoBoardSpec) -> np.ndarray:
        """The texture as a grey uint8 image (checked size); row 0 is the board's y = -margin edge."""
        self.size_px(board)
        return board_image(board, self.px_per_square, self.margin_px)


DEFAULT_TEXTURE = BoardTexture()


def add_charuco_board(
    spec: mujoco.MjSpec,
    board: CharucoBoardSpec,
    *,
    texture: BoardTexture = DEFAULT_TEXTURE,
    thickness_m: float = BOARD_THICKNESS_M,
    name: str = "charuco",
    parent: mujoco.MjsBody | None = None,
    T_parent_board: np.ndarray | None = None,
) -> str:
    """Add the board (texture, material, quad mesh, backing plate) to ``spec``; return the quad geom's name.

    The geoms are visual only (no contacts) and massless. Put the board in a mocap body to move it.
    An invalid board raises :class:`darp.errors.CalibrationError` (the board's own rules, from
    :func:`darp.calibration.board.validate_board`); a texture size off the multiple-of-64 rule, a bad
    pose or thickness raise :class:`TwinError`.
    """
    if not isinstance(board, CharucoBoardSpec):
        raise TwinError(f"board must be a darp.formats.calibration.CharucoBoardSpec, "
                        f"got {type(board).__name__}")
    validate_board(board)
    if not (np.isfinite(thickness_m) and thickness_m > 0.0):
        raise TwinError(f"board thickness must be positive, got {thickness_m} m")
    body = parent if parent is not None else spec.worldbody
    T = np.eye(4) if T_parent_board is None else np.asarray(T_parent_board, dtype=float)
    if T.shape != (4, 4):
        raise TwinError(f"T_parent_board must be 4x4, got shape {T.shape}")
    img = texture.image(board)
    rgb = np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    tex = spec.add_texture(
        name=f"{name}_tex",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        width=rgb.shape[1],
        height=rgb.shape[0],
        nchannel=3,
    )
    tex.data = rgb.tobytes()
    mat = spec.add_material(
        name=f"{name}_mat", rgba=[1, 1, 1, 1], specular=0.0, shininess=0.0, reflectance=0.0
    )
    mat.textures[int(mujoco.mjtTextureRole.mjTEXROLE_RGB)] = f"{name}_tex"

    x0, y0, x1, y1 = texture.extent_m(board)
    # Quad in the board plane z = 0, wound counter-clockwise seen from -z (the printed side).
    # Texture row 0 lies at v = 0 and is the board's y0 edge; column 0 (u = 0) is the x0 edge.
    mesh = spec.add_mesh(name=f"{name}_mesh", inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)
    mesh.uservert = [x0, y0, 0.0, x1, y0, 0.0, x1, y1, 0.0, x0, y1, 0.0]
    mesh.usertexcoord = [0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0]
    mesh.userface = [0, 2, 1, 0, 3, 2]

    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, T[:3, :3].reshape(-1).copy())
    pos = T[:3, 3]
    frame = body.add_frame(pos=pos, quat=quat)
    geom = frame.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=f"{name}_mesh",
        material=f"{name}_mat",
        contype=0,
        conaffinity=0,
        mass=0.0,
    )
    geom.rgba = [1, 1, 1, 1]
    half = [0.5 * (x1 - x0), 0.5 * (y1 - y0), 0.5 * thickness_m]
    frame.add_geom(
        name=f"{name}_plate",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=half,
        pos=[0.5 * (x0 + x1), 0.5 * (y0 + y1), half[2] + 1e-4],
        rgba=[0.5, 0.5, 0.5, 1],
        contype=0,
        conaffinity=0,
        mass=0.0,
    )
    return name


__all__ = ["BOARD_THICKNESS_M", "DEFAULT_TEXTURE", "TEXTURE_SIDE_MULTIPLE_PX", "BoardTexture",
           "add_charuco_board"]
