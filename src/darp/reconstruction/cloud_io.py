"""PLY files for clouds and meshes: binary little-endian writing (atomic) and a small validating reader.

Written clouds carry ``x y z`` (float32, metres, world frame), optional ``nx ny nz`` (float32), optional
``red green blue`` (uchar) and any extra per-point scalar fields (e.g. ``n_frames``, ``arm_mask``), so
that a viewer (MeshLab, CloudCompare, Open3D) shows them and darp can read its own annotations back.
Meshes add ``element face`` with ``property list uchar int vertex_indices``. The reader understands
ascii and binary (either endianness) files with scalar vertex properties and triangle faces, which
covers darp's own files, Open3D's and trimesh's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from darp.errors import FormatError
from darp.formats.atomic import atomic_open
from darp.formats.io_input import LIMITS, read_input_bytes

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                 "f4": "float", "f8": "double"}


@dataclass
class PlyData:
    """The vertex properties and triangles of a PLY file."""

    vertex: dict[str, np.ndarray]  # property name -> (N,) array
    triangles: np.ndarray | None  # (T, 3) int64, None when the file has no faces
    comments: list[str] = field(default_factory=list)

    @property
    def points(self) -> np.ndarray:
        return np.column_stack([self.vertex[k] for k in ("x", "y", "z")]).astype(np.float64)

    @property
    def normals(self) -> np.ndarray | None:
        if all(k in self.vertex for k in ("nx", "ny", "nz")):
            return np.column_stack([self.vertex[k] for k in ("nx", "ny", "nz")]).astype(np.float64)
        return None

    @property
    def colours(self) -> np.ndarray | None:
        if all(k in self.vertex for k in ("red", "green", "blue")):
            return np.column_stack([self.vertex[k] for k in ("red", "green", "blue")]).astype(np.uint8)
        return None


# -- writing ---------------------------------------------------------------------------------------
def _vertex_records(points: np.ndarray, normals: np.ndarray | None, colours: np.ndarray | None,
                    fields: dict[str, np.ndarray] | None) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise FormatError(f"points must be (N, 3), got {points.shape}")
    n = points.shape[0]
    columns: list[tuple[str, np.ndarray]] = [(k, points[:, i].astype("<f4")) for i, k in enumerate("xyz")]
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (n, 3):
            raise FormatError(f"normals must be ({n}, 3), got {normals.shape}")
        columns += [(k, normals[:, i].astype("<f4")) for i, k in enumerate(("nx", "ny", "nz"))]
    if colours is not None:
        colours = np.asarray(colours)
        if colours.shape[0] != n or colours.ndim != 2 or colours.shape[1] < 3:
            raise FormatError(f"colours must be ({n}, 3), got {colours.shape}")
        columns += [(k, colours[:, i].astype("u1")) for i, k in enumerate(("red", "green", "blue"))]
    for name, values in (fields or {}).items():
        values = np.asarray(values)
        if values.shape != (n,) or values.dtype.str.lstrip("<>|=") not in _NUMPY_TO_PLY:
            raise FormatError(f"field {name!r} must be a ({n},) numeric array, got {values.shape} {values.dtype}")
        if not name.isidentifier():
            raise FormatError(f"field name {name!r} is not a valid PLY property name")
        columns.append((name, values.astype(values.dtype.newbyteorder("<"))))
    records = np.empty(n, dtype=[(name, values.dtype) for name, values in columns])
    for name, values in columns:
        records[name] = values
    return records


def _header(records: np.ndarray, n_faces: int | None, comments: list[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", "comment written by darp"]
    lines += [f"comment {c}" for c in comments]
    lines.append(f"element vertex {records.shape[0]}")
    for name in records.dtype.names or ():
        lines.append(f"property {_NUMPY_TO_PLY[records.dtype[name].str.lstrip('<>|=')]} {name}")
    if n_faces is not None:
        lines += [f"element face {n_faces}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_cloud_ply(path: str | Path, points: np.ndarray, *, normals: np.ndarray | None = None,
                    colours: np.ndarray | None = None, fields: dict[str, np.ndarray] | None = None,
                    comments: list[str] | None = None) -> Path:
    """Write a point cloud as binary PLY, atomically. Returns the path."""
    path = Path(path)
    try:
        records = _vertex_records(points, normals, colours, fields)
    except FormatError as err:
        raise FormatError(err.message, path) from None
    with atomic_open(path, "wb") as handle:
        handle.write(_header(records, None, comments or []))
        handle.write(records.tobytes())
    return path


def write_mesh_ply(path: str | Path, vertices: np.ndarray, triangles: np.ndarray, *,
                   normals: np.ndarray | None = None, colours: np.ndarray | None = None,
                   comments: list[str] | None = None) -> Path:
    """Write a triangle mesh as binary PLY, atomically. Returns the path."""
    path = Path(path)
    tri = np.asarray(triangles)
    try:
        records = _vertex_records(vertices, normals, colours, None)
        if tri.size and (tri.ndim != 2 or tri.shape[1] != 3 or tri.min() < 0 or tri.max() >= records.shape[0]):
            raise FormatError(f"triangles must be (T, 3) indices below {records.shape[0]}")
    except FormatError as err:
        raise FormatError(err.message, path) from None
    faces = np.empty(tri.shape[0] if tri.size else 0, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    if tri.size:
        faces["i"] = tri
    with atomic_open(path, "wb") as handle:
        handle.write(_header(records, faces.shape[0], comments or []))
        handle.write(records.tobytes())
        handle.write(faces.tobytes())
    return path


# -- reading ---------------------------------------------------------------------------------------
@dataclass
class _Element:
    name: str
    count: int
    scalars: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type)
    lists: list[tuple[str, str, str]] = field(default_factory=list)  # (name, count type, item type)


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], list[str], int]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise FormatError("not a PLY file (no 'ply' magic or no end_header)", path)
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements, comments = "", [], []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] in ("comment", "obj_info"):
                comments.append(line.partition(" ")[2])
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2])))
            elif words[0] == "property" and words[1] == "list":
                elements[-1].lists.append((words[4], _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            elif words[0] == "property":
                elements[-1].scalars.append((words[2], _PLY_TYPES[words[1]]))
        except (IndexError, KeyError, ValueError):
            raise FormatError(f"header line {number}: cannot parse {line!r}", path) from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FormatError(f"unsupported PLY format {fmt!r}", path)
    return fmt, elements, comments, body_start


def _read_binary(data: bytes, offset: int, elements: list[_Element], order: str,
                 path: Path) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    vertex: dict[str, np.ndarray] = {}
    triangles = None
    for el in elements:
        if el.lists and (el.scalars or len(el.lists) != 1 or el.name != "face"):
            raise FormatError(f"element {el.name!r}: only scalar properties or one face list are supported", path)
        if el.lists:  # faces: assume triangles, then check
            _, count_t, item_t = el.lists[0]
            dtype = np.dtype([("n", order + count_t), ("i", order + item_t, (3,))])
            size = dtype.itemsize * el.count
            if offset + size > len(data):
                raise FormatError(f"file ends inside element {el.name!r}", path)
            faces = np.frombuffer(data, dtype=dtype, count=el.count, offset=offset)
            if el.count and np.any(faces["n"] != 3):
                raise FormatError("only triangle faces are supported", path)
            triangles = faces["i"].astype(np.int64)
        else:
            dtype = np.dtype([(name, order + t) for name, t in el.scalars])
            size = dtype.itemsize * el.count
            if offset + size > len(data):
                raise FormatError(f"file ends inside element {el.name!r}", path)
            records = np.frombuffer(data, dtype=dtype, count=el.count, offset=offset)
            if el.name == "vertex":
                vertex = {name: records[name].astype(records.dtype[name].newbyteorder("=")) for name, _ in el.scalars}
        offset += size
    return vertex, triangles


def _read_ascii(data: bytes, offset: int, elements: list[_Element],
                path: Path) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    lines = data[offset:].decode("ascii", errors="replace").splitlines()
    vertex: dict[str, np.ndarray] = {}
    triangles = None
    pos = 0
    for el in elements:
        rows = lines[pos:pos + el.count]
        if len(rows) < el.count:
            raise FormatError(f"file ends inside element {el.name!r}", path)
        pos += el.count
        try:
            if el.lists:
                values = [list(map(int, r.split())) for r in rows]
                if any(v[0] != 3 or len(v) != 4 for v in values):
                    raise FormatError("only triangle faces are supported", path)
                triangles = np.array([v[1:] for v in values], np.int64).reshape(-1, 3)
            elif el.name == "vertex":
                table = np.array([r.split() for r in rows], dtype=np.float64).reshape(el.count, len(el.scalars))
                vertex = {name: table[:, i].astype(t) for i, (name, t) in enumerate(el.scalars)}
        except ValueError:
            raise FormatError(f"element {el.name!r}: bad numbers", path) from None
    return vertex, triangles


def read_ply(path: str | Path) -> PlyData:
    """Read a PLY file's vertex properties and triangles; FormatError names what is wrong."""
    path = Path(path)
    data = read_input_bytes(path, "a PLY file", limit=LIMITS["cloud"])
    fmt, elements, comments, offset = _parse_header(data, path)
    if fmt == "ascii":
        vertex, triangles = _read_ascii(data, offset, elements, path)
    else:
        vertex, triangles = _read_binary(data, offset, elements, "<" if fmt.endswith("little_endian") else ">", path)
    if not all(k in vertex for k in ("x", "y", "z")):
        raise FormatError("no vertex element with x, y, z", path)
    n = vertex["x"].shape[0]
    if triangles is not None and triangles.size and (triangles.min() < 0 or triangles.max() >= n):
        raise FormatError(f"face indices outside 0..{n - 1}", path)
    return PlyData(vertex=vertex, triangles=triangles, comments=comments)


def read_mesh_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (T, 3) int64) of a PLY mesh."""
    ply = read_ply(path)
    if ply.triangles is None:
        raise FormatError("the PLY file has no faces", path)
    return ply.points, ply.triangles


__all__ = ["PlyData", "read_mesh_ply", "read_ply", "write_cloud_ply", "write_mesh_ply"]
