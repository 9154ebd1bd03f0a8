"""Hand-eye calibration for any arm: a documented captures folder, detection, darp's solver, held-out checks.

The folder (docs/any-arm.md)::

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

The solve reuses darp's calibration chain (:mod:`darp.calibration.model`, ``handeye``, ``refine``) with
measured flange poses in place of the Z1's forward kinematics (``Observations.T_base_flange``) and no
joint-zero offsets. Eye-to-hand (camera fixed, board on the flange) is the same problem with the flange
poses inverted: the solver's "hand-eye" is then the camera in the base and its "board" the board on the
flange.

Quality: k-fold over captures, each fold calibrated without its captures, and for each withheld capture
(a) its corners' errors (:func:`darp.calibration.evaluate.kfold_heldout`) and (b) **board consistency**:
the board placed in the base by that capture alone (``F_i X T_cam_board_i``) against the calibration's
board, as the distance of the board's centre (mm) and the rotation angle (deg).
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np

from darp.calibration import handeye
from darp.calibration.board import ARUCO_DICTIONARIES
from darp.calibration.detect import board_pose_pnp
from darp.calibration.evaluate import fold_assignment, kfold_heldout, summarise
from darp.calibration.model import ChainParams, Observations, flange_poses, reprojection_errors
from darp.calibration.refine import RefineSettings, refine
from darp.errors import CalibrationError, FormatError
from darp.formats.calibration import ArmCalibration, Calibration, CharucoBoardSpec
from darp.formats.text import read_yaml_mapping
from darp.kinematics.transforms import invert_transform, pose_error, quaternion_to_rotation

SIDECAR = "handeye.yaml"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
POSE_SUFFIXES = (".txt", ".npy", ".csv")
OPENCV_METHODS = tuple(f"calibrateHandEye/{m}" for m in handeye.HAND_EYE_METHODS)


# -- board --------------------------------------------------------------------------------------------

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

    def cv_charuco(self) -> cv2.aruco.CharucoBoard:
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
    """A :class:`Board` from the sidecar's ``board`` mapping (lengths in mm, as printed)."""
    kind = str(data.get("type", "charuco")).lower()
    try:
        sx, sy = int(data["squares_x"]), int(data["squares_y"])
        square = float(data["square_mm"]) / 1e3
    except (KeyError, TypeError, ValueError) as err:
        raise FormatError(f"board needs squares_x, squares_y and square_mm ({err})", path) from None
    if kind == "chessboard":
        if sx < 3 or sy < 3:
            raise FormatError(f"a chessboard needs at least 3 x 3 squares, got {sx} x {sy}", path)
        return Board("chessboard", sx, sy, square)
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


def detect_corners(board: Board, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ids (N,), distorted pixels (N, 2)) of the board's inner corners in an 8-bit grey image."""
    if board.kind == "charuco":
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        charuco = cv2.aruco.CharucoParameters()
        charuco.tryRefineMarkers = True
        corners, ids, _, _ = cv2.aruco.CharucoDetector(board.cv_charuco(), charuco, params).detectBoard(grey)
        if ids is None or len(ids) == 0:
            return np.zeros(0, int), np.zeros((0, 2))
        ids = ids.reshape(-1).astype(int)
        order = np.argsort(ids, kind="stable")
        return ids[order], corners.reshape(-1, 2).astype(np.float64)[order]
    size = (board.squares_x - 1, board.squares_y - 1)
    found, pts = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not found:
        found, pts = cv2.findChessboardCorners(grey, size)
        if not found:
            return np.zeros(0, int), np.zeros((0, 2))
        pts = cv2.cornerSubPix(grey, pts, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3))
    return np.arange(size[0] * size[1]), pts.reshape(-1, 2).astype(np.float64)


