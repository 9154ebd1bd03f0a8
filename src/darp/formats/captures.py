"""The any-arm captures folder of ``darp calib handeye`` (docs/any-arm.md), read as written::

    CAPTURES/
      handeye.yaml        board, pose conventions, mode, arm name (see :func:`load_sidecar`)
      images/<id>.png     board photographs (any OpenCV-readable image), or
      board_poses/<id>.*  the board in the camera per capture instead of images (4x4 .txt/.npy, or .npz
                          with OpenCV ``rvec``/``tvec``), metres
      poses.csv           id, x, y, z, q1..q4 (or id + 16 values): base-from-flange, unit and quaternion
                          order declared; also poses.npz / poses.json / poses.txt (darp.formats.pose_tables), or
      poses/<id>.txt|npy  4x4 base-from-flange per capture (unit declared)
      intrinsics.*        optional: 3x3 .txt/.npy, .npz (cameraMatrix, distCoeffs) or .json; solved from
                          the images when absent
      <arm>/...           two or more arms sharing one board: one such folder per arm (same layout)

Images, board poses and flange poses are paired by :mod:`darp.formats.pairing`'s rule (the file stem, role
words dropped; an id column; or an order file), the pairing kept in :attr:`ArmCaptures.pairing` to be printed.
The sidecar's ``board`` mapping is turned into a board by the caller's parser (calibration's
:func:`darp.calibration.board.parse_board`), so that this reader knows files, not calibration targets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np

from darp.errors import FormatError
from darp.formats.atomic import UNFINISHED_FILE
from darp.formats.intrinsics import CameraModel, load_intrinsics
from darp.formats.pairing import Pairing, pair_names, read_order_file, shift_poses
from darp.formats.pose_tables import PoseTable, read_pose_table, swapped_quaternion_table
from darp.formats.poses import PoseConventions, pose_conventions
from darp.formats.text import read_yaml_mapping

SIDECAR = "handeye.yaml"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
INTRINSICS_NAMES = ("intrinsics.json", "intrinsics.npz", "intrinsics.npy", "intrinsics.txt", "intrinsics.yaml",
                    "camera_info.yaml", "camera_info.json", "camera_intrinsics.npz", "camera_intrinsics.json",
                    "camera-intrinsics.txt")

BoardT = TypeVar("BoardT")


@dataclass
class ArmCaptures:
    """One arm's captures: flange poses and either images or board poses."""

    arm: str
    folder: Path
    T_base_flange: dict[str, np.ndarray]
    images: dict[str, Path] = field(default_factory=dict)
    board_poses: dict[str, np.ndarray] = field(default_factory=dict)
    pose_source: Path | None = None
    camera: CameraModel | None = None  # this arm's own intrinsics (an arm sub-folder's intrinsics.*)
    pairing: Pairing | None = None  # how images / board poses were paired with the flange poses
    table: PoseTable | None = None  # the flange poses as read
    swapped: dict[str, np.ndarray] | None = None  # the same poses read with the other quaternion order (by id)


@dataclass
class CaptureFolder(Generic[BoardT]):
    """A generic captures folder, loaded (poses in metres, not yet checked against the images)."""

    root: Path
    board: BoardT
    conventions: PoseConventions
    eye_to_hand: bool
    arms: list[ArmCaptures]
    camera: CameraModel | None
    image_size: tuple[int, int] | None = None


def load_sidecar(root: Path) -> dict[str, Any]:
    """``handeye.yaml``: ``board`` (type, squares_x, squares_y, square_mm, marker_mm, dictionary, legacy),
    ``unit`` (m | mm), ``quaternion`` (xyzw | wxyz), ``mode`` (eye_in_hand | eye_to_hand), ``arm`` (name)."""
    path = root / SIDECAR
    if not path.is_file():
        raise FormatError(f"no {SIDECAR} (it declares the board and the pose unit; see docs/any-arm.md)", root)
    return read_yaml_mapping(path)


def find_intrinsics(folder: Path) -> Path | None:
    """The folder's intrinsics file (the first of :data:`INTRINSICS_NAMES` present), or None."""
    for name in INTRINSICS_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


POSE_TABLES = ("poses.csv", "poses.txt", "poses.npz", "poses.json")


def find_pose_source(folder: Path) -> Path | None:
    """The folder's flange poses: ``poses.csv|txt|npz|json`` or a ``poses/`` folder, or None."""
    for name in POSE_TABLES:
        if (folder / name).is_file():
            return folder / name
    return folder / "poses" if (folder / "poses").is_dir() else None


@dataclass(frozen=True)
class PairingOptions:
    """How to pair (docs/any-arm.md, Pairing): an id column, an order file, a deliberate shift."""

    id_column: str | None = None
    order: Path | None = None
    shift: int = 0


