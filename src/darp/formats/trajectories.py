"""Camera trajectories in the common conventions, read as world-from-camera (OpenCV camera axes, metres).

- ``tum``: ``timestamp tx ty tz qx qy qz qw`` per line (TUM RGB-D), ``#`` comments;
- ``log``: Open3D/Redwood ``trajectory.log``: a line ``id id frame`` then four rows of the 4x4;
- ``pose-txt``: one 4x4 per frame file (3DMatch / 7-Scenes ``frame-000000.pose.txt``), a folder of them;
- ``nerfstudio``: ``transforms.json`` ``frames[].transform_matrix`` (camera-to-world in OpenGL axes:
  x right, y up, z back; turned to OpenCV's x right, y down, z forward), keyed by ``file_path``.

Every reader returns ``{key: T_world_cam}`` with the key a frame's number (the last number in its
name or, for TUM, the line's timestamp as written) so that frames and poses can be matched. Every pose must be
rigid by :mod:`darp.geometry.rigid`'s rule; rotations a little off orthonormal are replaced by the nearest
rotation, with one warning per file. TUM is read and written here for every darp writer
(:func:`read_tum_trajectory`, :func:`write_tum`).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from darp.errors import FormatError
from darp.formats.intrinsics import check_camera_matrix, read_open3d_intrinsic
from darp.formats.io_input import LIMITS
from darp.formats.text import read_utf8_text
from darp.geometry.rigid import orthonormalised, warn_orthonormalised
from darp.geometry.transforms import rotation_to_quaternion

FORMATS = ("tum", "log", "pose-txt", "nerfstudio")
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def frame_key(name: str) -> str:
    """The frame key of a file name: its last number without leading zeros (else the stem)."""
    stem = Path(name).name.split(".")[0]
    runs = re.findall(r"\d+", stem)
    return (runs[-1].lstrip("0") or "0") if runs else stem


def _rows(path: Path) -> list[list[float]]:
    try:
        text = read_utf8_text(path, "a text file")
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


class _Rigid:
    """One file's poses through :func:`darp.geometry.rigid.orthonormalised`, warned about once."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.errors: list[float] = []

    def __call__(self, T: np.ndarray, where: str) -> np.ndarray:
        out, err = orthonormalised(T, where, self.path, error=FormatError)
        self.errors.append(err)
        return out

    def warn(self) -> None:
        warn_orthonormalised(self.errors, self.path)


TUM_HEADER = "timestamp tx ty tz qx qy qz qw"


def read_tum_trajectory(path: str | Path) -> tuple[list[str], np.ndarray]:
    """A TUM trajectory ``timestamp tx ty tz qx qy qz qw`` per line (``#`` comments): the timestamps as written
    and ``T (N, 4, 4)`` in file order (quaternions normalised)."""
    p = Path(path)
    try:
        text = read_utf8_text(p, "a text file")
    except (OSError, UnicodeDecodeError) as err:
        raise FormatError(f"cannot read ({err})", p) from None
    stamps: list[str] = []
    poses: list[np.ndarray] = []
    for number, line in enumerate(text.splitlines(), start=1):
        r = line.split()
        if not r or r[0].startswith("#"):
            continue
        if len(r) != 8:
            raise FormatError(f"line {number}: expected 8 values ({TUM_HEADER}), got {len(r)}", p)
        try:
            v = np.array([float(x) for x in r[1:]])
            float(r[0])
        except ValueError:
            raise FormatError(f"line {number}: not numbers", p) from None
        norm = np.linalg.norm(v[3:7])
        if not (np.all(np.isfinite(v)) and norm > 0):
            raise FormatError(f"line {number}: not a pose (non-finite values or a zero quaternion)", p)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(v[3:7] / norm).as_matrix()  # x y z w
        T[:3, 3] = v[:3]
        stamps.append(r[0])
        poses.append(T)
    return stamps, np.array(poses).reshape(-1, 4, 4)