# -- intrinsics ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CameraModel:
    """OpenCV pinhole + distortion (k1, k2, p1, p2[, k3 ...])."""

    K: np.ndarray
    dist: np.ndarray
    source: str = ""
    model: str = "Brown Conrady"  # librealsense's name; "Brown Conrady" is OpenCV's model

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> ideal pinhole pixels of the same K."""
        if not np.any(self.dist) or len(uv) == 0:
            return np.asarray(uv, np.float64)
        if self.model != "Brown Conrady":  # a RealSense model: librealsense's own equations
            from darp.calibration.geometry import undistort_pixels
            from darp.formats.realsense.types import Intrinsics

            K = self.K
            c = tuple(float(v) for v in (list(self.dist) + [0.0] * 5)[:5])
            intr = Intrinsics(int(round(2 * K[0, 2] + 1)), int(round(2 * K[1, 2] + 1)), float(K[0, 0]),
                              float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), self.model, c)  # type: ignore[arg-type]
            return np.asarray(undistort_pixels(np.asarray(uv, np.float64), intr))
        out = cv2.undistortPoints(np.asarray(uv, np.float64).reshape(-1, 1, 2), self.K, self.dist, P=self.K)
        return cast(np.ndarray, out.reshape(-1, 2))


def _check_K(K: np.ndarray, path: Path) -> np.ndarray:
    K = np.asarray(K, np.float64).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and abs(K[2, 2] - 1) < 1e-9
            and K[2, 0] == 0 and K[2, 1] == 0):
        raise FormatError("not a 3x3 camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] (check row/column order)", path)
    return K


def load_intrinsics(path: str | Path) -> CameraModel:
    """Intrinsics from a 3x3 text/.npy, an .npz (``cameraMatrix``/``K``, ``distCoeffs``/``dist``), JSON, or a
    RealSense recording (``.bag``/``.db3``: its colour stream, to which aligned depth is registered).

    JSON: ``{"K": 3x3}`` or ``{"fx", "fy", "cx"|"ppx", "cy"|"ppy"}``, optional ``"dist"``/``"coeffs"``;
    a nerfstudio-style ``fl_x``/``fl_y`` works too. A text file may hold the 3x3 then one distortion line.
    """
    p = Path(path)
    if not p.is_file():
        raise FormatError("intrinsics file not found", p)
    if p.suffix in (".bag", ".db3"):
        return _recording_intrinsics(p)
    dist = np.zeros(5)
    try:
        if p.suffix == ".npz":
            with np.load(p) as z:
                key = next((k for k in ("cameraMatrix", "camera_matrix", "K", "mtx") if k in z), None)
                if key is None:
                    raise FormatError(f"no cameraMatrix/K array (has {', '.join(z.files)})", p)
                K = z[key]
                dk = next((k for k in ("distCoeffs", "dist_coeffs", "dist", "D") if k in z), None)
                if dk is not None:
                    dist = np.asarray(z[dk], np.float64).reshape(-1)
        elif p.suffix == ".npy":
            K = np.load(p)
        elif p.suffix == ".json":
            d = json.loads(p.read_text(encoding="utf-8"))
            if "K" in d or "camera_matrix" in d:
                K = np.asarray(d.get("K", d.get("camera_matrix")), np.float64)
            else:
                fx = d.get("fx", d.get("fl_x"))
                fy = d.get("fy", d.get("fl_y", fx))
                cx = d.get("cx", d.get("ppx"))
                cy = d.get("cy", d.get("ppy"))
                if None in (fx, cx, cy):
                    raise FormatError("JSON intrinsics need K, or fx, fy, cx, cy", p)
                K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)
            for k in ("dist", "coeffs", "distortion", "dist_coeffs"):
                if k in d:
                    dist = np.asarray(d[k], np.float64).reshape(-1)
                    break
            else:
                dist = np.array([d.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")], np.float64)
        else:
            rows = [r for r in (line.replace(",", " ").split() for line in p.read_text(encoding="utf-8")
                                .splitlines() if line.strip() and not line.lstrip().startswith("#")) if r]
            vals = [[float(v) for v in r] for r in rows]
            K = np.array(vals[:3], np.float64)
            if len(vals) > 3:
                dist = np.array(vals[3], np.float64)
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read intrinsics ({err})", p) from None
    return CameraModel(_check_K(K, p), np.asarray(dist, np.float64), str(p))


def _recording_intrinsics(p: Path) -> CameraModel:
    from darp.formats.realsense import open_recording

    with open_recording(p) as rec:
        key = "color" if "color" in rec.streams else "depth"
        i = rec.stream(key).intrinsics
    if i is None:
        raise FormatError(f"the recording's {key} stream has no intrinsics", p)
    return CameraModel(i.K, np.asarray(i.coeffs, np.float64), f"{p} ({key} stream)",
                       "Brown Conrady" if i.model == "None" else i.model)


# -- poses --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseConventions:
    """How pose files are written: the translation unit and the quaternion order."""

    unit: str = "m"  # "m" | "mm"
    quaternion: str = "xyzw"  # "xyzw" | "wxyz"

    @property
    def scale(self) -> float:
        return 1e-3 if self.unit == "mm" else 1.0


def _conventions(data: dict[str, Any], path: Path, base: PoseConventions | None = None) -> PoseConventions:
    b = base or PoseConventions()
    unit = str(data.get("unit", b.unit)).lower()
    quat = str(data.get("quaternion", b.quaternion)).lower()
    if unit not in ("m", "mm"):
        raise FormatError(f"unit {unit!r} is not m or mm", path)
    if quat not in ("xyzw", "wxyz"):
        raise FormatError(f"quaternion order {quat!r} is not xyzw or wxyz", path)
    return PoseConventions(unit, quat)


def quat_pose(values: Sequence[float], conv: PoseConventions) -> np.ndarray:
    """4x4 from (x, y, z, q1..q4) in the declared unit and quaternion order."""
    v = np.asarray(values, np.float64)
    q = v[3:7] if conv.quaternion == "xyzw" else v[[4, 5, 6, 3]]
    n = np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q / n)
    T[:3, 3] = v[:3] * conv.scale
    return T


def read_matrix_file(path: Path) -> np.ndarray:
    """A 4x4 (or 3x4) transform from text (whitespace/commas, # comments) or .npy, as written."""
    try:
        if path.suffix == ".npy":
            M = np.asarray(np.load(path), np.float64)
        else:
            rows = [line.replace(",", " ").split() for line in path.read_text(encoding="utf-8").splitlines()
                    if line.strip() and not line.lstrip().startswith("#")]
            M = np.array([[float(v) for v in r] for r in rows], np.float64)
    except (ValueError, OSError) as err:
        raise FormatError(f"cannot read a 4x4 matrix ({err})", path) from None
    if M.shape == (3, 4):
        M = np.vstack([M, [0, 0, 0, 1]])
    if M.shape != (4, 4):
        raise FormatError(f"expected a 4x4 matrix, got shape {M.shape}", path)
    return M


def check_rigid(T: np.ndarray, path: Path, what: str = "pose") -> np.ndarray:
    """Raise unless ``T`` is a finite rigid transform (orthonormal rotation, last row 0 0 0 1)."""
    R = T[:3, :3]
    if not (np.all(np.isfinite(T)) and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6)
            and np.allclose(R @ R.T, np.eye(3), atol=2e-3) and np.linalg.det(R) > 0):
        raise FormatError(f"{what} is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)",
                          path)
    return T


