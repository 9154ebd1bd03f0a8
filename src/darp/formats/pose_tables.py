"""Pose tables in the forms people save them: one file of many poses, or a folder of one pose per file.

:func:`read_pose_table` reads (translations in the declared unit, returned in metres):

- ``.csv`` / ``.txt`` rows: ``id, x, y, z, q1, q2, q3, q4`` (the quaternion order declared, or read from a
  header naming ``qw`` first / last); ``id, x, y, z, r1, r2, r3`` with the rotation form declared
  (``rotation: rotvec`` as UR controllers write, or ``euler-xyz-deg`` ...); ``id`` + 16 (or 12) values of a
  row-major 4x4 (3x4); or the same without an id column (then the rows pair by order); a header is optional,
  ``--id-column NAME`` picks the id column by its header name; whitespace or commas; ``#`` comments
  (``# unit: mm, quaternion: wxyz, rotation: rotvec`` declares the conventions). A ``.txt`` of stacked 4x4
  blocks (4 rows of 4 numbers per pose) is read in order;
- ``.npz``: one ``(N, 4, 4)`` array (with an ``ids``/``names``/``frames``/``stamps`` array or without: then in
  order), ``(N, 7)`` ``x y z q..`` rows (``(N, 6)`` with a declared rotation form), or one 4x4 array per id;
- ``.json``: a list of 4x4s, ``{id: 4x4}``, or a list of records ``{"id"|"name"|"frame"|"image"|"file": ..,
  "pose"|"matrix"|"T"|"transform": 4x4}`` or with ``x y z qx qy qz qw`` / ``position`` + ``orientation``;
  ``{"poses": ...}`` / ``{"frames": ...}`` around any of these;
- a folder: one 4x4 ``.txt``/``.npy``/``.json`` per pose, or an ``.npz`` with OpenCV's ``rvec``/``tvec``.

Ids follow :func:`darp.formats.pairing.frame_id`. Each pose must be rigid by :mod:`darp.geometry.rigid`'s
rule; rotations a little off are replaced by the nearest rotation with one warning naming the file.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from darp.errors import FormatError
from darp.formats.io_input import LIMITS, load_numpy
from darp.formats.pairing import frame_id, keyed
from darp.formats.poses import (
    PoseConventions,
    comment_declarations,
    is_number,
    pose_conventions,
    quat_pose,
    read_matrix_file,
    six_value_pose,
)
from darp.formats.text import read_utf8_text
from darp.geometry.rigid import orthonormalised, warn_orthonormalised

ID_KEYS = ("id", "ids", "name", "names", "frame", "frames", "frame_id", "image", "file", "filename", "stamp",
           "stamps", "timestamp", "key", "keys", "capture")
POSE_KEYS = ("pose", "matrix", "T", "transform", "transformation", "T_base_flange", "T_world_cam", "pose_matrix")


@dataclass
class PoseTable:
    """Poses (metres) by id, in the table's order; ``has_ids`` False when the rows pair by position."""

    source: Path
    poses: dict[str, np.ndarray]
    names: dict[str, str] = field(default_factory=dict)  # id -> the name as written (file, id cell)
    has_ids: bool = True
    quaternions: bool = False  # the rotations were read from quaternions (the other order is a likely mistake)
    conventions: PoseConventions = field(default_factory=PoseConventions)

    @property
    def order(self) -> list[str]:
        return list(self.poses)


