"""The calibration board: its spec, the OpenCV board object, corner coordinates, a printable PDF.

darp's own board is a ChArUco board whose spec is :class:`darp.formats.calibration.CharucoBoardSpec`
(squares, square and marker length, ArUco dictionary), the same record the calibration file stores, so
that a calibration names the board it came from. :class:`Board` is the general target: that spec, or
another arm's ChArUco (OpenCV's legacy layout too) or chessboard as an any-arm captures folder declares it
(:func:`parse_board`); the OpenCV board and the corner coordinates of both come from it.

The board frame is OpenCV's ChArUco object frame: origin at the outer corner of the first chessboard square
(top-left of the printed image), x along the columns, y along the rows (down on the print), z into the board;
the printed face looks along -z. Corners are indexed by their ChArUco id.

``write_board_pdf`` prints the board at true physical size: the image is embedded unresampled (each
square an exact number of image pixels) in an axes whose extent on the page is the board's size in
points, on a page of standard paper size. The spec, the frame axes and a 100 mm ruler are printed
beside it, so that a print at the wrong scale is caught with a ruler before it is used.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from darp.errors import CalibrationError, FormatError
from darp.formats.atomic import atomic_path
from darp.formats.calibration import CharucoBoardSpec

# Dictionaries a board may use: OpenCV's predefined ArUco dictionaries (name -> (id, size)).
ARUCO_DICTIONARIES: dict[str, tuple[int, int]] = {
    name: (getattr(cv2.aruco, name), int(name.rsplit("_", 1)[1]))
    for name in (
        "DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000",
        "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000",
        "DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000",
        "DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000",
    )
}

# darp's default board: 10 x 7 squares of 30 mm (300 x 210 mm, fits A3 with its ruler), 22 mm markers.
# At 0.6 m a square spans about 30 colour pixels (D435 colour at 640x480), enough for 5x5 markers.
DEFAULT_BOARD = CharucoBoardSpec(squares_x=10, squares_y=7, square_length_m=0.030, marker_length_m=0.022,
                                 dictionary="DICT_5X5_100")

PAPER_SIZES_MM: dict[str, tuple[float, float]] = {  # portrait width, height
    "A4": (210.0, 297.0), "A3": (297.0, 420.0), "A2": (420.0, 594.0), "A1": (594.0, 841.0),
    "A0": (841.0, 1189.0), "letter": (215.9, 279.4), "tabloid": (279.4, 431.8),
}
_MM_PER_INCH = 25.4


@dataclass(frozen=True)
class Board:
    """A calibration target: ChArUco (any size and dictionary, OpenCV's legacy layout too) or chessboard.

    ``squares_x`` x ``squares_y`` squares of ``square_m``; the inner corners are the targets, numbered
    row by row (ChArUco: its corner ids). Board frame: OpenCV's, origin at the first inner corner's
    square's outer corner (ChArUco) or at the first inner corner (chessboard), z into the board.
    """

    kind: str  # "charuco" | "chessboard"
    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"
    legacy: bool = False

    @classmethod
    def from_spec(cls, spec: CharucoBoardSpec) -> Board:
        """darp's ChArUco board of a calibration or capture file's spec."""
        return cls("charuco", spec.squares_x, spec.squares_y, spec.square_length_m, spec.marker_length_m,
                   spec.dictionary)

    def cv_charuco(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ``CharucoBoard`` (ChArUco boards only)."""
        d = cv2.aruco.getPredefinedDictionary(ARUCO_DICTIONARIES[self.dictionary][0])
        b = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)
        b.setLegacyPattern(self.legacy)
        return b

    def corners_m(self) -> np.ndarray:
        """(N, 3) inner corners in the board frame, row k = corner id k."""
        if self.kind == "charuco":
            return np.asarray(self.cv_charuco().getChessboardCorners(), np.float64).reshape(-1, 3)
        nx, ny = self.squares_x - 1, self.squares_y - 1
        g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), axis=-1).reshape(-1, 2) * self.square_m
        return np.concatenate([g, np.zeros((len(g), 1))], axis=1)

    def spec(self) -> CharucoBoardSpec | None:
        """The calibration file's board record (ChArUco only)."""
        if self.kind != "charuco":
            return None
        return CharucoBoardSpec(self.squares_x, self.squares_y, self.square_m, self.marker_m, self.dictionary)

    def describe(self) -> dict[str, Any]:
        return {"type": self.kind, "squares_x": self.squares_x, "squares_y": self.squares_y,
                "square_mm": self.square_m * 1e3, "marker_mm": self.marker_m * 1e3,
                "dictionary": self.dictionary, "legacy": self.legacy}