def read_pose_csv(path: Path, conv: PoseConventions) -> dict[str, np.ndarray]:
    """``id, x, y, z, q1, q2, q3, q4`` rows (header optional; ``# unit: mm, quaternion: wxyz`` comment)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise FormatError(f"cannot read ({err})", path) from None
    declared: dict[str, Any] = {}
    body = []
    for line in lines:
        s = line.strip()
        if s.startswith("#"):
            for part in s.lstrip("#").replace(";", ",").split(","):
                if ":" in part or "=" in part:
                    k, v = part.replace("=", ":").split(":", 1)
                    declared[k.strip().lower()] = v.strip()
        elif s:
            body.append(s)
    conv = _conventions(declared, path, conv)
    out: dict[str, np.ndarray] = {}
    for n, row in enumerate(csv.reader(body)):
        if n == 0 and not _is_number(row[1] if len(row) > 1 else ""):
            continue  # header
        if len(row) < 8:
            raise FormatError(f"row {n + 1} has {len(row)} values; expected id, x, y, z, q1, q2, q3, q4", path)
        try:
            vals = [float(v) for v in row[1:8]]
        except ValueError:
            raise FormatError(f"row {n + 1} has a value that is not a number", path) from None
        key = _capture_key(row[0].strip())
        if key in out:
            raise FormatError(f"capture {key!r} appears twice (duplicated row)", path)
        q = np.array(vals[3:7])
        if not 0.9 < np.linalg.norm(q) < 1.1:
            raise FormatError(f"row {n + 1}: quaternion norm {np.linalg.norm(q):.3f} is not 1 (is it a rotation "
                              "vector or Euler angles?)", path)
        out[key] = quat_pose(vals, conv)
    return out


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def read_poses(folder: Path, conv: PoseConventions) -> tuple[dict[str, np.ndarray], Path]:
    """Base-from-flange poses (metres) by capture id, from ``poses.csv`` or ``poses/<id>.txt|.npy``."""
    csv_path = folder / "poses.csv"
    if csv_path.is_file():
        return read_pose_csv(csv_path, conv), csv_path
    pdir = folder / "poses"
    if not pdir.is_dir():
        raise FormatError("no poses.csv and no poses/ folder (flange poses are required)", folder)
    out = {}
    for f in sorted(pdir.iterdir()):
        if f.suffix in (".txt", ".npy") and not f.name.startswith("."):
            T = read_matrix_file(f)
            T[:3, 3] *= conv.scale
            out[_capture_key(f.stem)] = check_rigid(T, f)
    if not out:
        raise FormatError("no 4x4 pose files (.txt, .npy)", pdir)
    return out, pdir


def _capture_key(stem: str) -> str:
    """The capture id of a file: its last number (``pose_003`` and ``calib_3`` -> ``3``), else its stem."""
    runs = re.findall(r"\d+", stem)
    return (runs[-1].lstrip("0") or "0") if runs else stem


def read_board_poses(folder: Path) -> dict[str, np.ndarray]:
    """Camera-from-board poses (metres) by capture id from ``board_poses/`` (4x4 .txt/.npy or rvec/tvec .npz)."""
    out = {}
    for f in sorted(folder.iterdir()):
        if f.suffix == ".npz":
            with np.load(f) as z:
                if "rvec" not in z or "tvec" not in z:
                    raise FormatError(f"expected rvec and tvec arrays (has {', '.join(z.files)})", f)
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(np.asarray(z["rvec"], np.float64).reshape(3))[0]
                T[:3, 3] = np.asarray(z["tvec"], np.float64).reshape(3)
        elif f.suffix in (".txt", ".npy"):
            T = read_matrix_file(f)
        else:
            continue
        out[_capture_key(f.stem)] = check_rigid(T, f, "board pose")
    return out


# -- the folder ---------------------------------------------------------------------------------------

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
class CaptureFolder:
    """A generic captures folder, loaded (poses in metres, not yet checked against the images)."""

    root: Path
    board: Board
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


def _find_intrinsics(folder: Path) -> Path | None:
    for name in ("intrinsics.json", "intrinsics.npz", "intrinsics.npy", "intrinsics.txt",
                 "camera_intrinsics.npz", "camera-intrinsics.txt"):
        if (folder / name).is_file():
            return folder / name
    return None


def _load_arm(folder: Path, arm: str, conv: PoseConventions) -> ArmCaptures:
    poses, source = read_poses(folder, conv)
    images: dict[str, Path] = {}
    if (folder / "images").is_dir():
        for f in sorted((folder / "images").iterdir()):
            if f.suffix.lower() in IMAGE_SUFFIXES:
                key = _capture_key(f.stem)
                if key in images:
                    raise FormatError(f"two images for capture {key!r} ({images[key].name}, {f.name})", f.parent)
                images[key] = f
    board_poses = read_board_poses(folder / "board_poses") if (folder / "board_poses").is_dir() else {}
    if not images and not board_poses:
        raise FormatError("no images/ (board photographs) and no board_poses/ folder", folder)
    return ArmCaptures(arm, folder, poses, images, board_poses, source)


def _arm_camera(folder: Path) -> CameraModel | None:
    path = _find_intrinsics(folder)
    return load_intrinsics(path) if path is not None else None


def load_capture_folder(root: str | Path, intrinsics: str | Path | None = None,
                        eye_to_hand: bool | None = None) -> CaptureFolder:
    """Read a generic captures folder (one arm at its root, or one sub-folder per arm)."""
    root = Path(root)
    if not root.is_dir():
        raise FormatError("captures folder not found", root)
    side = load_sidecar(root)
    sidecar = root / SIDECAR
    if "board" not in side or not isinstance(side["board"], dict):
        raise FormatError("needs a 'board' mapping (type, squares_x, squares_y, square_mm, marker_mm, dictionary)",
                          sidecar)
    board = parse_board(side["board"], sidecar)
    conv = _conventions(side, sidecar)
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
    ipath = Path(intrinsics) if intrinsics is not None else _find_intrinsics(root)
    camera = load_intrinsics(ipath) if ipath is not None else None
    return CaptureFolder(root, board, conv, e2h, arms, camera)


# -- detections -> observations -----------------------------------------------------------------------

@dataclass
class GenericDetection:
    """One capture's corners (ideal pixels) and single-image board pose."""

    arm: str
    capture_id: str
    ids: np.ndarray
    corners_px: np.ndarray
    ok: bool
    reason: str = ""
    T_cam_board: np.ndarray | None = None
    pnp_rms_px: float = float("nan")
    source: str = ""