def _finish(path: Path, raw: list[tuple[str, np.ndarray]], conv: PoseConventions, has_ids: bool,
            quaternions: bool = False, scaled: bool = False) -> PoseTable:
    if not raw:
        raise FormatError("no poses found", path)
    fixed: list[float] = []
    out: list[tuple[str, np.ndarray]] = []
    for name, M in raw:
        T = np.array(M, np.float64)
        if T.shape == (3, 4):
            T = np.vstack([T, [0, 0, 0, 1]])
        if T.shape != (4, 4):
            raise FormatError(f"pose {name!r}: expected a 4x4 matrix, got shape {T.shape}", path)
        if not scaled:
            T[:3, 3] *= conv.scale
        T, err = orthonormalised(T, f"pose {name!r}", path, error=FormatError)
        fixed.append(err)
        out.append((name, T))
    warn_orthonormalised(fixed, path)
    if has_ids:
        poses = keyed(out, path, "pose")
        names = {frame_id(n): n for n, _ in out}
    else:
        poses = {str(i): T for i, (_, T) in enumerate(out)}
        names = {str(i): n for i, (n, _) in enumerate(out)}
    return PoseTable(path, poses, names, has_ids, quaternions, conv)


QUATERNION_COLUMNS = ("qx", "qy", "qz", "qw", "q_x", "q_y", "q_z", "q_w")


def _rows_table(path: Path, conv: PoseConventions, id_column: str | None) -> PoseTable:
    lines = read_utf8_text(path, "a pose table").splitlines()
    conv = pose_conventions(comment_declarations(lines), path, conv)
    body = [s for s in (line.strip() for line in lines) if s and not s.startswith("#")]
    if not body:
        raise FormatError("no pose rows", path)
    delim = "," if "," in body[0] else None
    rows = list(csv.reader(io.StringIO("\n".join(body)))) if delim else [r.split() for r in body]
    rows = [[c.strip() for c in r if c.strip() != ""] for r in rows]
    header: list[str] | None = None
    if len(rows[0]) > 1 and not all(is_number(c) for c in rows[0][1:]):
        header = [h.lower() for h in rows[0]]
        rows = rows[1:]
    if not rows:
        raise FormatError("a header but no pose rows", path)
    # which column is the id
    idc: int | None = None
    if id_column is not None:
        if header is None or id_column.lower() not in header:
            raise FormatError(f"no column named {id_column!r} (header: {', '.join(header or ['none'])})", path)
        idc = header.index(id_column.lower())
    elif (rows and not is_number(rows[0][0])) or (header is not None and header[0] in ID_KEYS):
        idc = 0
    values = [[c for j, c in enumerate(r) if j != idc] for r in rows]
    names = [r[idc] if idc is not None else str(i) for i, r in enumerate(rows)]
    width = {len(v) for v in values}
    if len(width) != 1:
        raise FormatError(f"rows have different numbers of values ({sorted(width)}): one pose per row expected", path)
    n = width.pop()
    if n == 4 and idc is None and len(values) % 4 == 0:  # stacked 4x4 blocks
        M = np.array(values, np.float64).reshape(-1, 4, 4)
        return _finish(path, [(str(i), m) for i, m in enumerate(M)], conv, False)
    try:
        V = np.array(values, np.float64)
    except ValueError:
        raise FormatError("a value is not a number (is the id column not the first? give --id-column)",
                          path) from None
    quats = False
    if n in (16, 12):
        mats = [v.reshape(4 if n == 16 else 3, 4) for v in V]
    elif n == 7:
        hdr = [h for j, h in enumerate(header) if j != idc] if header is not None else []
        if len(hdr) == 7 and hdr[3] in ("qw", "w", "q_w", "rw"):
            conv = PoseConventions(conv.unit, "wxyz")
        elif len(hdr) == 7 and hdr[6] in ("qw", "w", "q_w", "rw"):
            conv = PoseConventions(conv.unit, "xyzw")
        for i, v in enumerate(V):
            q = np.linalg.norm(v[3:7])
            if not 0.9 < q < 1.1:
                raise FormatError(f"row {i + 1}: quaternion norm {q:.3f} is not 1 (is it a rotation vector or "
                                  "Euler angles?)", path)
        mats = [quat_pose(v, PoseConventions("m", conv.quaternion)) for v in V]
        quats = True
    elif n == 6:
        named = [h for j, h in enumerate(header or []) if j != idc and h in QUATERNION_COLUMNS]
        if named and not conv.rotation:  # x y z + 3 of a quaternion's 4: a column is missing, not a rotation vector
            raise FormatError(f"6 values per pose but the header names quaternion columns ({', '.join(named)}): "
                              "a quaternion needs 4 (x y z qx qy qz qw); is a column missing?", path)
        mats = [six_value_pose(v, conv, path) for v in V]
    else:
        raise FormatError(f"{n} values per pose: expected x y z + a quaternion (7) or a row-major 4x4 (16) / 3x4 (12)"
                          + (" after the id" if idc is not None else ""), path)
    return _finish(path, list(zip(names, mats, strict=True)), conv, idc is not None, quats)