def read_tum(path: str | Path) -> dict[str, np.ndarray]:
    """TUM ``timestamp tx ty tz qx qy qz qw``; key = the timestamp as written."""
    stamps, T = read_tum_trajectory(path)
    out: dict[str, np.ndarray] = {}
    for stamp, pose in zip(stamps, T, strict=True):
        if stamp in out:
            raise FormatError(f"timestamp {stamp} appears twice (duplicated frame)", path)
        out[stamp] = pose
    return out


def exact(value: float) -> str:
    """A float with 17 significant digits (reads back exactly)."""
    return repr(float(value))


def tum_text(stamps: Sequence[str], T_world_cam: np.ndarray, comments: Sequence[str] = (),
             number: Callable[[float], str] = exact) -> str:
    """TUM text: the ``comments`` lines (``#`` included), then one ``timestamp tx ty tz qx qy qz qw`` line per
    pose, the quaternion with ``w >= 0`` and each number written by ``number`` (default: exactly)."""
    T = np.asarray(T_world_cam, np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(T):
        raise FormatError(f"{len(stamps)} timestamps for {len(T)} poses")
    lines = list(comments)
    if len(T):
        quats = rotation_to_quaternion(T[:, :3, :3])
        for stamp, pose, q in zip(stamps, T, quats, strict=True):
            lines.append(" ".join([stamp, *(number(v) for v in (*pose[:3, 3], *q))]))
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, stamps: Sequence[str], T_world_cam: np.ndarray, comments: Sequence[str] = (),
              number: Callable[[float], str] = exact) -> None:
    """Write :func:`tum_text` atomically."""
    from darp.formats.atomic import write_text_atomic

    write_text_atomic(path, tum_text(stamps, T_world_cam, comments, number))


def read_log(path: str | Path) -> dict[str, np.ndarray]:
    """Open3D/Redwood ``trajectory.log``; key = the frame number of each block's header line."""
    p = Path(path)
    rows = _rows(p)
    if len(rows) % 5:
        raise FormatError(f"{len(rows)} lines is not a multiple of 5 (a header and 4 matrix rows per frame)", p)
    out = {}
    rigid = _Rigid(p)
    for k in range(0, len(rows), 5):
        head = rows[k]
        key = str(int(head[0]))
        if key in out:
            raise FormatError(f"frame {key} appears twice (duplicated frame)", p)
        out[key] = rigid(np.array(rows[k + 1:k + 5]), f"frame {key}")
    rigid.warn()
    return out


def read_pose_txt(folder: str | Path, pattern: str = "*.pose.txt") -> dict[str, np.ndarray]:
    """A folder of per-frame 4x4 text files (3DMatch / 7-Scenes); key = the frame number in the name."""
    root = Path(folder)
    files = sorted(root.glob(pattern)) or sorted(root.glob("*.txt"))
    out = {}
    errors = []
    for f in files:
        M = np.array(_rows(f))
        if M.shape != (4, 4):
            raise FormatError(f"expected a 4x4 matrix, got shape {M.shape}", f)
        out[frame_key(f.name)], err = orthonormalised(M, "pose", f, error=FormatError)
        errors.append(err)
    if not out:
        raise FormatError(f"no pose files ({pattern})", root)
    warn_orthonormalised(errors, root)
    return out