def parse_board(data: dict[str, Any], path: Path) -> Board:
    """A :class:`Board` from an any-arm sidecar's ``board`` mapping (lengths in mm, as printed); a FormatError
    naming the sidecar when it is not a board OpenCV can make."""
    kind = str(data.get("type", "charuco")).lower()
    try:
        sx, sy = int(data["squares_x"]), int(data["squares_y"])
        square = float(data["square_mm"]) / 1e3
    except (KeyError, TypeError, ValueError) as err:
        raise FormatError(f"board needs squares_x, squares_y and square_mm ({err})", path) from None
    if not (np.isfinite(square) and 0 < square <= 1.0):
        raise FormatError(f"board.square_mm: must be within (0, 1000] mm, got {square * 1e3:g}", path)
    if max(sx, sy) > 200:
        raise FormatError(f"board: {sx} x {sy} squares is not a printable board (at most 200 a side)", path)
    if kind == "chessboard":  # OpenCV finds at least 3 x 3 inner corners: 4 x 4 squares
        if sx < 4 or sy < 4:
            raise FormatError(f"board: a chessboard needs at least 4 x 4 squares (3 x 3 inner corners), got "
                              f"{sx} x {sy}", path)
        return Board("chessboard", sx, sy, square)
    if sx < 3 or sy < 3:
        raise FormatError(f"board: a ChArUco board needs at least 3 x 3 squares, got {sx} x {sy}", path)
    if kind != "charuco":
        raise FormatError(f"board type {kind!r} is not charuco or chessboard", path)
    dictionary = str(data.get("dictionary", "DICT_5X5_100")).upper()
    if dictionary not in ARUCO_DICTIONARIES:
        raise FormatError(f"unknown ArUco dictionary {dictionary!r} (known: {', '.join(ARUCO_DICTIONARIES)})", path)
    try:
        marker = float(data["marker_mm"]) / 1e3
    except (KeyError, TypeError, ValueError):
        raise FormatError("a ChArUco board needs marker_mm", path) from None
    if not 0 < marker < square:
        raise FormatError(f"marker_mm {marker * 1e3:g} must be in (0, square_mm {square * 1e3:g})", path)
    if (sx * sy) // 2 > ARUCO_DICTIONARIES[dictionary][1]:
        raise FormatError(f"a {sx} x {sy} board needs {(sx * sy) // 2} markers but {dictionary} has "
                          f"{ARUCO_DICTIONARIES[dictionary][1]}", path)
    return Board("charuco", sx, sy, square, marker, dictionary, bool(data.get("legacy", False)))


def make_board_spec(squares_x: int, squares_y: int, square_length_m: float, marker_length_m: float,
                    dictionary: str = "DICT_5X5_100") -> CharucoBoardSpec:
    """A validated board spec (see :func:`validate_board`)."""
    spec = CharucoBoardSpec(int(squares_x), int(squares_y), float(square_length_m), float(marker_length_m),
                            str(dictionary))
    validate_board(spec)
    return spec


