"""Boolean-free mesh construction for the twin's objects: revolved profiles, swept tubes, hulls.

Everything here returns :class:`Piece` triangle soups (vertices, faces, optional UV) so that the
builders in :mod:`darp.twin.objects.shapes` can colour, texture and transform them before they become
named parts. Closed profiles are revolved so that the solid is watertight by construction: no
boolean operations (trimesh needs an extra engine for those) and no cracks to repair afterwards.

Profiles live in the (r, z) half-plane and are walked with the solid on the left (counterclockwise),
which makes every revolved face point outward. ``Piece.oriented_outward`` checks it anyway.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from darp.kinematics.transforms import matvec

CM = 0.01  # builders write their dimensions in centimetres, as the paper's table does


@dataclass
class Piece:
    """A triangle soup in metres; ``uv`` (one row per vertex, v up) only on textured pieces."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None

    def transformed(self, T: np.ndarray) -> Piece:
        """The piece moved by a 4x4 rigid or scaling transform (faces flipped if it mirrors)."""
        v = matvec(T[:3, :3], self.vertices) + T[:3, 3]  # no BLAS: object shapes independent of its kernel
        faces = self.faces[:, ::-1] if np.linalg.det(T[:3, :3]) < 0 else self.faces
        return Piece(v, faces.copy(), None if self.uv is None else self.uv.copy())

    def signed_volume(self) -> float:
        """Volume enclosed by the piece (positive when faces point outward; only meaningful if closed)."""
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def concat(pieces: Sequence[Piece]) -> Piece:
    """One piece from several (UV kept only if every piece has it)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces[:-1]])
    vertices = np.vstack([p.vertices for p in pieces])
    faces = np.vstack([p.faces + o for p, o in zip(pieces, offsets, strict=True)])
    uvs = [p.uv for p in pieces if p.uv is not None]
    uv = np.vstack(uvs) if len(uvs) == len(pieces) else None
    return Piece(vertices, faces, uv)


def arc(cr: float, cz: float, radius: float, deg0: float, deg1: float, n: int) -> list[tuple[float, float]]:
    """``n`` points on a circular arc in the (r, z) plane from angle deg0 to deg1, both ends included."""
    a = np.radians(np.linspace(deg0, deg1, n))
    return [(cr + radius * np.cos(t), cz + radius * np.sin(t)) for t in a]


def profile(runs: Sequence[tuple[str, Sequence[tuple[float, float]]]]) -> tuple[np.ndarray, list[str]]:
    """Join labelled runs of (r, z) points (cm) into one polyline (m) with a label per segment.

    The first point of the first run starts the line; every later point adds a segment labelled by
    its run, so a run's first segment joins it to the previous run.
    """
    points: list[tuple[float, float]] = []
    labels: list[str] = []
    for label, run in runs:
        for p in run:
            if points:
                labels.append(label)
            points.append((float(p[0]), float(p[1])))
    return np.asarray(points) * CM, labels


def revolve(
    points_rz: np.ndarray,
    labels: Sequence[str],
    *,
    sections: int = 72,
    y_scale: np.ndarray | None = None,
    theta0_rad: float = 0.0,
) -> dict[str, Piece]:
    """Revolve a labelled (r, z) polyline about the z axis; one piece per label, with UV.

    u runs once around (the seam column is duplicated so textures wrap cleanly), v is the arc length
    along the label's segments (0 at its first point, 1 at its last). ``y_scale`` (one factor per
    profile point) squeezes rings into ellipses, e.g. a bottle that is oval below and round at the cap.
    Triangles that collapse on the axis are dropped.
    """
    r, z = points_rz[:, 0], points_rz[:, 1]
    ys = np.ones_like(r) if y_scale is None else np.asarray(y_scale, dtype=float)
    theta = theta0_rad + 2.0 * np.pi * np.arange(sections + 1) / sections
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    cos_t[-1], sin_t[-1] = cos_t[0], sin_t[0]  # bit-identical seam so the seam merges exactly
    seg_len = np.hypot(np.diff(r), np.diff(z))
    pieces: dict[str, list[Piece]] = {}
    arc_done: dict[str, float] = {}
    total = {lab: float(seg_len[[k for k, lb in enumerate(labels) if lb == lab]].sum()) for lab in set(labels)}
    j = np.arange(sections)
    for k, label in enumerate(labels):
        rows = []
        for i in (k, k + 1):
            rows.append(np.column_stack([r[i] * cos_t, r[i] * sin_t * ys[i], np.full(sections + 1, z[i])]))
        vertices = np.vstack(rows)
        a, b, c, d = j, j + sections + 1, j + sections + 2, j + 1  # (k,j) (k+1,j) (k+1,j+1) (k,j+1)
        faces = np.vstack([np.column_stack([a, c, b]), np.column_stack([a, d, c])])
        v0 = arc_done.get(label, 0.0)
        arc_done[label] = v0 + float(seg_len[k])
        span = max(total[label], 1e-12)
        u = np.tile(np.arange(sections + 1) / sections, 2)
        v = np.repeat([v0 / span, arc_done[label] / span], sections + 1)
        piece = _drop_degenerate(Piece(vertices, faces, np.column_stack([u, v])))
        pieces.setdefault(label, []).append(piece)
    return {label: concat(group) for label, group in pieces.items()}


def arc_tube(
    centre_xz: tuple[float, float],
    radius: float,
    deg0: float,
    deg1: float,
    half_width: float,
    half_depth: float,
    *,
    n_path: int = 40,
    n_cross: int = 24,
) -> Piece:
    """A closed tube of elliptical cross-section swept along an arc in the xz plane (a mug handle).

    ``half_width`` is the section's half-size in the arc's plane, ``half_depth`` along y. Both ends
    are capped with fans, so the tube is watertight on its own.
    """
    t = np.radians(np.linspace(deg0, deg1, n_path))
    phi = 2.0 * np.pi * np.arange(n_cross) / n_cross
    cx, cz = centre_xz
    radial = np.column_stack([np.cos(t), np.zeros_like(t), np.sin(t)])  # in-plane normal of the path
    centres = np.column_stack([cx + radius * np.cos(t), np.zeros_like(t), cz + radius * np.sin(t)])
    ring = (
        centres[:, None, :]
        + half_width * np.cos(phi)[None, :, None] * radial[:, None, :]
        + half_depth * np.sin(phi)[None, :, None] * np.array([0.0, 1.0, 0.0])[None, None, :]
    )
    vertices = np.vstack([ring.reshape(-1, 3), centres[[0, -1]]])
    faces = []
    for i in range(n_path - 1):
        for k in range(n_cross):
            a, b = i * n_cross + k, i * n_cross + (k + 1) % n_cross
            faces += [[a, b, b + n_cross], [a, b + n_cross, a + n_cross]]
    start, end = len(vertices) - 2, len(vertices) - 1
    last = (n_path - 1) * n_cross
    for k in range(n_cross):
        faces.append([start, (k + 1) % n_cross, k])
        faces.append([end, last + k, last + (k + 1) % n_cross])
    return orient_outward(Piece(vertices, np.asarray(faces)))


def hull(points: np.ndarray) -> Piece:
    """Convex hull of points (m): a closed, outward-facing piece (rounded blocks, struts)."""
    mesh = trimesh.convex.convex_hull(np.asarray(points, dtype=float))
    return Piece(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def rounded_block(size_xyz_cm: Sequence[float], corner_cm: float, *, subdivisions: int = 2) -> Piece:
    """An axis-aligned box with rounded edges and corners, base on z=0, centred in x and y."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=corner_cm * CM)
    half = np.asarray(size_xyz_cm, dtype=float) * CM / 2.0 - corner_cm * CM
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    block = hull((corners[:, None, :] + np.asarray(sphere.vertices)[None, :, :]).reshape(-1, 3))
    block.vertices[:, 2] += size_xyz_cm[2] * CM / 2.0
    return block


