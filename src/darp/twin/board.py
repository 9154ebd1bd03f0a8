"""A ChArUco calibration board for the MuJoCo twin: OpenCV board, texture image and a textured geom.

The board frame is OpenCV's ChArUco object frame: origin at the outer corner of the first chessboard
square (the top-left of ``CharucoBoard.generateImage``), x along the columns, y along the rows, z into
the board. The printed face therefore faces -z; ``CharucoBoard.getChessboardCorners()`` are the inner
corners in this frame, in metres. ``T_parent_board`` places this frame in the parent MuJoCo body.

The board is a textured quad mesh (explicit texture coordinates, so the orientation is exact) in front
of a thin backing box (the physical plate, grey). Texture resolution is set by ``px_per_square``: about
as fine as the camera sees it at the closest working distance keeps it sharp (MuJoCo samples textures
with trilinear mipmapping).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from darp.errors import TwinError
from darp.twin.render import mujoco  # imported there after choosing the headless GL backend

ARUCO_DICTIONARIES = {
    "DICT_4X4_50": cv2.aruco.DICT_4X4_50,
    "DICT_4X4_100": cv2.aruco.DICT_4X4_100,
    "DICT_5X5_100": cv2.aruco.DICT_5X5_100,
    "DICT_5X5_250": cv2.aruco.DICT_5X5_250,
    "DICT_6X6_250": cv2.aruco.DICT_6X6_250,
}


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board: squares, their metric size, marker size and dictionary; plus its printed margin."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.03
    marker_m: float = 0.022
    dictionary: str = "DICT_5X5_100"
    margin_m: float = 0.01  # white border printed around the squares
    px_per_square: int = 96  # texture resolution
    thickness_m: float = 0.003  # backing plate

    def __post_init__(self) -> None:
        if self.dictionary not in ARUCO_DICTIONARIES:
            raise TwinError(
                f"unknown ArUco dictionary {self.dictionary!r} (available: {', '.join(ARUCO_DICTIONARIES)})"
            )
        if self.squares_x < 2 or self.squares_y < 2:
            raise TwinError("a ChArUco board needs at least 2x2 squares")
        if not 0.0 < self.marker_m < self.square_m:
            raise TwinError(f"marker size {self.marker_m} m must be in (0, square size {self.square_m} m)")
        if self.margin_m < 0.0 or self.px_per_square < 8 or self.thickness_m <= 0.0:
            raise TwinError("board margin must be >= 0, px_per_square >= 8 and thickness > 0")

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the squared area in metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (for detection and object points)."""
        dictionary = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARIES[self.dictionary])
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary
        )

    def corners_board_m(self) -> np.ndarray:
        """(N, 3) inner chessboard corners in the board frame, indexed by ChArUco corner id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    def margin_px(self) -> int:
        return round(self.margin_m / self.square_m * self.px_per_square)

    def image(self) -> np.ndarray:
        """Printed board as a grey uint8 image, margin included; row 0 is the board's y = -margin edge."""
        s = self.px_per_square
        squares = self.cv_board().generateImage(
            (self.squares_x * s, self.squares_y * s), marginSize=0, borderBits=1
        )
        m = self.margin_px()
        return cv2.copyMakeBorder(squares, m, m, m, m, cv2.BORDER_CONSTANT, value=255)

    def extent_m(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the printed area in the board frame (squares plus the pixel-rounded margin)."""
        m = self.margin_px() * self.square_m / self.px_per_square
        w, h = self.size_m
        return -m, -m, w + m, h + m


def add_charuco_board(
    spec: mujoco.MjSpec,
    board: CharucoBoardSpec,
    *,
    name: str = "charuco",
    parent: mujoco.MjsBody | None = None,
    T_parent_board: np.ndarray | None = None,
) -> str:
    """Add the board (texture, material, quad mesh, backing plate) to ``spec``; return the quad geom's name.

    The geoms are visual only (no contacts) and massless. Put the board in a mocap body to move it.
    """
    body = parent if parent is not None else spec.worldbody
    T = np.eye(4) if T_parent_board is None else np.asarray(T_parent_board, dtype=float)
    if T.shape != (4, 4):
        raise TwinError(f"T_parent_board must be 4x4, got shape {T.shape}")
    img = board.image()
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

    x0, y0, x1, y1 = board.extent_m()
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
    half = [0.5 * (x1 - x0), 0.5 * (y1 - y0), 0.5 * board.thickness_m]
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