def _npz_table(path: Path, conv: PoseConventions) -> PoseTable:
    loaded = load_numpy(path, "a pose .npz")
    arrays = {k: np.asarray(v) for k, v in loaded.items()} if isinstance(loaded, dict) else {"poses": loaded}
    ids_key = next((k for k in arrays if k.lower() in ID_KEYS), None)
    ids = [str(v) for v in arrays.pop(ids_key).reshape(-1)] if ids_key else None
    stacks = {k: a for k, a in arrays.items() if a.ndim == 3 and a.shape[1:] in ((4, 4), (3, 4))}
    rows7 = {k: a for k, a in arrays.items() if a.ndim == 2 and a.shape[1] in (6, 7)}
    if len(stacks) == 1 or (not stacks and len(rows7) == 1):
        A = next(iter(stacks.values())) if stacks else next(iter(rows7.values()))
        if ids is not None and len(ids) != len(A):
            raise FormatError(f"{len(ids)} ids for {len(A)} poses", path)
        names = ids or [str(i) for i in range(len(A))]
        if A.ndim == 3:
            return _finish(path, list(zip(names, A, strict=True)), conv, ids is not None)
        if A.shape[1] == 6:
            mats = [six_value_pose(v, conv, path) for v in A.astype(np.float64)]
        else:
            mats = [quat_pose(v, PoseConventions("m", conv.quaternion)) for v in A.astype(np.float64)]
        return _finish(path, list(zip(names, mats, strict=True)), conv, ids is not None, A.shape[1] == 7)
    per = [(k, a) for k, a in arrays.items() if a.shape in ((4, 4), (3, 4))]
    if per and len(per) == len(arrays):
        return _finish(path, per, conv, True)
    shapes = ", ".join(f"{k} {a.shape}" for k, a in arrays.items())
    raise FormatError(f"no pose table found (has {shapes}): expected one (N, 4, 4) array with an optional ids "
                      "array, (N, 7) x y z + quaternion rows, or one 4x4 array per id", path)


def _record_pose(rec: Any, conv: PoseConventions) -> tuple[np.ndarray, bool]:
    if isinstance(rec, dict):
        for k in POSE_KEYS:
            if k in rec:
                return _record_pose(rec[k], conv)
        pos = rec.get("position", rec.get("translation"))
        ori = rec.get("orientation", rec.get("rotation", rec.get("quaternion")))
        if pos is None and all(k in rec for k in ("x", "y", "z")):
            pos = [rec["x"], rec["y"], rec["z"]]
            ori = [rec[k] for k in ("qx", "qy", "qz", "qw")] if "qw" in rec else ori
            if ori is not None:
                return quat_pose([*pos, *ori], PoseConventions("m", "xyzw")), True
        if pos is not None and ori is not None:
            p = [pos[k] for k in ("x", "y", "z")] if isinstance(pos, dict) else list(pos)
            if isinstance(ori, dict):
                return quat_pose([*p, *(ori[k] for k in ("x", "y", "z", "w"))], PoseConventions("m", "xyzw")), True
            return quat_pose([*p, *ori], PoseConventions("m", conv.quaternion)), True
        raise KeyError(f"no pose in record (keys {', '.join(map(str, rec))})")
    return np.asarray(rec, np.float64), False


