"""Per-capture pose files: base-from-flange poses (a quaternion CSV or 4x4 matrices) and board poses.

- ``poses.csv``: ``id, x, y, z, q1, q2, q3, q4`` rows, header optional, the translation unit and quaternion
  order declared (:class:`PoseConventions`; also in a ``# unit: mm, quaternion: wxyz`` comment);
- a folder of 4x4 (or 3x4) matrices, one ``.txt`` (whitespace or commas, ``#`` comments) or ``.npy`` per capture;
- ``board_poses/``: camera-from-board per capture, 4x4 ``.txt``/``.npy`` or ``.npz`` with OpenCV's ``rvec``/``tvec``.

Each file is keyed by its capture id (:func:`capture_key`: :mod:`darp.formats.pairing`'s rule). More table
forms (``.npz``, ``.json``, 4x4 rows) are read by :mod:`darp.formats.pose_tables`. Every matrix must be a
rigid transform by :mod:`darp.geometry.rigid`'s rule; rotations a little off orthonormal (up to
``NEAR_RIGID_LIMIT``) are replaced by the nearest rotation with one warning per file or folder.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.io_input import load_numpy
from darp.formats.text import read_utf8_text
from darp.geometry.rigid import orthonormalised, warn_orthonormalised
from darp.geometry.transforms import quaternion_to_rotation

ROTATION_FORMS = "rotvec (x y z rx ry rz, UR style), euler-<axes>-<deg|rad> (e.g. euler-xyz-deg: SciPy's axes, " \
    "lower case extrinsic, upper case intrinsic)"


@dataclass(frozen=True)
class PoseConventions:
    """How pose files are written: the translation unit, the quaternion order, and what six values per pose
    mean (``rotation``: ``rotvec`` or ``euler-<axes>-<deg|rad>``; empty: six values are refused)."""

    unit: str = "m"  # "m" | "mm"
    quaternion: str = "xyzw"  # "xyzw" | "wxyz"
    rotation: str = ""  # x y z + 3 rotation values: "rotvec" | "euler-xyz-deg" | "euler-ZYX-rad" ...

    @property
    def scale(self) -> float:
        return 1e-3 if self.unit == "mm" else 1.0


def six_value_pose(values: Any, conv: PoseConventions, path: Path) -> np.ndarray:
    """4x4 from ``x y z`` + three rotation values in the declared ``rotation`` form (translation as written)."""
    from scipy.spatial.transform import Rotation

    v = np.asarray(values, np.float64)
    T = np.eye(4)
    T[:3, 3] = v[:3]
    if conv.rotation == "rotvec":
        T[:3, :3] = Rotation.from_rotvec(v[3:6]).as_matrix()
        return T
    parts = conv.rotation.split("-")
    if len(parts) != 3 or parts[0] != "euler" or parts[2] not in ("deg", "rad"):
        raise FormatError(f"6 values per pose: x y z and a rotation vector or Euler angles are ambiguous; declare "
                          f"rotation: {ROTATION_FORMS} (or write x y z qx qy qz qw, or the 4x4)", path)
    try:
        T[:3, :3] = Rotation.from_euler(parts[1], v[3:6], degrees=parts[2] == "deg").as_matrix()
    except ValueError as err:
        raise FormatError(f"rotation {conv.rotation!r}: {err}", path) from None
    return T


def pose_conventions(data: dict[str, Any], path: Path, base: PoseConventions | None = None) -> PoseConventions:
    """The ``unit`` and ``quaternion`` of a mapping (a sidecar, a CSV's comment), defaulting to ``base``'s."""
    b = base or PoseConventions()
    unit = str(data.get("unit", b.unit)).lower()
    quat = str(data.get("quaternion", b.quaternion)).lower()
    rotation = str(data.get("rotation", b.rotation))
    if unit not in ("m", "mm"):
        raise FormatError(f"unit {unit!r} is not m or mm", path)
    if quat not in ("xyzw", "wxyz"):
        raise FormatError(f"quaternion order {quat!r} is not xyzw or wxyz", path)
    return PoseConventions(unit, quat, rotation)


def capture_key(stem: str) -> str:
    """The capture id of a file or CSV id: :func:`darp.formats.pairing.frame_id` (the stem without role words;
    ``pose_003``, ``calib_3`` and ``003`` -> ``3``; ``img_14-05-41`` -> ``14-05-41``)."""
    from darp.formats.pairing import frame_id

    return frame_id(stem)


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
            M = np.asarray(load_numpy(path, "a .npy matrix"), np.float64)
        else:
            text = read_utf8_text(path, "a text file")
            rows = [line.replace(",", " ").split() for line in text.splitlines()
                    if line.strip() and not line.lstrip().startswith("#")]
            M = np.array([[float(v) for v in r] for r in rows], np.float64)
    except (ValueError, OSError) as err:
        raise FormatError(f"cannot read a 4x4 matrix ({err})", path) from None
    if M.shape == (3, 4):
        M = np.vstack([M, [0, 0, 0, 1]])
    if M.shape != (4, 4):
        raise FormatError(f"expected a 4x4 matrix, got shape {M.shape}", path)
    return M


def read_pose_csv(path: Path, conv: PoseConventions) -> dict[str, np.ndarray]:
    """``id, x, y, z, q1, q2, q3, q4`` rows (header optional; ``# unit: mm, quaternion: wxyz`` comment)."""
    try:
        lines = read_utf8_text(path, "a text file").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise FormatError(f"cannot read ({err})", path) from None
    body = [s for s in (line.strip() for line in lines) if s and not s.startswith("#")]
    conv = pose_conventions(comment_declarations(lines), path, conv)
    out: dict[str, np.ndarray] = {}
    for n, row in enumerate(csv.reader(body)):
        if n == 0 and not is_number(row[1] if len(row) > 1 else ""):
            continue  # header
        if len(row) < 8:
            raise FormatError(f"row {n + 1} has {len(row)} values; expected id, x, y, z, q1, q2, q3, q4", path)
        try:
            vals = [float(v) for v in row[1:8]]
        except ValueError:
            raise FormatError(f"row {n + 1} has a value that is not a number", path) from None
        key = capture_key(row[0].strip())
        if key in out:
            raise FormatError(f"capture {key!r} appears twice (duplicated row)", path)
        q = np.array(vals[3:7])
        if not 0.9 < np.linalg.norm(q) < 1.1:
            raise FormatError(f"row {n + 1}: quaternion norm {np.linalg.norm(q):.3f} is not 1 (is it a rotation "
                              "vector or Euler angles?)", path)
        out[key] = quat_pose(vals, conv)
    return out


def is_number(s: str) -> bool:
    """Whether ``s`` parses as a float (a header row's cells do not)."""
    try:
        float(s)
    except ValueError:
        return False
    return True


def comment_declarations(lines: list[str]) -> dict[str, str]:
    """``key: value`` (or ``key=value``) pairs declared in a table's comment lines, e.g.
    ``# unit: mm, quaternion: wxyz``; keys lower-cased."""
    out: dict[str, str] = {}
    for line in lines:
        s = line.strip()
        if s.startswith("#"):
            for part in s.lstrip("#").replace(";", ",").split(","):
                if ":" in part or "=" in part:
                    k, v = part.replace("=", ":").split(":", 1)
                    out[k.strip().lower()] = v.strip()
    return out


def _stem_key(f: Path) -> str:
    return capture_key(f.stem)


def read_pose_folder(folder: Path, conv: PoseConventions, key: Callable[[Path], str] = _stem_key
                     ) -> dict[str, np.ndarray]:
    """4x4 poses (translations in ``conv``'s unit, returned in metres) from a folder's ``.txt``/``.npy`` files
    by ``key(file)`` (default: the capture id of its stem); hidden files are skipped."""
    out: dict[str, np.ndarray] = {}
    fixed: list[float] = []
    for f in sorted(folder.iterdir()):
        if f.suffix in (".txt", ".npy") and not f.name.startswith("."):
            T = read_matrix_file(f)
            T[:3, 3] *= conv.scale
            out[key(f)], err = orthonormalised(T, "pose", f, error=FormatError)
            fixed.append(err)
    if not out:
        raise FormatError("no 4x4 pose files (.txt, .npy)", folder)
    warn_orthonormalised(fixed, folder)
    return out


def read_poses(folder: Path, conv: PoseConventions) -> tuple[dict[str, np.ndarray], Path]:
    """Base-from-flange poses (metres) by capture id, from ``poses.csv`` or ``poses/<id>.txt|.npy``."""
    csv_path = folder / "poses.csv"
    if csv_path.is_file():
        return read_pose_csv(csv_path, conv), csv_path
    pdir = folder / "poses"
    if not pdir.is_dir():
        raise FormatError("no poses.csv and no poses/ folder (flange poses are required)", folder)
    return read_pose_folder(pdir, conv), pdir


def read_board_poses(folder: Path) -> dict[str, np.ndarray]:
    """Camera-from-board poses (metres) by capture id from ``board_poses/`` (4x4 .txt/.npy or rvec/tvec .npz)."""
    import cv2  # OpenCV's own rvec -> matrix, exactly as the rvec was meant

    out = {}
    fixed: list[float] = []
    for f in sorted(folder.iterdir()):
        if f.suffix == ".npz":
            z = load_numpy(f, "an .npz file")
            if "rvec" not in z or "tvec" not in z:
                raise FormatError(f"expected rvec and tvec arrays (has {', '.join(z)})", f)
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(np.asarray(z["rvec"], np.float64).reshape(3))[0]
            T[:3, 3] = np.asarray(z["tvec"], np.float64).reshape(3)
        elif f.suffix in (".txt", ".npy"):
            T = read_matrix_file(f)
        else:
            continue
        out[capture_key(f.stem)], err = orthonormalised(T, "board pose", f, error=FormatError)
        fixed.append(err)
    warn_orthonormalised(fixed, folder, "board pose")
    return out


__all__ = ["ROTATION_FORMS", "PoseConventions", "capture_key", "comment_declarations", "is_number",
           "pose_conventions", "quat_pose", "read_board_poses", "read_matrix_file", "read_pose_csv",
           "read_pose_folder", "read_poses", "six_value_pose"]
