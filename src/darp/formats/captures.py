"""The any-arm captures folder of ``darp calib handeye`` (docs/any-arm.md), read as written::

    CAPTURES/
      handeye.yaml        board, pose conventions, mode, arm name (see :func:`load_sidecar`)
      images/<id>.png     board photographs (any OpenCV-readable image), or
      board_poses/<id>.*  the board in the camera per capture instead of images (4x4 .txt/.npy, or .npz
                          with OpenCV ``rvec``/``tvec``), metres
      poses.csv           id, x, y, z, q1..q4: base-from-flange, unit and quaternion order declared, or
      poses/<id>.txt|npy  4x4 base-from-flange per capture (unit declared)
      intrinsics.*        optional: 3x3 .txt/.npy, .npz (cameraMatrix, distCoeffs) or .json; solved from
                          the images when absent
      <arm>/...           two or more arms sharing one board: one such folder per arm (same layout)

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
from darp.formats.poses import PoseConventions, capture_key, pose_conventions, read_board_poses, read_poses
from darp.formats.text import read_yaml_mapping

SIDECAR = "handeye.yaml"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
INTRINSICS_NAMES = ("intrinsics.json", "intrinsics.npz", "intrinsics.npy", "intrinsics.txt", "camera_intrinsics.npz",
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


def _load_arm(folder: Path, arm: str, conv: PoseConventions) -> ArmCaptures:
    poses, source = read_poses(folder, conv)
    images: dict[str, Path] = {}
    if (folder / "images").is_dir():
        for f in sorted((folder / "images").iterdir()):
            if f.suffix.lower() in IMAGE_SUFFIXES:
                key = capture_key(f.stem)
                if key in images:
                    raise FormatError(f"two images for capture {key!r} ({images[key].name}, {f.name})", f.parent)
                images[key] = f
    board_poses = read_board_poses(folder / "board_poses") if (folder / "board_poses").is_dir() else {}
    if not images and not board_poses:
        raise FormatError("no images/ (board photographs) and no board_poses/ folder", folder)
    return ArmCaptures(arm, folder, poses, images, board_poses, source)


def _arm_camera(folder: Path) -> CameraModel | None:
    path = find_intrinsics(folder)
    return load_intrinsics(path) if path is not None else None


def read_capture_folder(root: str | Path, parse_board: Callable[[dict[str, Any], Path], BoardT],
                        intrinsics: str | Path | None = None, eye_to_hand: bool | None = None
                        ) -> CaptureFolder[BoardT]:
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
    if (root / "poses.csv").is_file() or (root / "poses").is_dir():
        arms = [_load_arm(root, str(side.get("arm", "arm")), conv)]
    else:
        subs = sorted(d for d in root.iterdir() if d.is_dir() and ((d / "poses.csv").is_file()
                                                                   or (d / "poses").is_dir()))
        if not subs:
            raise FormatError("no poses.csv or poses/ here nor in any arm sub-folder", root)
        arms = [_load_arm(d, d.name, conv) for d in subs]
        for a in arms:
            a.camera = _arm_camera(a.folder)
    ipath = Path(intrinsics) if intrinsics is not None else find_intrinsics(root)
    camera = load_intrinsics(ipath) if ipath is not None else None
    return CaptureFolder(root, board, conv, e2h, arms, camera)


__all__ = ["IMAGE_SUFFIXES", "INTRINSICS_NAMES", "SIDECAR", "ArmCaptures", "CaptureFolder", "find_intrinsics",
           "load_sidecar", "read_capture_folder"]