def validate_board(spec: CharucoBoardSpec) -> None:
    """Raise :class:`CalibrationError` for a board OpenCV cannot make or detect reliably."""
    if spec.dictionary not in ARUCO_DICTIONARIES:
        raise CalibrationError(f"unknown ArUco dictionary {spec.dictionary!r} "
                               f"(known: {', '.join(ARUCO_DICTIONARIES)})")
    if spec.squares_x < 3 or spec.squares_y < 3:
        raise CalibrationError(f"a ChArUco board needs at least 3 x 3 squares, got "
                               f"{spec.squares_x} x {spec.squares_y}")
    if not (np.isfinite(spec.square_length_m) and spec.square_length_m > 0):
        raise CalibrationError(f"square length must be positive, got {spec.square_length_m}")
    if not 0.0 < spec.marker_length_m < spec.square_length_m:
        raise CalibrationError(f"marker length {spec.marker_length_m} m must be in (0, square length "
                               f"{spec.square_length_m} m)")
    need = n_markers(spec)
    size = ARUCO_DICTIONARIES[spec.dictionary][1]
    if need > size:
        raise CalibrationError(f"a {spec.squares_x} x {spec.squares_y} board needs {need} markers but "
                               f"{spec.dictionary} has {size}")


def n_markers(spec: CharucoBoardSpec) -> int:
    """Number of ArUco markers on the board (the white squares)."""
    return (spec.squares_x * spec.squares_y) // 2


def n_corners(spec: CharucoBoardSpec) -> int:
    """Number of inner chessboard corners (ChArUco corner ids 0 .. n-1)."""
    return (spec.squares_x - 1) * (spec.squares_y - 1)


def board_size_m(spec: CharucoBoardSpec) -> tuple[float, float]:
    """Width (x) and height (y) of the squared area in metres."""
    return spec.squares_x * spec.square_length_m, spec.squares_y * spec.square_length_m


def cv_board(spec: CharucoBoardSpec) -> cv2.aruco.CharucoBoard:
    """The OpenCV ``CharucoBoard`` for detection and object points."""
    validate_board(spec)
    return Board.from_spec(spec).cv_charuco()


def corners_board_m(spec: CharucoBoardSpec) -> np.ndarray:
    """(N, 3) inner corners in the board frame (z = 0), row k = ChArUco corner id k."""
    validate_board(spec)
    return Board.from_spec(spec).corners_m()


def board_image(spec: CharucoBoardSpec, px_per_square: int = 200, margin_px: int = 0) -> np.ndarray:
    """The printed pattern as a grey uint8 image; every square is exactly ``px_per_square`` pixels."""
    if px_per_square < 8:
        raise CalibrationError(f"px_per_square must be at least 8, got {px_per_square}")
    s = int(px_per_square)
    image = cv_board(spec).generateImage((spec.squares_x * s, spec.squares_y * s), marginSize=0, borderBits=1)
    if margin_px > 0:
        image = cv2.copyMakeBorder(image, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT,
                                   value=255)
    return image


def spec_text(spec: CharucoBoardSpec) -> str:
    """One line describing the board, as printed on it."""
    w, h = board_size_m(spec)
    return (f"ChArUco {spec.squares_x} x {spec.squares_y} squares, square {spec.square_length_m * 1e3:.3f} mm, "
            f"marker {spec.marker_length_m * 1e3:.3f} mm, {spec.dictionary}, pattern {w * 1e3:.1f} x "
            f"{h * 1e3:.1f} mm")


def choose_paper(spec: CharucoBoardSpec, paper: str = "auto", margin_mm: float = 12.0,
                 text_mm: float = 32.0) -> tuple[str, float, float]:
    """(name, width_mm, height_mm) of the page: the given paper, or the smallest that holds board and text.

    The page is turned to landscape when the board is wider than tall.
    """
    w_mm, h_mm = (v * 1e3 for v in board_size_m(spec))
    need_w, need_h = w_mm + 2 * margin_mm, h_mm + 2 * margin_mm + text_mm
    names = list(PAPER_SIZES_MM) if paper == "auto" else [paper]
    if paper != "auto" and paper not in PAPER_SIZES_MM:
        raise CalibrationError(f"unknown paper {paper!r} (known: auto, {', '.join(PAPER_SIZES_MM)})")
    for name in names:
        pw, ph = PAPER_SIZES_MM[name]
        if w_mm > h_mm:
            pw, ph = ph, pw
        if pw >= need_w and ph >= need_h:
            return name, pw, ph
    raise CalibrationError(f"the {w_mm:.0f} x {h_mm:.0f} mm board does not fit on "
                           f"{'any standard paper' if paper == 'auto' else paper} with its ruler and text")


