"""Camera trajectories in the common conventions, read as world-from-camera (OpenCV camera axes, metres).

- ``tum``: ``timestamp tx ty tz qx qy qz qw`` per line (TUM RGB-D), ``#`` comments;
- ``log``: Open3D/Redwood ``trajectory.log``: a line ``id id frame`` then four rows of the 4x4;
- ``pose-txt``: one 4x4 per frame file (3DMatch / 7-Scenes ``frame-000000.pose.txt``), a folder of them;
- ``nerfstudio``: ``transforms.json`` ``frames[].transform_matrix`` (camera-to-world in OpenGL axes:
  x right, y up, z back; turned to OpenCV's x right, y down, z forward), keyed by ``file_path``.

Every reader returns ``{key: T_world_cam}`` with the key a frame's number (the last number in its
name or, for TUM, the line's timestamp as written) so that frames and poses can be matched.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from darp.errors import FormatError

FORMATS = ("tum", "log", "pose-txt", "nerfstudio")
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def frame_key(name: str) -> str:
    """The frame key of a file name: its last number without leading zeros (else the stem)."""
    stem = Path(name).name.split(".")[0]
    runs = re.findall(r"\d+", stem)
    return (runs[-1].lstrip("0") or "0") if runs else stem


def _rows(path: Path) -> list[list[float]]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise FormatError(f"cannot read ({err})", path) from None
    out = []
    for n, line in enumerate(text.splitlines()):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            out.append([float(v) for v in s.replace(",", " ").split()])
        except ValueError:
            raise FormatError(f"line {n + 1} has a value that is not a number", path) from None
    return out


def _rigid(T: np.ndarray, path: Path, where: str) -> np.ndarray:
    R = T[:3, :3]
    if not (np.all(np.isfinite(T)) and np.allclose(R @ R.T, np.eye(3), atol=2e-3) and np.linalg.det(R) > 0):
        raise FormatError(f"{where}: not a rigid transform (rotation not orthonormal)", path)
    return T


def read_tum(path: str | Path) -> dict[str, np.ndarray]:
    """TUM ``timestamp tx ty tz qx qy qz qw``; key = the timestamp as written."""
    p = Path(path)
    out: dict[str, np.ndarray] = {}
    raw = [line.split() for line in p.read_text(encoding="utf-8").splitlines()
           if line.strip() and not line.lstrip().startswith("#")]
    for n, r in enumerate(raw):
        if len(r) != 8:
            raise FormatError(f"line {n + 1} has {len(r)} values; TUM is timestamp tx ty tz qx qy qz qw", p)
        v = np.array([float(x) for x in r[1:]])
        if r[0] in out:
            raise FormatError(f"timestamp {r[0]} appears twice (duplicated frame)", p)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(v[3:7] / np.linalg.norm(v[3:7])).as_matrix()  # x y z w
        T[:3, 3] = v[:3]
        out[r[0]] = T
    return out


def read_log(path: str | Path) -> dict[str, np.ndarray]:
    """Open3D/Redwood ``trajectory.log``; key = the frame number of each block's header line."""
    p = Path(path)
    rows = _rows(p)
    if len(rows) % 5:
        raise FormatError(f"{len(rows)} lines is not a multiple of 5 (a header and 4 matrix rows per frame)", p)
    out = {}
    for k in range(0, len(rows), 5):
        head = rows[k]
        key = str(int(head[0]))
        if key in out:
            raise FormatError(f"frame {key} appears twice (duplicated frame)", p)
        out[key] = _rigid(np.array(rows[k + 1:k + 5]), p, f"frame {key}")
    return out


def read_pose_txt(folder: str | Path, pattern: str = "*.pose.txt") -> dict[str, np.ndarray]:
    """A folder of per-frame 4x4 text files (3DMatch / 7-Scenes); key = the frame number in the name."""
    root = Path(folder)
    files = sorted(root.glob(pattern)) or sorted(root.glob("*.txt"))
    out = {}
    for f in files:
        M = np.array(_rows(f))
        if M.shape != (4, 4):
            raise FormatError(f"expected a 4x4 matrix, got shape {M.shape}", f)
        out[frame_key(f.name)] = _rigid(M, f, "pose")
    if not out:
        raise FormatError(f"no pose files ({pattern})", root)
    return out


def read_nerfstudio(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """nerfstudio ``transforms.json``: poses (OpenCV axes) by frame key, and its intrinsics (fl_x, ...)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read ({err})", p) from None
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise FormatError("no 'frames' list", p)
    out: dict[str, np.ndarray] = {}
    for fr in frames:
        M = np.asarray(fr.get("transform_matrix"), float)
        if M.shape != (4, 4):
            raise FormatError(f"frame {fr.get('file_path')}: transform_matrix is not 4x4", p)
        out[frame_key(str(fr.get("file_path", len(out))))] = _rigid(M @ OPENGL_TO_OPENCV, p, str(fr.get("file_path")))
    intr = {k: float(data[k]) for k in ("fl_x", "fl_y", "cx", "cy", "w", "h") if k in data}
    return out, intr


def read_trajectory(path: str | Path, kind: str) -> dict[str, np.ndarray]:
    """World-from-camera poses by frame key from a trajectory of ``kind`` (one of :data:`FORMATS`)."""
    if kind == "tum":
        return read_tum(path)
    if kind == "log":
        return read_log(path)
    if kind == "pose-txt":
        return read_pose_txt(path)
    if kind == "nerfstudio":
        return read_nerfstudio(path)[0]
    raise FormatError(f"unknown trajectory format {kind!r} (known: {', '.join(FORMATS)})", path)


def write_tum(path: str | Path, poses: dict[str, np.ndarray]) -> None:
    """Write poses as TUM lines (key as the timestamp); for round trips and exports."""
    from darp.formats.atomic import write_text_atomic

    lines = []
    for k, T in poses.items():
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x y z w
        lines.append(" ".join([k, *(f"{v:.9f}" for v in (*T[:3, 3], *q))]))
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_log(path: str | Path, poses: dict[str, np.ndarray]) -> None:
    """Write poses as an Open3D ``trajectory.log``."""
    from darp.formats.atomic import write_text_atomic

    n = len(poses)
    blocks = []
    for k, T in poses.items():
        blocks.append(f"{k} {k} {n}")
        blocks += [" ".join(f"{v:.9f}" for v in row) for row in T]
    write_text_atomic(path, "\n".join(blocks) + "\n")


__all__ = ["FORMATS", "frame_key", "read_log", "read_nerfstudio", "read_pose_txt", "read_trajectory", "read_tum",
           "write_log", "write_tum"]