def quads(corners: np.ndarray, quad_list: Sequence[tuple[int, int, int, int]],
          outward: Sequence[ArrayLike]) -> Piece:
    """Triangulate planar quads, each wound so that its normal points along its ``outward`` vector."""
    corners = np.asarray(corners, dtype=float)
    faces = []
    for (a, b, c, d), out in zip(quad_list, outward, strict=True):
        n = np.cross(corners[b] - corners[a], corners[c] - corners[a])
        faces += [[a, b, c], [a, c, d]] if np.dot(n, out) > 0 else [[a, c, b], [a, d, c]]
    return Piece(corners, np.asarray(faces))


def orient_outward(piece: Piece) -> Piece:
    """Flip a closed, consistently wound piece whose faces point inward."""
    if piece.signed_volume() < 0:
        return Piece(piece.vertices, piece.faces[:, ::-1].copy(), piece.uv)
    return piece


def planar_uv(vertices: np.ndarray, centre: np.ndarray, u_axis: np.ndarray, v_axis: np.ndarray,
              half_size: tuple[float, float]) -> np.ndarray:
    """UV by projecting onto a plane: (0.5, 0.5) at ``centre``, 0 and 1 at +-half_size (m)."""
    rel = vertices - centre
    return np.column_stack([0.5 + rel @ u_axis / (2 * half_size[0]), 0.5 + rel @ v_axis / (2 * half_size[1])])


def rotation(axis: str, deg: float) -> np.ndarray:
    """4x4 rotation about a principal axis."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    T = np.eye(4)
    i, k = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    T[i, i], T[i, k], T[k, i], T[k, k] = c, -s, s, c
    return T


def translation(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    """4x4 translation (m)."""
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def scaling(sx: float, sy: float, sz: float) -> np.ndarray:
    """4x4 axis scaling."""
    return np.diag([sx, sy, sz, 1.0])


def _drop_degenerate(piece: Piece) -> Piece:
    a, b, c = (piece.vertices[piece.faces[:, k]] for k in range(3))
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    keep = area2 > 1e-14
    return Piece(piece.vertices, piece.faces[keep], piece.uv)