def write_board_pdf(spec: CharucoBoardSpec, path: str | Path, *, paper: str = "auto",
                    px_per_square: int = 200) -> dict[str, Any]:
    """Write a printable PDF of the board at true scale; returns the layout (page and board in mm).

    Print at 100 % ("actual size"); check the 100 mm ruler and the pattern width with a rule.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    validate_board(spec)
    name, page_w, page_h = choose_paper(spec, paper)
    w_mm, h_mm = (v * 1e3 for v in board_size_m(spec))
    left = (page_w - w_mm) / 2.0
    bottom = page_h - 12.0 - h_mm  # board near the top, text and ruler below it
    fig = Figure(figsize=(page_w / _MM_PER_INCH, page_h / _MM_PER_INCH))
    ax = fig.add_axes((left / page_w, bottom / page_h, w_mm / page_w, h_mm / page_h))
    ax.imshow(board_image(spec, px_per_square), cmap="gray", vmin=0, vmax=255, interpolation="none",
              extent=(0.0, w_mm, h_mm, 0.0), aspect="auto")
    ax.set_xlim(0.0, w_mm)
    ax.set_ylim(h_mm, 0.0)
    ax.set_axis_off()
    # Board frame: origin at the top-left corner of the first square, x right, y down (z into the board).
    page = fig.add_axes((0.0, 0.0, 1.0, 1.0), facecolor="none")
    page.set_xlim(0.0, page_w)
    page.set_ylim(0.0, page_h)
    page.set_axis_off()
    ox, oy = left, bottom + h_mm
    arrow = {"arrowstyle": "->", "lw": 0.8, "color": "tab:red"}
    page.annotate("", xy=(ox + 15, oy + 4), xytext=(ox, oy + 4), arrowprops=arrow)
    page.annotate("", xy=(ox - 4, oy - 15), xytext=(ox - 4, oy), arrowprops=arrow)
    page.text(ox + 16, oy + 4, "x", color="tab:red", fontsize=7, va="center")
    page.text(ox - 4, oy - 17, "y", color="tab:red", fontsize=7, ha="center", va="top")
    page.plot([ox], [oy], marker="+", color="tab:red", markersize=6)
    y_text = bottom - 7.0
    page.text(left, y_text, spec_text(spec), fontsize=8, va="top")
    page.text(left, y_text - 5.0, f"darp calibration board. Print at 100 % (actual size) on {name}; the "
              "bar below must measure 100 mm and the pattern its width above.", fontsize=6.5, va="top")
    y_bar = y_text - 17.0
    page.plot([left, left + 100.0], [y_bar, y_bar], color="black", lw=0.8)
    for k in range(101):
        tick = 3.0 if k % 10 == 0 else (2.0 if k % 5 == 0 else 1.0)
        page.plot([left + k, left + k], [y_bar, y_bar + tick], color="black", lw=0.3)
        if k % 10 == 0:
            page.text(left + k, y_bar + 3.6, str(k), fontsize=5, ha="center", va="bottom")
    page.text(left + 103.0, y_bar, "100 mm", fontsize=6, va="center")
    path = Path(path)
    pdf = io.BytesIO()  # rendered in memory: a full disk then fails a plain write, not matplotlib's PDF stream
    fig.savefig(pdf, format="pdf", metadata={"Title": spec_text(spec), "Creator": "darp calib board"})
    with atomic_path(path) as tmp:
        tmp.write_bytes(pdf.getvalue())
    return {"paper": name, "page_mm": (page_w, page_h), "board_origin_mm": (left, page_h - bottom - h_mm),
            "board_size_mm": (w_mm, h_mm), "px_per_square": px_per_square}


__all__ = [
    "ARUCO_DICTIONARIES", "DEFAULT_BOARD", "PAPER_SIZES_MM", "Board", "board_image", "board_size_m",
    "choose_paper", "corners_board_m", "cv_board", "make_board_spec", "n_corners", "n_markers", "parse_board",
    "spec_text", "validate_board", "write_board_pdf",
]