def solve_intrinsics(board: Board, found: list[tuple[np.ndarray, np.ndarray]], size: tuple[int, int]
                     ) -> tuple[CameraModel, float]:
    """OpenCV ``calibrateCamera`` on the detected corners of every image; (model, RMS px)."""
    P = board.corners_m()
    obj = [P[ids].astype(np.float32).reshape(-1, 1, 3) for ids, _ in found if len(ids) >= 8]
    img = [uv.astype(np.float32).reshape(-1, 1, 2) for ids, uv in found if len(ids) >= 8]
    if len(obj) < 4:
        raise CalibrationError(f"solving the intrinsics needs at least 4 images with 8+ corners, got {len(obj)} "
                               "(give intrinsics with --intrinsics)")
    w, h = size
    K0 = np.array([[max(w, h), 0, w / 2 - 0.5], [0, max(w, h), h / 2 - 0.5], [0, 0, 1]], np.float64)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), K0, np.zeros(5),
                                             flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    return CameraModel(K, dist.reshape(-1), "solved from the images (cv2.calibrateCamera)"), float(rms)


def detect_folder(folder: CaptureFolder, min_corners: int = 8, max_pnp_rms_px: float = 2.0
                  ) -> tuple[list[GenericDetection], dict[str, CameraModel], dict[str, Any]]:
    """Corners and board poses of every capture; intrinsics (per arm) solved from the images when not given."""
    raw: list[tuple[str, str, np.ndarray, np.ndarray, str]] = []
    size: tuple[int, int] | None = None
    for arm in folder.arms:
        for key, img_path in arm.images.items():
            grey = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE)
            if grey is None:
                raise FormatError("cannot read the image", img_path)
            if size is None:
                size = (grey.shape[1], grey.shape[0])
            elif size != (grey.shape[1], grey.shape[0]):
                raise FormatError(f"image is {grey.shape[1]} x {grey.shape[0]}, the others {size[0]} x {size[1]}",
                                  img_path)
            ids, uv = detect_corners(folder.board, grey)
            raw.append((arm.arm, key, ids, uv, str(img_path)))
    info: dict[str, Any] = {}
    cameras: dict[str, CameraModel] = {}
    for arm in folder.arms:
        camera = arm.camera or folder.camera
        if camera is None:
            mine = [(i, u) for a, _, i, u, _ in raw if a == arm.arm and len(i) >= min_corners]
            if not mine or size is None:
                raise CalibrationError("board poses without intrinsics: give intrinsics (3x3) to weight them",
                                       arm.folder)
            camera, rms = solve_intrinsics(folder.board, mine, size)
            info.setdefault("intrinsics_rms_px", {})[arm.arm] = rms
        cameras[arm.arm] = camera
    info["intrinsics_source"] = {a: c.source for a, c in cameras.items()}
    P = folder.board.corners_m()
    dets: list[GenericDetection] = []
    for arm_name, key, ids, uv, src in raw:
        camera = cameras[arm_name]
        d = GenericDetection(arm_name, key, ids, camera.undistort(uv), False, source=src)
        if len(ids) < min_corners:
            d.reason = f"too few corners ({len(ids)} < {min_corners})"
        else:
            T, rms = board_pose_pnp(P[ids], d.corners_px, camera.K)
            d.T_cam_board, d.pnp_rms_px = T, rms
            d.ok = T is not None and rms <= max_pnp_rms_px
            d.reason = "" if d.ok else f"PnP reprojection error {rms:.2f} px > {max_pnp_rms_px} px"
        dets.append(d)
    for arm in folder.arms:  # board poses given instead of images: their corners, seen through K
        camera = cameras[arm.arm]
        for key, T in arm.board_poses.items():
            if key in arm.images:
                continue
            Pc = P @ T[:3, :3].T + T[:3, 3]
            uv = (Pc[:, :2] / Pc[:, 2:3]) * np.diag(camera.K)[:2] + camera.K[:2, 2]
            dets.append(GenericDetection(arm.arm, key, np.arange(len(P)), uv, bool(np.all(Pc[:, 2] > 0)),
                                         "" if np.all(Pc[:, 2] > 0) else "board behind the camera", T, 0.0,
                                         "board_poses"))
    return dets, cameras, info