def _load_arm(folder: Path, arm: str, conv: PoseConventions, how: PairingOptions = PairingOptions()) -> ArmCaptures:
    source = find_pose_source(folder)
    if source is None:
        raise FormatError("no poses.csv (or poses.txt/.npz/.json) and no poses/ folder (flange poses are required)",
                          folder)
    table = read_pose_table(source, conv, how.id_column)
    images = [f for f in sorted((folder / "images").iterdir()) if f.suffix.lower() in IMAGE_SUFFIXES] if (
        folder / "images").is_dir() else []
    bdir = folder / "board_poses"
    boards = read_pose_table(bdir, PoseConventions("m")) if bdir.is_dir() else None
    if not images and boards is None:
        raise FormatError("no images/ (board photographs) and no board_poses/ folder", folder)
    obs_names = [f.name for f in images] if images else list(boards.names.values()) if boards else []
    order = read_order_file(how.order) if how.order is not None else None
    pairing, omap, pmap = pair_names(obs_names, [table.names[k] for k in table.order], source, order=order,
                                     poses_have_ids=table.has_ids)
    by_name = {table.names[k]: T for k, T in table.poses.items()}
    flange = {pmap[n]: T for n, T in by_name.items() if n in pmap}
    img = {omap[f.name]: f for f in images if f.name in omap}
    bp = {omap[boards.names[k]]: T for k, T in boards.poses.items() if boards.names[k] in omap} if (
        boards is not None and not images) else {}
    if images and boards is not None:  # images win; board poses keyed by the same rule for captures without one
        bp = {omap.get(n, k): boards.poses[k] for k, n in boards.names.items()}
    other = swapped_quaternion_table(table, how.id_column)
    swapped = None
    if other is not None:
        swapped = {pmap[table.names[k]]: T for k, T in other.poses.items() if table.names.get(k) in pmap}
    if how.shift:
        ids = sorted(set(img) | set(bp))
        flange = shift_poses(flange, ids, how.shift)
        swapped = shift_poses(swapped, ids, how.shift) if swapped is not None else None
    return ArmCaptures(arm, folder, flange, img, bp, source, pairing=pairing, table=table, swapped=swapped)


def _arm_camera(folder: Path) -> CameraModel | None:
    path = find_intrinsics(folder)
    return load_intrinsics(path) if path is not None else None


def read_capture_folder(root: str | Path, parse_board: Callable[[dict[str, Any], Path], BoardT],
                        intrinsics: str | Path | None = None, eye_to_hand: bool | None = None,
                        how: PairingOptions = PairingOptions()) -> CaptureFolder[BoardT]:
    """Read a generic captures folder (one arm at its root, or one sub-folder per arm); the sidecar's
    ``board`` mapping becomes ``parse_board(mapping, sidecar path)``."""
    root = Path(root)
    if not root.is_dir():
        raise FormatError("captures folder not found", root)
    if (root / UNFINISHED_FILE).exists():
        raise FormatError(f"unfinished captures folder ({UNFINISHED_FILE}: the run that wrote it did not complete)",
                          root)
    side = load_sidecar(root)
    sidecar = root / SIDECAR
    if "board" not in side or not isinstance(side["board"], dict):
        raise FormatError("needs a 'board' mapping (type, squares_x, squares_y, square_mm, marker_mm, dictionary)",
                          sidecar)
    board = parse_board(side["board"], sidecar)
    conv = pose_conventions(side, sidecar)
    mode = str(side.get("mode", "eye_in_hand")).lower().replace("-", "_")
    if mode not in ("eye_in_hand", "eye_to_hand"):
        raise FormatError(f"mode {mode!r} is not eye_in_hand or eye_to_hand", sidecar)
    e2h = (mode == "eye_to_hand") if eye_to_hand is None else eye_to_hand
    if find_pose_source(root) is not None:
        arms = [_load_arm(root, str(side.get("arm", "arm")), conv, how)]
    else:
        subs = sorted(d for d in root.iterdir() if d.is_dir() and find_pose_source(d) is not None)
        if not subs:
            raise FormatError("no poses.csv (or .txt/.npz/.json) or poses/ here nor in any arm sub-folder", root)
        arms = [_load_arm(d, d.name, conv, how) for d in subs]
        for a in arms:
            a.camera = _arm_camera(a.folder)
    ipath = Path(intrinsics) if intrinsics is not None else find_intrinsics(root)
    camera = load_intrinsics(ipath) if ipath is not None else None
    return CaptureFolder(root, board, conv, e2h, arms, camera)


__all__ = ["IMAGE_SUFFIXES", "INTRINSICS_NAMES", "POSE_TABLES", "SIDECAR", "ArmCaptures", "CaptureFolder",
           "PairingOptions", "find_intrinsics", "find_pose_source", "load_sidecar", "read_capture_folder"]