def _json_table(path: Path, conv: PoseConventions) -> PoseTable:
    try:
        d = json.loads(read_utf8_text(path, "a JSON file", limit=LIMITS["json"]))
    except json.JSONDecodeError as err:
        raise FormatError(f"cannot read the JSON ({err})", path) from None
    if isinstance(d, dict):
        d = next((d[k] for k in ("poses", "frames", "captures", "transforms") if k in d), d)
    raw: list[tuple[str, np.ndarray]] = []
    quats = False
    try:
        if isinstance(d, dict):
            has_ids = True
            for k, v in d.items():
                T, q = _record_pose(v, conv)
                raw.append((str(k), T))
                quats |= q
        else:
            has_ids = bool(d) and isinstance(d[0], dict) and any(k in d[0] for k in ID_KEYS)
            for i, rec in enumerate(d):
                name = next((str(rec[k]) for k in ID_KEYS if k in rec), str(i)) if isinstance(rec, dict) else str(i)
                T, q = _record_pose(rec, conv)
                raw.append((name, T))
                quats |= q
    except (KeyError, TypeError, ValueError) as err:
        raise FormatError(f"cannot read poses ({err})", path) from None
    return _finish(path, raw, conv, has_ids, quats)


def _folder_table(folder: Path, conv: PoseConventions) -> PoseTable:
    import cv2

    raw: list[tuple[str, np.ndarray]] = []
    for f in sorted(folder.iterdir()):
        if f.name.startswith(".") or not f.is_file():
            continue
        if f.suffix in (".txt", ".npy"):
            raw.append((f.name, read_matrix_file(f)))
        elif f.suffix == ".json":
            try:
                T, _ = _record_pose(json.loads(read_utf8_text(f, "a JSON file", limit=LIMITS["json"])), conv)
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
                raise FormatError(f"cannot read a pose ({err})", f) from None
            raw.append((f.name, T))
        elif f.suffix == ".npz":
            z = load_numpy(f, "a pose .npz")
            z = z if isinstance(z, dict) else {"T": z}
            if "rvec" in z and "tvec" in z:
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(np.asarray(z["rvec"], np.float64).reshape(3))[0]
                T[:3, 3] = np.asarray(z["tvec"], np.float64).reshape(3)
            else:
                key = next((k for k in z if np.shape(z[k]) in ((4, 4), (3, 4))), None)
                if key is None:
                    raise FormatError(f"expected a 4x4 array or rvec and tvec (has {', '.join(z)})", f)
                T = np.asarray(z[key], np.float64)
            raw.append((f.name, T))
    if not raw:
        raise FormatError("no pose files (.txt, .npy, .npz, .json)", folder)
    return _finish(folder, raw, conv, True)


def read_pose_table(path: str | Path, conv: PoseConventions | None = None, id_column: str | None = None
                    ) -> PoseTable:
    """Poses (metres) by id from any supported table or folder (module docstring)."""
    p = Path(path)
    conv = conv or PoseConventions()
    if p.is_dir():
        return _folder_table(p, conv)
    if not p.is_file():
        raise FormatError("pose file not found", p)
    if p.suffix == ".npz":
        return _npz_table(p, conv)
    if p.suffix == ".json":
        return _json_table(p, conv)
    if p.suffix == ".npy":
        A = np.asarray(load_numpy(p, "a pose .npy"))
        if A.ndim == 3:
            return _finish(p, [(str(i), a) for i, a in enumerate(A)], conv, False)
        return _finish(p, [(p.name, A)], conv, False)
    return _rows_table(p, conv, id_column)


def swapped_quaternion_table(table: PoseTable, id_column: str | None = None) -> PoseTable | None:
    """The same file read with the other quaternion order (None when it holds no quaternions)."""
    if not table.quaternions:
        return None
    c = table.conventions
    other = PoseConventions(c.unit, "wxyz" if c.quaternion == "xyzw" else "xyzw")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return read_pose_table(table.source, other, id_column)
        except FormatError:
            return None


__all__ = ["PoseTable", "read_pose_table", "swapped_quaternion_table"]