def build_generic_observations(folder: CaptureFolder, dets: list[GenericDetection],
                               cameras: dict[str, CameraModel]) -> tuple[Observations, list[str]]:
    """Observations for darp's chain: measured flange poses (inverted for eye-to-hand); warnings."""
    warnings_out: list[str] = []
    P = folder.board.corners_m()
    flange = {a.arm: a for a in folder.arms}
    good = []
    for d in dets:
        if not d.ok:
            continue
        if d.capture_id not in flange[d.arm].T_base_flange:
            warnings_out.append(f"{flange[d.arm].pose_source}: no flange pose for capture {d.capture_id!r} "
                                f"({d.source}); capture skipped")
            continue
        good.append(d)
    for a in folder.arms:
        have = {d.capture_id for d in dets if d.arm == a.arm}
        extra = sorted(set(a.T_base_flange) - have)
        if extra:
            warnings_out.append(f"{a.pose_source}: {len(extra)} pose(s) without an image or board pose "
                                f"(e.g. {extra[0]!r}); check for missing frames")
    if not good:
        raise CalibrationError("no capture has a usable board detection and a flange pose", folder.root)
    arms = tuple(dict.fromkeys(d.arm for d in good))
    F = np.array([flange[d.arm].T_base_flange[d.capture_id] for d in good])
    if folder.eye_to_hand:
        F = invert_transform(F)
    counts = np.array([len(d.ids) for d in good])
    obs = Observations(
        arms=arms, capture_ids=[f"{d.arm}/{d.capture_id}" if len(arms) > 1 else d.capture_id for d in good],
        arm_index=np.array([arms.index(d.arm) for d in good]), q_rad=np.zeros((len(good), 6)),
        T_stream_depth=np.tile(np.eye(4), (len(good), 1, 1)), K=np.array([cameras[d.arm].K for d in good]),
        corner_capture=np.repeat(np.arange(len(good)), counts), corner_id=np.concatenate([d.ids for d in good]),
        P_board=np.concatenate([P[d.ids] for d in good]), uv=np.concatenate([d.corners_px for d in good]),
        T_depth_board_pnp=np.array([d.T_cam_board for d in good]), T_base_flange=F)
    return obs, warnings_out