def read_nerfstudio(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """nerfstudio ``transforms.json``: poses (OpenCV axes) by frame key, and its top-level intrinsics (fl_x, ...)
    as written (cx/cy with nerfstudio's +0.5 pixel centres; :func:`read_nerfstudio_folder` converts them)."""
    p = Path(path)
    try:
        data = json.loads(read_utf8_text(p, "a JSON file", limit=LIMITS["json"]))
    except (OSError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read ({err})", p) from None
    frames = data.get("frames")
    if not isinstance(frames, list):
        raise FormatError("no 'frames' list", p)
    out: dict[str, np.ndarray] = {}
    rigid = _Rigid(p)
    for fr in frames:
        M = np.asarray(fr.get("transform_matrix"), float)
        if M.shape != (4, 4):
            raise FormatError(f"frame {fr.get('file_path')}: transform_matrix is not 4x4", p)
        out[frame_key(str(fr.get("file_path", len(out))))] = rigid(M @ OPENGL_TO_OPENCV, str(fr.get("file_path")))
    rigid.warn()
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


def write_log(path: str | Path, poses: dict[str, np.ndarray]) -> None:
    """Write poses as an Open3D ``trajectory.log``."""
    from darp.formats.atomic import write_text_atomic

    n = len(poses)
    blocks = []
    for k, T in poses.items():
        blocks.append(f"{k} {k} {n}")
        blocks += [" ".join(f"{v:.9f}" for v in row) for row in T]
    write_text_atomic(path, "\n".join(blocks) + "\n")


# --- posed RGB-D folders: frames paired with their poses (and intrinsics) in each format's own way ---------------

TUM_DEPTH_SCALE_M = 1.0 / 5000.0  # TUM RGB-D: 16-bit PNG, 5000 per metre
TUM_MAX_DT_S = 0.02  # the TUM tools' default max_difference when associating by timestamp


@dataclass
class PosedFrames:
    """A posed RGB-D folder read in its format's own pairing: image files, poses and (where the folder gives
    them) intrinsics by frame key (the frame's position, ``"0"``, ``"1"``, ..., or its number in the name).

    ``intrinsics`` maps a key to ``(K, dist)`` with OpenCV's pixel centres at integer coordinates (a
    format with centres at +0.5, like nerfstudio's, is converted on reading); ``depth_scale_m`` is
    metres per depth unit where the format fixes or declares it; ``stamps`` seconds where it has them.
    """

    kind: str
    colour: dict[str, Path] = field(default_factory=dict)
    depth: dict[str, Path] = field(default_factory=dict)
    poses: dict[str, np.ndarray] = field(default_factory=dict)
    intrinsics: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    depth_scale_m: float | None = None
    stamps: dict[str, float] = field(default_factory=dict)
    source: str = ""


def _stamped_list(path: Path) -> list[tuple[float, str]]:
    """A TUM ``rgb.txt``/``depth.txt``: ``timestamp filename`` lines."""
    out = []
    for n, line in enumerate(read_utf8_text(path, "a text file").splitlines()):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        try:
            out.append((float(parts[0]), parts[1]))
        except (ValueError, IndexError):
            raise FormatError(f"line {n + 1} is not 'timestamp filename'", path) from None
    if not out:
        raise FormatError("no 'timestamp filename' lines", path)
    return out


def associate(a: np.ndarray, b: np.ndarray, max_dt_s: float) -> dict[int, int]:
    """One-to-one timestamp association as the TUM tools' ``associate.py`` makes it: every pair closer than
    ``max_dt_s``, closest first, each stamp used once; ``{index in a: index in b}``."""
    order = np.argsort(b, kind="stable")
    sb = b[order]
    pairs = []
    for i, t in enumerate(a):
        lo, hi = np.searchsorted(sb, t - max_dt_s, "left"), np.searchsorted(sb, t + max_dt_s, "right")
        pairs += [(abs(float(sb[j]) - float(t)), i, int(order[j])) for j in range(lo, hi)]
    out: dict[int, int] = {}
    used: set[int] = set()
    for dt, i, j in sorted(pairs):
        if dt <= max_dt_s and i not in out and j not in used:
            out[i] = j
            used.add(j)
    return out


def read_tum_folder(folder: str | Path, groundtruth: str | Path | None = None,
                    max_dt_s: float = TUM_MAX_DT_S) -> PosedFrames:
    """A TUM RGB-D sequence folder: ``depth.txt`` frames, each with an ``rgb.txt`` image and a pose from
    ``groundtruth`` (default: the folder's ``groundtruth.txt``) within ``max_dt_s`` seconds, associated
    one-to-one, closest first, as the TUM tools' ``associate.py`` pairs them (:func:`associate`). Keys are the
    depth frames' positions in ``depth.txt``. Intrinsics from a ``calibration.txt`` (``fx fy cx cy [k1 k2 p1
    p2 k3]``) when the folder has one; depth 5000 per metre."""
    root = Path(folder)
    depth_list = root / "depth.txt"
    if not depth_list.is_file():
        raise FormatError("not a TUM RGB-D folder: no depth.txt", root)
    gt = Path(groundtruth) if groundtruth is not None else root / "groundtruth.txt"
    if gt.is_dir():
        raise FormatError("a TUM trajectory is a file (groundtruth.txt), not a folder", gt)
    if not gt.is_file():
        raise FormatError("no groundtruth.txt: give the trajectory with --trajectory", root)
    depths = _stamped_list(depth_list)
    rgbs = sorted(_stamped_list(root / "rgb.txt")) if (root / "rgb.txt").is_file() else []
    truth = read_tum(gt)
    gt_keys = sorted(truth, key=float)
    gt_t = np.array([float(k) for k in gt_keys])
    depth_t = np.array([t for t, _ in depths])
    out = PosedFrames("tum", depth_scale_m=TUM_DEPTH_SCALE_M, source=str(gt))
    to_rgb = associate(depth_t, np.array([t for t, _ in rgbs]), max_dt_s)
    to_gt = associate(depth_t, gt_t, max_dt_s)
    for n, (t, name) in enumerate(depths):
        key = str(n)
        out.depth[key] = root / name
        out.stamps[key] = t
        if n in to_rgb:
            out.colour[key] = root / rgbs[to_rgb[n]][1]
        if n in to_gt:
            out.poses[key] = truth[gt_keys[to_gt[n]]]
    if not out.poses:
        raise FormatError(f"no depth frame has a ground-truth pose within {max_dt_s:g} s (depth {depths[0][0]:.3f}"
                          f"..{depths[-1][0]:.3f} s, poses {gt_t[0]:.3f}..{gt_t[-1]:.3f} s): another sequence's "
                          "trajectory, or a clock offset?", gt)
    calib = root / "calibration.txt"
    if calib.is_file():
        rows = [r for r in _rows(calib) if len(r) >= 4]
        if not rows:
            raise FormatError("no 'fx fy cx cy [k1 k2 p1 p2 k3]' line", calib)
        fx, fy, cx, cy, *dist = rows[0]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        d = np.array((list(dist) + [0.0] * 5)[:5])
        out.intrinsics = dict.fromkeys(out.depth, (K, d))
    return out


NERFSTUDIO_PIXEL_CENTRE = 0.5  # nerfstudio (like COLMAP) puts pixel centres at +0.5; darp/OpenCV at integers


def read_nerfstudio_folder(path: str | Path) -> PosedFrames:
    """A nerfstudio dataset: ``transforms.json`` (or its folder). Frames pair by ``file_path`` and
    ``depth_file_path`` (relative to the JSON's folder); keys are the frames' positions in ``frames``.
    Intrinsics per frame or at the top level (``fl_x fl_y cx cy k1 k2 p1 p2 [k3]``), with ``cx``/``cy`` moved
    from nerfstudio's +0.5 pixel centres to OpenCV's integer ones (``ppx = cx - 0.5``); the depth unit from
    ``depth_unit_scale_factor`` (nerfstudio's default 0.001 when absent)."""
    p = Path(path)
    if p.is_dir():
        p = p / "transforms.json"
    try:
        data = json.loads(read_utf8_text(p, "a JSON file", limit=LIMITS["json"]))
    except (OSError, json.JSONDecodeError) as err:
        raise FormatError(f"cannot read ({err})", p) from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise FormatError("no 'frames' list", p)
    root = p.parent
    rigid = _Rigid(p)
    out = PosedFrames("nerfstudio", depth_scale_m=float(data.get("depth_unit_scale_factor", 1e-3)), source=str(p))
    seen: dict[str, int] = {}
    for n, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise FormatError(f"frame {n}: not a JSON object", p)
        key, where = str(n), f"frame {n} ({fr.get('file_path')})"
        first = seen.setdefault(str(fr.get("depth_file_path")), n)
        if first != n:  # one image listed twice: a broken file (and 100,000 copies would be imported 100,000 times)
            raise FormatError(f"{where}: depth_file_path repeats frame {first} (duplicate frames)", p)
        M = np.asarray(fr.get("transform_matrix"), float)
        if M.shape != (4, 4):
            raise FormatError(f"{where}: transform_matrix is not 4x4", p)
        out.poses[key] = rigid(M @ OPENGL_TO_OPENCV, where)
        if fr.get("file_path"):
            out.colour[key] = root / str(fr["file_path"])
        if not fr.get("depth_file_path"):
            raise FormatError(f"{where}: no depth_file_path (darp imports RGB-D frames)", p)
        out.depth[key] = root / str(fr["depth_file_path"])
        get = {k: fr.get(k, data.get(k)) for k in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "k3")}
        if get["fl_x"] is not None and get["cx"] is not None and get["cy"] is not None:
            fx = float(get["fl_x"])
            fy = float(get["fl_y"] if get["fl_y"] is not None else fx)
            K = np.array([[fx, 0.0, float(get["cx"]) - NERFSTUDIO_PIXEL_CENTRE],
                          [0.0, fy, float(get["cy"]) - NERFSTUDIO_PIXEL_CENTRE], [0.0, 0.0, 1.0]])
            dist = np.array([float(get[k] or 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
            out.intrinsics[key] = (check_camera_matrix(K, p, where), dist)
    if out.intrinsics and len(out.intrinsics) != len(out.poses):
        raise FormatError(f"{len(out.poses) - len(out.intrinsics)} frame(s) have no fl_x/cx/cy (per frame or at the "
                          "top level)", p)
    rigid.warn()
    return out


def read_open3d_folder(folder: str | Path, log: str | Path | None = None) -> PosedFrames:
    """An Open3D/Redwood folder: ``color/`` and ``depth/`` images keyed by the number in their names, paired
    with ``trajectory.log`` blocks by their frame id (the first number of each header line); intrinsics from
    ``camera_intrinsic.json`` when present; depth 1000 per metre (Open3D's default ``depth_scale``)."""
    root = Path(folder)
    traj = Path(log) if log is not None else root / "trajectory.log"
    out = PosedFrames("log", poses=read_log(traj), depth_scale_m=None, source=str(traj))
    images = [".png", ".jpg", ".jpeg"]
    for sub, target in (("color", out.colour), ("image", out.colour), ("rgb", out.colour), ("depth", out.depth)):
        if (root / sub).is_dir():
            for f in sorted((root / sub).iterdir()):
                if f.suffix.lower() in images:
                    k = frame_key(f.name)
                    if k in target:
                        raise FormatError(f"two images for frame {k} ({target[k].name}, {f.name})", root / sub)
                    target[k] = f
    if not out.depth:
        raise FormatError("no depth/ folder of images", root)
    js = root / "camera_intrinsic.json"
    if js.is_file():
        K, _, _ = read_open3d_intrinsic(js)
        out.intrinsics = dict.fromkeys(out.depth, (K, np.zeros(5)))
    return out


def detect_posed_folder(folder: str | Path) -> str | None:
    """The posed-folder format of ``folder`` (``nerfstudio``, ``tum``, ``log``), or None."""
    root = Path(folder)
    if (root / "transforms.json").is_file():
        return "nerfstudio"
    if (root / "depth.txt").is_file() and (root / "groundtruth.txt").is_file():
        return "tum"
    if (root / "trajectory.log").is_file():
        return "log"
    return None


__all__ = ["FORMATS", "NERFSTUDIO_PIXEL_CENTRE", "TUM_DEPTH_SCALE_M", "TUM_HEADER", "TUM_MAX_DT_S", "PosedFrames",
           "associate", "detect_posed_folder", "exact", "frame_key", "read_log", "read_nerfstudio",
           "read_nerfstudio_folder", "read_open3d_folder", "read_pose_txt", "read_trajectory", "read_tum",
           "read_tum_folder", "read_tum_trajectory", "tum_text", "write_log", "write_tum"]