# -- solving and held-out checks ----------------------------------------------------------------------

REFINE = RefineSettings(estimate_offsets=False)


def darp_solver(obs: Observations, settings: RefineSettings = REFINE, metric: bool = False) -> ChainParams:
    """darp's calibration of measured-pose observations: best OpenCV start, then the joint refinement.

    ``metric``: the captures are board *poses* (no pixels were measured), so the refinement minimises
    the boards' disagreement in the reference frame (:func:`refine_metric`) instead of pixels.
    """
    est = {a: handeye.opencv_hand_eye(obs, a) for a in obs.arms}
    start = handeye.chain_from_estimates({a: handeye.best(est[a]) for a in obs.arms}, obs.arms)
    if metric:
        return refine_metric(start, obs)
    return refine(start, obs, None, settings).params


def metric_solver(obs: Observations) -> ChainParams:
    """:func:`darp_solver` for board-pose captures."""
    return darp_solver(obs, metric=True)


ROTATION_LEVER_MM = 1000.0  # board-pose refinement: mm of residual per radian of board rotation


def refine_metric(p0: ChainParams, obs: Observations, centre_board: np.ndarray | None = None,
                  lever_mm: float = ROTATION_LEVER_MM) -> ChainParams:
    """Hand-eyes, other bases and the board that best place every capture's board together (board poses).

    Per capture i (arm a) the board placed by that capture, ``T_i = T_ref_base_a F_i X_a T_cam_board_i``, is
    compared with the board ``W``: the distance of the board's centre (mm) and its rotation
    ``log(W^-1 T_i)`` (rad) times ``lever_mm``. The large default lever makes the rotation dominate (the
    hand-eye rotation is fitted first, as the two-step AX = XB methods do) and the centre fixes the
    translations; this is the held-out board consistency the report scores. Same parameterisation as
    the pixel refinement (:class:`darp.calibration.refine.Layout`, right perturbations, no joint offsets).
    """
    from scipy.optimize import least_squares

    from darp.calibration.geometry import log_delta
    from darp.calibration.refine import Layout

    if obs.T_base_flange is None:
        raise CalibrationError("board-pose refinement needs measured flange poses")
    layout = Layout(p0.arms, {a: np.zeros(6, bool) for a in p0.arms})
    c = np.append(np.unique(obs.P_board, axis=0).mean(axis=0) if centre_board is None else centre_board, 1.0)
    F, B = np.asarray(obs.T_base_flange), obs.T_depth_board_pnp

    def fun(x: np.ndarray) -> np.ndarray:
        p = layout.unpack(x, p0)
        T = np.empty_like(B)
        for a, arm in enumerate(obs.arms):
            sel = obs.arm_index == a
            T[sel] = p.T_ref_base[arm] @ F[sel] @ p.T_flange_cam[arm] @ B[sel]
        d = 1e3 * ((T @ c)[:, :3] - (p.T_ref_board @ c)[:3])
        r = lever_mm * log_delta(invert_transform(p.T_ref_board) @ T)[:, :3]
        return np.concatenate([d.ravel(), r.ravel()])

    x = np.zeros(layout.size)
    if lever_mm > 0:
        x = least_squares(fun, x, method="lm").x
        return layout.unpack(x, p0)
    lever = 100.0  # whitened: the lever is the ratio of the residuals' own spreads, re-estimated (3 rounds)
    for _ in range(3):
        lever_mm = lever
        x = least_squares(fun, x, method="lm").x
        r = fun(x)
        n = len(r) // 2
        lever = float(np.sqrt(np.mean(r[:n] ** 2)) / max(np.sqrt(np.mean((r[n:] / lever_mm) ** 2)), 1e-9))
    return layout.unpack(x, p0)


def opencv_solver(method: str) -> Callable[[Observations], ChainParams]:
    """One OpenCV method alone (e.g. ``"calibrateHandEye/TSAI"``): its hand-eye, board averaged over captures."""
    def solve(obs: Observations) -> ChainParams:
        chosen = {}
        for a in obs.arms:
            pick = [e for e in handeye.opencv_hand_eye(obs, a) if e.method == method]
            if not pick or not pick[0].ok:
                raise CalibrationError(f"{method} failed on these captures")
            chosen[a] = pick[0]
        return handeye.chain_from_estimates(chosen, obs.arms)
    return solve


def board_in_reference(params: ChainParams, obs: Observations) -> np.ndarray:
    """(M, 4, 4) the board placed in the reference frame by each capture alone."""
    out = np.empty((obs.n_captures, 4, 4))
    for a, arm in enumerate(obs.arms):
        sel = obs.arm_index == a
        if np.any(sel):
            out[sel] = (params.T_ref_base[arm] @ flange_poses(obs, sel, params.dq[arm]) @ params.T_flange_cam[arm]
                        @ obs.T_depth_board_pnp[sel])
    return out


def board_consistency(params: ChainParams, obs: Observations, centre_board: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per capture: distance (mm) of the board centre and rotation (deg) vs the calibration's board."""
    T = board_in_reference(params, obs)
    c = np.append(centre_board, 1.0)
    pred = T @ c
    ref = params.T_ref_board @ c
    d = 1e3 * np.linalg.norm(pred[:, :3] - ref[:3], axis=1)
    _, r = pose_error(T, np.broadcast_to(params.T_ref_board, T.shape))
    return d, np.degrees(np.asarray(r))


def heldout_consistency(obs: Observations, solver: Callable[[Observations], ChainParams], centre_board: np.ndarray,
                        k: int = 5, seed: int = 0) -> dict[str, Any]:
    """k-fold held-out board consistency: each withheld capture against the calibration made without it."""
    folds = fold_assignment(obs, k, seed)
    mm = np.full(obs.n_captures, np.nan)
    deg = np.full(obs.n_captures, np.nan)
    for f in range(k):
        test = folds == f
        if not np.any(test):
            continue
        params = solver(obs.subset(~test))
        d, r = board_consistency(params, obs.subset(test), centre_board)
        mm[test], deg[test] = d, r
    return {"folds": k, "mm": summarise(mm), "deg": summarise(deg),
            "per_capture": {c: {"mm": float(a), "deg": float(b)} for c, a, b in zip(obs.capture_ids, mm, deg,
                                                                                   strict=True)}}


@dataclass
class HandEyeOutcome:
    """What :func:`solve_folder` found."""

    calibration: Calibration
    params: ChainParams
    observations: Observations
    detections: list[GenericDetection]
    cameras: dict[str, CameraModel]
    heldout: dict[str, Any]
    consistency: dict[str, Any]
    comparison: dict[str, dict[str, Any]]
    warnings: list[str]


def solve_folder(root: str | Path, *, intrinsics: str | Path | None = None, eye_to_hand: bool | None = None,
                 folds: int = 5, seed: int = 0, compare: bool = True) -> HandEyeOutcome:
    """The whole any-arm calibration of a captures folder."""
    from darp.calibration.diagnose import check_pose_conventions

    folder = load_capture_folder(root, intrinsics, eye_to_hand)
    dets, cameras, info = detect_folder(folder)
    obs, warns = build_generic_observations(folder, dets, cameras)
    for arm in obs.arms:
        if int(np.sum(obs.for_arm(arm))) < 4:
            raise CalibrationError(f"{arm}: {int(np.sum(obs.for_arm(arm)))} usable captures; hand-eye needs at "
                                   "least 4", folder.root)
        check_pose_conventions(folder, obs, arm)
    pose_only = all(d.source == "board_poses" for d in dets if d.ok)
    solver = metric_solver if pose_only else darp_solver
    params = solver(obs)
    centre = folder.board.corners_m().mean(axis=0)
    k = min(folds, min(int(np.sum(obs.for_arm(a))) for a in obs.arms)) if folds > 1 else 0
    held = kfold_heldout(obs, solver, k, seed) if k > 1 else {}
    cons = heldout_consistency(obs, solver, centre, k, seed) if k > 1 else {}
    comparison: dict[str, dict[str, Any]] = {}
    if compare and k > 1:
        for m in OPENCV_METHODS:
            try:
                comparison[m] = heldout_consistency(obs, opencv_solver(m), centre, k, seed)
            except CalibrationError as err:
                comparison[m] = {"error": str(err)}
    fit = reprojection_errors(params, obs)
    fit_cons = board_consistency(params, obs, centre)
    report: dict[str, Any] = {
        "kind": "any-arm hand-eye",
        "mode": "eye_to_hand" if folder.eye_to_hand else "eye_in_hand",
        "refinement": ("board poses: board centre (mm) and rotation (x 1000 mm/rad) in the base" if pose_only
                       else "corner reprojection (px), darp's joint refinement without joint offsets"),
        "captures_folder": str(folder.root),
        "board": folder.board.describe(),
        "pose_conventions": {"unit": folder.conventions.unit, "quaternion": folder.conventions.quaternion},
        "intrinsics": {"K": {a: c.K for a, c in cameras.items()}, "dist": {a: c.dist for a, c in cameras.items()},
                       **info},
        "n_captures": {a: int(np.sum(obs.for_arm(a))) for a in obs.arms},
        "rejected": {f"{d.arm}/{d.capture_id}": d.reason for d in dets if not d.ok},
        "fit": {"reprojection_px": summarise(fit), "board_consistency_mm": summarise(fit_cons[0]),
                "board_consistency_deg": summarise(fit_cons[1])},
        "heldout": {"folds": k,
                    "corner_3d_mm": {a: summarise(v["corner_3d_mm"]) for a, v in held.get("per_arm", {}).items()},
                    "reprojection_px": {a: summarise(v["reprojection_px"]) for a, v in held.get("per_arm", {}).items()},
                    "board_consistency_mm": cons.get("mm"), "board_consistency_deg": cons.get("deg")},
        "opencv_heldout_board_consistency": {m: ({"mm": v["mm"], "deg": v["deg"]} if "mm" in v else v)
                                             for m, v in comparison.items()},
        "warnings": warns,
    }
    if folder.eye_to_hand:
        a0 = obs.arms[0]
        report["T_base_cam"] = params.T_flange_cam[a0]
        report["T_flange_board"] = params.T_ref_board
    if len(obs.arms) > 1:
        report["base_to_base"] = {f"{obs.arms[0]}->{a}": params.T_ref_base[a] for a in obs.arms[1:]}
    arms_out = {}
    for a in obs.arms:
        if folder.eye_to_hand:  # world = the fixed camera; the "wrist camera" is the board on the flange
            arms_out[a] = ArmCalibration("", invert_transform(params.T_flange_cam[a]), params.T_ref_board.copy(),
                                         n_captures=int(np.sum(obs.for_arm(a))))
        else:
            arms_out[a] = ArmCalibration("", params.T_ref_base[a].copy(), params.T_flange_cam[a].copy(),
                                         n_captures=int(np.sum(obs.for_arm(a))))
    world = ("eye-to-hand: world = the fixed camera's optical frame; T_wrist_cam holds the board on the flange "
             "(T_flange_board)" if folder.eye_to_hand else
             f"the base frame of {obs.arms[0]} (any-arm calibration, no joint offsets)")
    cal = Calibration(epoch=folder.root.name, date=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                      arms=arms_out, board=folder.board.spec(), world_frame=world, report=_jsonable(report))
    return HandEyeOutcome(cal, params, obs, dets, cameras, held, cons, comparison, warns)


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.floating | np.integer):
        return v.item()
    return v


__all__ = ["Board", "CameraModel", "CaptureFolder", "GenericDetection", "HandEyeOutcome", "OPENCV_METHODS",
           "PoseConventions", "board_consistency", "build_generic_observations", "darp_solver", "detect_corners",
           "detect_folder", "heldout_consistency", "load_capture_folder", "load_intrinsics", "metric_solver",
           "opencv_solver", "parse_board", "quat_pose", "read_matrix_file", "read_pose_csv", "read_poses",
           "refine_metric", "solve_folder", "solve_intrinsics"]
